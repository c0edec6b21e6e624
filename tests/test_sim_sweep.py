"""Seed sweeps: run classification, summaries, and scripts/seed_sweep.py end to end."""
import json

import pytest

from drift_sim.sweep import (ERROR, HELD, LOST, SPUN, TRIPPED, format_summary, outcome, parse_seeds,
                             summarise)

from conftest import load_script


def _held(e_y, beta=0.2):
    return {'spun': False, 'supervisor_trip_s': None, 'max_abs_e_y_m': e_y,
            'beta_rms_error_deg': beta, 'transition_time_s': None}


def test_seed_lists_and_ranges():
    assert parse_seeds('0-4') == [0, 1, 2, 3, 4]
    assert parse_seeds('7, 2-3,3') == [2, 3, 7]
    for bad in ('', '4-1', 'a', '1-b', '-1'):
        with pytest.raises(ValueError, match='seeds'):
            parse_seeds(bad)


def test_a_spin_counts_before_a_trip_and_an_error_before_both():
    assert outcome(_held(0.5)) == HELD
    assert outcome({'spun': True, 'supervisor_trip_s': 5.0}) == SPUN
    assert outcome({'spun': False, 'supervisor_trip_s': 5.0}) == TRIPPED
    assert outcome({'error': 'ParamError: x'}) == ERROR


def test_a_run_far_off_its_reference_or_path_is_lost_not_held():
    assert outcome(_held(4.9, 1.9)) == HELD
    assert outcome(_held(24.4, 10.4)) == LOST
    assert outcome(_held(0.3, 2.5)) == LOST
    assert outcome(_held(7.3, 0.97)) == LOST
    assert outcome(_held(None, None)) == HELD   # too short a run for the windows


def test_summary_spreads_only_over_held_runs():
    runs = [(0, _held(0.8, 0.2)), (1, _held(1.2, 0.3)), (2, _held(1.0, 0.25)),
            (3, {'spun': True, 'spin_time_s': 6.5, 'supervisor_trip_s': 6.1,
                 'max_abs_e_y_m': 40.0, 'beta_rms_error_deg': 120.0})]
    s = summarise(runs)
    assert (s['runs'], s['held'], s['as_expected']) == (4, 3, 3)
    assert s['max_abs_e_y_m'] == {'min': 0.8, 'median': 1.0, 'max': 1.2}
    assert s['beta_rms_error_deg']['max'] == 0.3
    assert s['transition_time_s'] is None
    assert s['not_held'] == [{'seed': 3, 'outcome': SPUN, 'time_s': 6.5, 'error': None}]
    line = format_summary('alternating_dry', s)
    assert 'held 3/4' in line and '0.80 / 1.00 / 1.20 m' in line and 'seed 3 spun at 6.5 s' in line


def test_expected_spin_scenarios_count_a_stop_as_expected_and_an_error_never():
    stop = {'spun': False, 'supervisor_trip_s': 4.1, 'expect_spin': True}
    kept_going = dict(_held(0.5), expect_spin=True)
    left_the_path = dict(_held(30.0), expect_spin=True)
    s = summarise([(0, stop), (1, kept_going), (2, left_the_path),
                   (3, {'error': 'RuntimeError: solver'})])
    assert (s['held'], s['as_expected']) == (1, 2)
    assert [f['outcome'] for f in s['not_held']] == [TRIPPED, LOST, ERROR]


@pytest.mark.slow
def test_sweep_runs_every_seed_and_writes_the_summary(tmp_path, capsys):
    pytest.importorskip('drift_control.nmpc')
    out = tmp_path / 'sweep.json'
    sweep = load_script('seed_sweep')
    rc = sweep.main(['--scenario', 'drift_hold_dry', '--seeds', '0-1', '--jobs', '1',
                     '--set', 'duration=2.0', '--json', str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert [r['seed'] for r in data['runs']] == [0, 1]
    # the seed reaches the plant: two seeds, two friction fields and noise draws
    assert [r['metrics']['seed'] for r in data['runs']] == [0, 1]
    assert data['runs'][0]['metrics'] != data['runs'][1]['metrics']
    assert data['summaries']['drift_hold_dry']['runs'] == 2
    assert 'drift_hold_dry: held' in capsys.readouterr().out


def test_a_bad_scenario_is_an_error_row_and_a_failing_exit():
    sweep = load_script('seed_sweep')
    rc = sweep.main(['--scenario', 'no_such_scenario', '--seeds', '0', '--jobs', '1'])
    assert rc == 1


def test_torque_smoothness_per_control_period_in_the_steady_windows():
    import numpy as np
    from drift_sim.metrics import torque_smoothness
    t = np.round(np.arange(0.0, 10.0, 0.01), 9)
    T = np.where((np.arange(len(t)) // 2) % 2 == 0, 1000.0, 1100.0)   # +-50 Nm every 20 ms
    std, change = torque_smoothness(t, T, [(2.0, 4.0), (6.0, 8.0)])
    assert std == pytest.approx(50.0) and change == pytest.approx(100.0)
    T[(t >= 4.0) & (t < 6.0)] = 5000.0   # outside the windows: not counted
    assert torque_smoothness(t, T, [(2.0, 4.0), (6.0, 8.0)]) == pytest.approx((std, change))
    assert all(np.isnan(torque_smoothness(t, T, [])))


def test_a_job_with_sensors_has_its_own_key_and_the_others_keep_theirs():
    from drift_sim.campaign import Job
    plain = Job('steady_dry', 'm3_competition', 0)
    # the key since it holds the configuration's digest (empty here): sensors left it alone
    assert plain.key == 'e3c7be5ff1d068be'
    sensed = Job('steady_dry', 'm3_competition', 0, sensors='realistic', estimator='ekf')
    assert sensed.key != plain.key and sensed.row()['sensors'] == 'realistic'
    assert '--sensors realistic --estimator ekf' in sensed.replay_command()
    assert 'sensors' not in plain.row()
