"""The stack assembly: one load of a run's configuration, the cross-file rules, the vehicle key."""
import json
import re
import shutil
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import load_script
from drift_control.assembly import load_setup, map_file, maps_dir, narrow_to_map
from drift_control.params import ParamError, config_dir, default_vehicle, vehicle_names
from drift_control.signals import Mode


@pytest.fixture
def cfg(tmp_path):
    """A copy of config/ whose maps (defaults.yaml: ../maps) are the checkout's, linked."""
    shutil.copytree(config_dir(), tmp_path / 'config')
    (tmp_path / 'maps').symlink_to(maps_dir())
    return tmp_path / 'config'


def _edit(path, pattern, replacement):
    text = path.read_text()
    new = re.sub(pattern, replacement, text, count=1, flags=re.M)
    assert new != text, pattern
    path.write_text(new)


def test_every_shipped_vehicle_assembles_with_its_maps():
    assert default_vehicle() in vehicle_names() and len(vehicle_names()) >= 2
    for name in vehicle_names():
        for scenario in ('steady_dry', 'steady_wet'):
            setup = load_setup(scenario=scenario, vehicle=name)
            assert setup.vehicle_name == name and setup.eqmap.meta['vehicle'] == name
            assert setup.surface.name == setup.scenario.surface.name
            assert setup.reference.radius_min >= float(setup.eqmap.radius[0])


def test_the_vehicle_comes_from_the_command_line_the_scenario_or_the_default(cfg):
    assert load_setup(cfg, 'steady_dry', with_map=False).vehicle_name == default_vehicle()
    other = next(n for n in vehicle_names() if n != default_vehicle())
    (cfg / 'scenarios' / 'mine.yaml').write_text(
        (cfg / 'scenarios' / 'steady_dry.yaml').read_text() + f'vehicle: {other}\n')
    assert load_setup(cfg, 'mine', with_map=False).vehicle_name == other
    assert load_setup(cfg, 'mine', default_vehicle(), with_map=False).vehicle_name == \
        default_vehicle(), '--vehicle wins over the scenario'
    assert load_setup(cfg, 'steady_dry', overrides=[f'vehicle={other}'],
                      with_map=False).vehicle_name == other


def test_a_scenario_s_mode_and_surface_reach_the_controller():
    setup = load_setup(scenario='semi_auto_wet', with_map=False)
    assert setup.mode == Mode.TORQUE_ONLY and setup.surface.name == 'wet'
    assert load_setup(with_map=False).mode == Mode.FULL


def test_the_entry_s_course_yaw_only_where_the_nmpc_steers(cfg):
    """The course-yaw correction in the entry ramp asks a faster rotation: in full mode of
    the steering and torque, with the driver steering of the torque alone, so it is off there."""
    ref = cfg / 'reference.yaml'   # on, whatever the shipped default
    ref.write_text(re.sub(r'^  course_yaw_entry: \w+', '  course_yaw_entry: true', ref.read_text(),
                          flags=re.M))
    full, torque_only = load_setup(cfg, 'steady_dry'), load_setup(cfg, 'semi_auto_dry')
    assert full.reference.course_yaw_entry and torque_only.reference.course_yaw_entry
    assert full.build_selector().p.course_yaw_entry
    assert not torque_only.build_selector().p.course_yaw_entry


def test_the_speed_rise_leaving_a_drift_scales_with_the_named_surface_s_friction():
    dry, wet = load_setup(scenario='exit_dry'), load_setup(scenario='exit_wet')
    assert dry.reference.speed_rise_max == wet.reference.speed_rise_max > 0.0
    assert dry.build_selector().p.speed_rise_max == dry.reference.speed_rise_max   # mu 1
    assert wet.build_selector().p.speed_rise_max == pytest.approx(
        wet.reference.speed_rise_max * wet.surface.mu)
    assert wet.surface.mu < 1.0


def test_the_drift_s_speed_rise_and_fall_scale_with_the_named_surface_s_friction():
    wet = load_setup(scenario='steady_wet')
    wet = replace(wet, reference=replace(wet.reference, drift_speed_rise=1.0,
                                         drift_speed_fall=1.5))
    p = wet.build_selector().p
    assert p.drift_speed_rise == pytest.approx(1.0 * wet.surface.mu)
    assert p.drift_speed_fall == pytest.approx(1.5 * wet.surface.mu)


def test_unknown_vehicle_is_one_line_naming_the_known_ones():
    with pytest.raises(ParamError, match=r"vehicle 'nope'.*known vehicles: .*m3_competition"):
        load_setup(scenario='steady_dry', vehicle='nope')


