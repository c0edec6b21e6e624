"""scripts/simulate.py end to end: the one-process closed loop runs and reports its metrics."""
import json
import math

import pytest

from conftest import load_script


@pytest.mark.slow
def test_nmpc_closed_loop_runs_and_writes_the_metrics(tmp_path):
    pytest.importorskip('drift_control.nmpc')
    out = tmp_path / 'metrics.json'
    rc = load_script('simulate').main(['--scenario', 'steady_dry', '--set', 'duration=3.0',
                                       '--quiet', '--json', str(out),
                                       '--trace', str(tmp_path / 'trace.npz')])
    assert rc == 0
    m = json.loads(out.read_text())
    for key in ('beta_rms_error_deg', 'max_abs_e_y_m', 'spun', 'time_in_drift_s',
                'solve_time_ms_p50', 'solve_time_ms_p99', 'real_time_factor'):
        assert key in m
    assert m['sim_duration_s'] == pytest.approx(2.99, abs=0.011)
    assert 0.0 < m['solve_time_ms_p50'] <= m['solve_time_ms_p99']
    assert m['commands_lost'] == 0 and math.isfinite(m['real_time_factor'])


def test_a_wrong_override_is_reported_not_raised(capsys):
    rc = load_script('simulate').main(['--scenario', 'steady_dry', '--set', 'plant.lsd.lockng=1',
                           '--controller', 'feedforward', '--quiet'])
    assert rc == 2
    assert 'lockng' in capsys.readouterr().err
