"""Real-time pacing: a late timer runs the cycles it missed, a long stall is dropped and counted."""
import pytest

from drift_control.pacing import Pacer


def test_on_time_ticks_run_one_cycle_each_even_with_jitter():
    pacer = Pacer(0.01)
    jitter = (0.0, 0.003, -0.002, 0.004, -0.004, 0.001)
    runs = [pacer.due(0.01 * k + jitter[k % len(jitter)]) for k in range(600)]
    assert runs == [1] * 600
    assert pacer.late == pacer.skipped == 0


def test_a_late_tick_catches_up_so_the_rate_holds():
    pacer = Pacer(0.01)
    ticks = [0.01 * k for k in range(100) if k % 14 != 13]   # rcl skipped every 14th tick
    assert sum(pacer.due(t) for t in ticks) == 100   # cycles 0..99 ran by the last, t = 0.99 s
    assert pacer.late > 0 and pacer.skipped == 0


def test_a_stall_longer_than_the_burst_is_dropped_and_counted():
    pacer = Pacer(0.01, max_burst=5)
    assert pacer.due(0.0) == 1
    assert pacer.due(0.2) == 5               # 20 cycles due: 5 run, 15 dropped
    assert pacer.skipped == 15
    assert pacer.due(0.21) == 1              # back on the grid after the stall


@pytest.mark.parametrize('period, burst', [(0.0, 5), (-0.01, 5), (0.01, 0)])
def test_bad_settings_are_refused(period, burst):
    with pytest.raises(ValueError, match='Pacer'):
        Pacer(period, burst)