@pytest.mark.parametrize('pattern, replacement, match', [
    (r'^m: .*$', '', r"missing key\(s\) \['m'\]"),
    (r'^I_z: .*$', 'I_z: -3000.0', r'vehicle\.I_z: must be positive'),
    (r'^(\s+)pKx1: .*$', r'\1pKx1: fast', r'rear_tyre\.pKx1: expected a number'),
])
def test_a_bad_vehicle_yaml_names_the_key(cfg, pattern, replacement, match):
    _edit(cfg / 'vehicle' / f'{default_vehicle()}.yaml', pattern, replacement)
    with pytest.raises(ParamError, match=match):
        load_setup(cfg, 'steady_dry')


def test_a_map_built_for_other_parameters_names_the_rebuild_command(cfg, tmp_path):
    (tmp_path / 'maps').unlink()
    shutil.copytree(maps_dir(), tmp_path / 'maps')
    _edit(cfg / 'vehicle' / f'{default_vehicle()}.yaml', r'^I_z: .*$', 'I_z: 3100.0')
    with pytest.raises(ParamError) as err:
        load_setup(cfg, 'steady_dry')
    text = str(err.value)
    assert 'stale' in text and '\n' not in text
    assert f'scripts/build_maps.py --vehicle {default_vehicle()} --surface dry --config-dir' in text


def test_a_map_of_another_vehicle_is_refused(cfg, tmp_path):
    (tmp_path / 'maps').unlink()
    shutil.copytree(maps_dir(), tmp_path / 'maps')
    meta = map_file(default_vehicle(), 'dry', cfg).with_suffix('.json')
    data = json.loads(meta.read_text())
    meta.write_text(json.dumps({**data, 'vehicle': 'someone_else'}))
    with pytest.raises(ParamError, match="built for vehicle 'someone_else'"):
        load_setup(cfg, 'steady_dry')


def test_a_missing_map_names_the_build_command(cfg, tmp_path):
    (tmp_path / 'maps').unlink()
    with pytest.raises(ParamError, match='not found.*rebuild: scripts/build_maps.py --vehicle'):
        load_setup(cfg, 'steady_dry')


def test_cross_file_rules_are_checked_once_here(cfg):
    _edit(cfg / 'reference.yaml', r'horizon_dt: [0-9.]+', 'horizon_dt: 0.05')
    with pytest.raises(ParamError, match='reference.horizon_dt'):
        load_setup(cfg, 'steady_dry', with_map=False)
    _edit(cfg / 'reference.yaml', r'horizon_dt: [0-9.]+', 'horizon_dt: 0.03')
    _edit(cfg / 'reference.yaml', r'horizon_steps: [0-9]+', 'horizon_steps: 10')
    with pytest.raises(ParamError, match=r'reference.horizon_steps: 10 .* N = 25'):
        load_setup(cfg, 'steady_dry', with_map=False)


def test_a_path_tighter_than_the_map_is_refused(cfg):
    (cfg / 'paths' / 'tight.yaml').write_text('path: {type: circle, radius: 6.0}\n')
    _edit(cfg / 'scenarios' / 'steady_dry.yaml', r'^path: .*$', 'path: tight')
    with pytest.raises(ParamError, match=r"tightest radius 6.00 m is below the map's smallest"):
        load_setup(cfg, 'steady_dry')


def test_the_flip_radius_is_narrowed_with_the_map_s_radii():
    """A map reaching less far than ``flip_radius_max`` caps the flip at its widest radius."""
    setup = load_setup(scenario='alternating_dry')
    ref = replace(setup.reference, radius_max=40.0, flip_radius_max=30.0)
    grid = SimpleNamespace(radius=np.array([8.0, 15.0, 25.0]))
    narrowed = narrow_to_map(ref, grid, setup.path)
    assert (narrowed.radius_max, narrowed.flip_radius_max) == (25.0, 25.0)
    assert narrow_to_map(replace(ref, flip_radius_max=0.0), grid, setup.path).flip_radius_max == 0


def test_entry_points_give_one_line_for_an_unknown_vehicle(capsys):
    for script, argv in (('simulate', ['--scenario', 'steady_dry', '--vehicle', 'nope']),
                         ('build_maps', ['--vehicle', 'nope']),
                         ('run_stack', ['--vehicle', 'nope', '--duration', '1'])):
        assert load_script(script).main(argv) == 2, script
        err = capsys.readouterr().err.strip()
        assert "vehicle 'nope'" in err and len(err.splitlines()) == 1, (script, err)
