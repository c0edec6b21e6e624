"""Issue 18's targets on the nominal car, closed loop: the courses beyond the paper's two.

Seed 0 of the default car's nominal plant (the README's courses table); over randomized plants
these courses are judged by `scripts/campaign.py`, not here. A module of its own, so that the
suite's workers run it beside ``test_acceptance.py``.
"""

import pytest

from drift_sim.closed_loop import run_closed_loop

pytestmark = pytest.mark.slow


def no_spin_no_trip(m):
    assert not m['spun'], f"spun at {m['spin_time_s']} s"
    assert m['supervisor_trip_s'] is None, f"supervisor tripped at {m['supervisor_trip_s']} s"


@pytest.mark.parametrize('scenario', ['figure8_dry', 'figure8_wet'])
def test_figure8_stays_within_a_metre_of_the_path(scenario):
    """Three laps, a flip at every crossing: max |e_y| after the entry <= 1 m."""
    m, _ = run_closed_loop(scenario, ())
    no_spin_no_trip(m)
    assert m['beta_rms_error_deg'] < 2.0
    assert m['max_abs_e_y_m'] <= 1.0
    assert m['transition_time_s'] < 2.0


@pytest.mark.parametrize('scenario', ['sideslip_profile_dry', 'sideslip_profile_wet'])
def test_a_sideslip_profile_along_the_path_is_tracked(scenario):
    """20 -> 35 -> 20 deg along each lap: sideslip RMS error <= 1.5 deg."""
    m, _ = run_closed_loop(scenario, ())
    no_spin_no_trip(m)
    assert m['beta_rms_error_deg'] <= 1.5
    assert m['max_abs_e_y_m'] <= 1.5


@pytest.mark.parametrize('scenario', ['exit_dry', 'exit_wet'])
def test_the_exit_reaches_grip_within_three_seconds(scenario):
    """From the drift back to grip on a straight: sideslip < 3 deg, yaw rate settled."""
    m, _ = run_closed_loop(scenario, ())
    no_spin_no_trip(m)
    assert m['exit_time_s'] is not None, 'never back to grip'
    assert m['exit_time_s'] <= 3.0
