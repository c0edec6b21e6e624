"""CycleWatch: a cycle's longest gap, split into its own running, waiting for a CPU and steal."""
import os
import time

import pytest

from drift_control.cycle_watch import CycleWatch

linux = pytest.mark.skipif(not os.path.exists('/proc/thread-self/schedstat'),
                           reason='no per-thread scheduler statistics here')


def test_the_longest_gap_is_kept_until_taken():
    watch = CycleWatch()
    for now in (0.0, 0.01, 0.05, 0.06):
        watch.tick(now)
    assert watch.take()['gap'] == pytest.approx(0.04)
    assert watch.take()['gap'] == 0.0, 'starts over'
    watch.tick(0.08)
    assert watch.take()['gap'] == pytest.approx(0.02), 'the gap since the last tick'


@linux
def test_a_sleeping_gap_is_not_running_and_a_busy_one_is():
    watch = CycleWatch()
    watch.tick(time.monotonic())
    time.sleep(0.05)
    watch.tick(time.monotonic())
    asleep = watch.take()
    assert asleep['gap'] >= 0.05 and asleep['ran'] < 0.5 * asleep['gap'], asleep
    end = time.monotonic() + 0.05
    while time.monotonic() < end:
        pass
    watch.tick(time.monotonic())
    busy = watch.take()
    # on a CPU, or kept from one by other tasks or the machine: never asleep
    assert busy['ran'] + busy['waited'] + busy['stolen'] > 0.5 * busy['gap'], busy
    assert all(0.0 <= busy[k] <= busy['gap'] + 0.011 for k in ('ran', 'waited', 'stolen')), busy
