"""scripts/results_table.py: a row per scenario with its first seed's metrics and its seed count."""

from drift_sim.sweep import summarise

from conftest import load_script


def _run(e_y, spun=False):
    return {'spun': spun, 'spin_time_s': 7.2 if spun else None, 'supervisor_trip_s': None,
            'beta_rms_error_deg': 0.25, 'max_abs_e_y_m': e_y, 'max_abs_e_y_steady_m': e_y,
            'transition_time_s': 0.8, 'solve_time_ms_p50': 1.1, 'solve_time_ms_p99': 1.5,
            'real_time_factor': 6.0}


def test_a_row_shows_seed_zero_and_how_many_seeds_held():
    rt = load_script('results_table')
    runs = [(0, _run(1.08)), (1, _run(0.8)), (2, _run(30.0, spun=True))]
    runs[0][1].update(torque_std_Nm=555.4, torque_change_Nm=440.2)
    estimated = dict(_run(1.0), torque_std_Nm=154.6, torque_change_Nm=60.4)
    row = (('alternating_dry', 'alternating_dry', (), 'max lateral deviation 1 m'),
           runs[0][1], summarise(runs), estimated)
    text = rt.table([row], [0, 1, 2])
    header, _, line = text.splitlines()
    assert 'held, seeds 0-2' in header
    assert header.count('|') == line.count('|')
    cells = [c.strip() for c in line.split('|')[1:-1]]
    assert cells[0] == 'alternating_dry' and cells[1] == 'no' and cells[3] == '1.08 / 1.08'
    assert cells[10] == '555 / 440' and cells[11] == '155 / 60; 0.25'
    assert cells[-2] == '2/3 (0.80 / 0.94 / 1.08)' and cells[-1] == 'max lateral deviation 1 m'


def test_an_error_row_keeps_the_columns():
    rt = load_script('results_table')
    row = (('steady_dry', 'steady_dry', (), '-'), {'error': 'ParamError: x'},
           summarise([(0, {'error': 'ParamError: x'})]), None)
    header, _, line = rt.table([row], [0]).splitlines()
    assert header.count('|') == line.count('|') and 'error: ParamError: x' in line


def test_a_paper_spin_row_says_how_many_runs_left_the_drift():
    rt = load_script('results_table')
    trip = {'spun': False, 'supervisor_trip_s': 4.1, 'expect_spin': True}
    assert rt._held(summarise([(0, trip), (1, trip)])) == '0/2; left the drift as in the paper 2/2'


def test_a_run_without_steady_parts_or_estimated_run_shows_dashes():
    rt = load_script('results_table')
    assert rt._torque({'torque_std_Nm': None}) == '-'
    assert rt._estimated(None) == '-'
    assert rt._estimated({'error': 'ValueError: y'}) == 'error: ValueError: y'
