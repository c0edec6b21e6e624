"""scripts/simulate.py end to end: the one-process closed loop runs and reports its metrics."""
import json
import math
import re
import shutil

import pytest

from conftest import load_script
from drift_control.assembly import maps_dir
from drift_control.params import ParamError, config_dir
from drift_sim.closed_loop import run_closed_loop


@pytest.mark.slow
def test_nmpc_closed_loop_runs_and_writes_the_metrics(tmp_path, capsys):
    pytest.importorskip('drift_control.nmpc')
    out = tmp_path / 'metrics.json'
    rc = load_script('simulate').main(['--scenario', 'steady_dry', '--set', 'duration=3.0',
                                       '--quiet', '--json', str(out),
                                       '--trace', str(tmp_path / 'trace.npz'),
                                       '--plan-at', '2.5', '--plan-at', '1.01',
                                       '--plan-at', '9'])
    assert rc == 0
    m = json.loads(out.read_text())
    for key in ('beta_rms_error_deg', 'max_abs_e_y_m', 'spun', 'time_in_drift_s',
                'solve_time_ms_p50', 'solve_time_ms_p99', 'real_time_factor'):
        assert key in m
    assert m['sim_duration_s'] == pytest.approx(2.99, abs=0.011)
    assert 0.0 < m['solve_time_ms_p50'] <= m['solve_time_ms_p99']
    assert m['commands_lost'] == 0 and math.isfinite(m['real_time_factor'])
    # --plan-at: the solve nearest each time (sorted), its plan starting at the measured state
    plans = m['plans']
    assert [p['t'] for p in plans] == pytest.approx([1.0, 2.5])
    for p in plans:
        assert len(p['states']['V']) == 26 and len(p['inputs']['T_R']) == 25
        assert len(p['reference']['beta']) == 26
        # the plan's first state is the warm start plus the QP's step to the measured one
        assert p['states']['V'][0] == pytest.approx(p['measured']['V'], rel=1e-9)
    err = capsys.readouterr().err
    assert 'NMPC plan at t = 1.00 s' in err and 'NMPC plan at t = 2.50 s' in err
    assert 'no NMPC solve at 9 s (the run ended at 2.99 s)' in err


def test_a_bad_plan_time_is_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as exit_:
        load_script('simulate').main(['--scenario', 'steady_dry', '--plan-at', 'soon'])
    assert exit_.value.code == 2
    assert "expected seconds >= 0, got 'soon'" in capsys.readouterr().err


def test_a_wrong_override_is_reported_not_raised(capsys):
    rc = load_script('simulate').main(['--scenario', 'steady_dry', '--set', 'plant.lsd.lockng=1',
                           '--controller', 'feedforward', '--quiet'])
    assert rc == 2
    assert 'lockng' in capsys.readouterr().err


def test_reference_horizon_spaced_unlike_the_nmpc_stages_is_refused(tmp_path):
    """Checked where both configurations meet, before the first step."""
    cfg = tmp_path / 'config'
    shutil.copytree(config_dir(), cfg)
    (tmp_path / 'maps').symlink_to(maps_dir())
    text = (cfg / 'reference.yaml').read_text()
    (cfg / 'reference.yaml').write_text(re.sub(r'horizon_dt: [0-9.]+', 'horizon_dt: 0.05', text))
    with pytest.raises(ParamError, match='reference.horizon_dt'):
        run_closed_loop('steady_dry', config=cfg)
