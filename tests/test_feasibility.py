"""Infeasible references are refused before the car moves, with where and why."""
from types import SimpleNamespace

import pytest

from drift_control.assembly import load_setup
from drift_control.feasibility import equilibrium_problem, reference_problems
from drift_control.ocp import effective_bounds
from drift_control.params import ParamError, config_dir, vehicle_names
from drift_control.scenario import control_scenario_names

CIRCLE = (config_dir() / 'paths' / 'circle_left_15.yaml').read_text()


def _problems(setup):
    return reference_problems(setup.path, setup.eqmap, effective_bounds(setup.vehicle, setup.nmpc),
                              setup.reference.radius_min, setup.reference.radius_max)


@pytest.mark.parametrize('vehicle', vehicle_names())
def test_every_shipped_scenario_asks_for_drifts_the_car_can_hold(vehicle):
    for name in control_scenario_names():
        setup = load_setup(scenario=name, vehicle=vehicle)
        assert _problems(setup) == [], (vehicle, name)
        setup.check_reference()


@pytest.mark.parametrize('beta_deg, refused', [(30.0, False), (40.0, True), (45.0, True)])
def test_a_sideslip_beyond_the_maps_edge_on_the_15_m_circle_is_refused(tmp_path, beta_deg,
                                                                       refused):
    path = tmp_path / 'circle.yaml'
    path.write_text(CIRCLE.replace('beta_deg: 30.0', f'beta_deg: {beta_deg}'))
    setup = load_setup(scenario='steady_dry', vehicle='m3_competition', path_file=str(path))
    problems = _problems(setup)
    assert bool(problems) == refused
    if not refused:
        return
    worst = problems[-1]
    assert worst.beta_deg == pytest.approx(beta_deg) and worst.radius == pytest.approx(15.0)
    assert 'no equilibrium above' in worst.why and 'steering lock' in worst.why
    # it starts once the entry ramp passes the map's edge, and lasts to the end of the lap
    assert 20.0 < worst.start < 65.0 and worst.end > setup.path.length
    with pytest.raises(ParamError, match=r'reference infeasible: .*m3_competition on dry') as err:
        setup.check_reference()
    assert '\n' not in str(err.value) and '--allow-infeasible' in str(err.value)


def test_equilibrium_problem_is_the_nmpcs_rule():
    bounds = SimpleNamespace(delta_max=0.5, T_R_min=-2000.0, T_R_max=6000.0)
    eq = SimpleNamespace(delta=-0.3, T_R=2000.0, V=9.0)
    assert equilibrium_problem(eq, bounds) is None
    assert 'beyond the 0.500 rad lock' in equilibrium_problem(
        SimpleNamespace(delta=-0.6, T_R=2000.0, V=9.0), bounds)
    assert 'outside [-2000, 6000] Nm' in equilibrium_problem(
        SimpleNamespace(delta=-0.3, T_R=7000.0, V=9.0), bounds)
    assert 'speed' in equilibrium_problem(SimpleNamespace(delta=0.0, T_R=0.0, V=0.0), bounds)


def test_simulate_refuses_before_the_run_in_one_line(tmp_path, capsys):
    from conftest import load_script
    scenario = (config_dir() / 'scenarios' / 'steady_dry.yaml').read_text()
    circle = tmp_path / 'c45.yaml'
    circle.write_text(CIRCLE.replace('beta_deg: 30.0', 'beta_deg: 45.0'))
    path = tmp_path / 'steady45.yaml'
    path.write_text(scenario.replace('path: circle_left_15', f'path: {circle}'))
    assert load_script('simulate').main(['--scenario', str(path), '--quiet']) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('simulate: reference infeasible') and len(err.splitlines()) == 1


def test_the_selector_keeps_its_sideslip_reference_holdable(tmp_path, monkeypatch):
    """Asked for more sideslip than the car can hold (45 deg on the 15 m circle), the selector
    asks for the largest the map holds there: a reference the NMPC accepts, with a warning."""
    import math

    from drift_control.feasibility import sideslip_limit
    from drift_control.signals import VehicleState
    path = tmp_path / 'circle.yaml'
    path.write_text(CIRCLE.replace('beta_deg: 30.0', 'beta_deg: 45.0'))
    setup = load_setup(scenario='steady_dry', vehicle='m3_competition', path_file=str(path))
    bounds = effective_bounds(setup.vehicle, setup.nmpc)
    limit = sideslip_limit(setup.eqmap, bounds)
    assert math.radians(30.0) < limit(15.0) < math.radians(45.0)
    assert limit(15.5) == min(limit(15.0), limit(16.0))
    import drift_control.reference as reference
    warnings = []   # recorded here: other tests may route the package's logging elsewhere
    monkeypatch.setattr(reference._log, 'warning', lambda msg, *args: warnings.append(msg % args))
    selector = setup.build_selector()
    selector.reset(s_hint=80.0)
    s = 80.0    # past the entry ramp, on the circle (centre (0, 15), start heading +x)
    angle = s / 15.0
    x, y = 15.0 * math.sin(angle), 15.0 - 15.0 * math.cos(angle)
    state = VehicleState(stamp=0.0, V=9.0, beta=math.radians(-30.0), r=0.6, x=x, y=y,
                         yaw=angle + math.radians(30.0))
    ref = selector.select(state)
    assert abs(ref.target.beta) == pytest.approx(limit(1.0 / abs(ref.curvature_cmd)), abs=1e-9)
    assert all(equilibrium_problem(e, bounds) is None for e in (ref.target, *ref.horizon))
    assert any('limited to' in w for w in warnings)


def test_an_identification_manoeuvre_is_not_a_controller_run():
    from drift_control.scenario import scenario_names
    manoeuvres = set(scenario_names()) - set(control_scenario_names())
    assert 'sysid_dry' in manoeuvres and 'steady_dry' not in manoeuvres
    with pytest.raises(ParamError, match='sysid_drive.py --scenario sysid_dry'):
        load_setup(scenario='sysid_dry')
