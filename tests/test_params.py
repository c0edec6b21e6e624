"""Parameter files: the shipped ones load; a wrong, missing or out-of-range key names itself."""
import copy
import re

import pytest
import yaml

from drift_control.params import (ParamError, VehicleParams, config_dir, from_dict, load_surface,
                                  load_vehicle, load_yaml, params_hash, split_override)


@pytest.fixture()
def raw():
    with open(config_dir() / 'vehicle' / 'm3_competition.yaml') as fh:
        return yaml.safe_load(fh)


def test_shipped_vehicle_and_surfaces_load():
    vp = load_vehicle()
    assert vp.a + vp.b == pytest.approx(vp.L)
    assert load_surface('dry').mu > load_surface('wet').mu


@pytest.mark.parametrize('mutate, message', [
    (lambda r: r.pop('I_z'), "missing key(s) ['I_z']"),
    (lambda r: r.update(I_zz=1.0), "unknown key(s) ['I_zz']"),
    (lambda r: r['rear_tyre'].update(pKx1='stiff'), 'rear_tyre.pKx1: expected a number'),
    (lambda r: r['front_tyre']['lateral'].pop('B'), "front_tyre.lateral: missing key(s) ['B']"),
    (lambda r: r.update(m=-5.0), 'vehicle.m: must be positive'),
    (lambda r: r['limits'].update(T_R_min=9000.0), 'T_R_min must be below T_R_max'),
    (lambda r: r.update(a=float('nan')), 'a: must be finite'),
    (lambda r: r.update(torque_lag=-0.1), 'vehicle.torque_lag: must be >= 0'),
    (lambda r: r.update(torque_lag='slow'), 'torque_lag: expected a number'),
])
def test_bad_vehicle_file_names_the_key(raw, mutate, message):
    bad = copy.deepcopy(raw)
    mutate(bad)
    with pytest.raises(ParamError, match=re.escape(message)):
        from_dict(VehicleParams, bad, 'vehicle')


def test_missing_file_and_unknown_surface_are_clear_errors(tmp_path):
    with pytest.raises(ParamError, match='not found'):
        load_vehicle(tmp_path / 'nope.yaml')
    (tmp_path / 'broken.yaml').write_text('m: [1, 2\n')
    with pytest.raises(ParamError, match='not valid YAML'):
        load_vehicle(tmp_path / 'broken.yaml')
    with pytest.raises(ParamError, match="no surface 'ice'"):
        load_surface('ice')


def test_parameter_hash_tracks_values(raw):
    a = from_dict(VehicleParams, raw, 'vehicle')
    raw['m'] = raw['m'] + 1.0
    b = from_dict(VehicleParams, raw, 'vehicle')
    assert params_hash(a) == params_hash(load_vehicle())
    assert params_hash(a) != params_hash(b)
    raw['torque_lag'] = 0.14   # an identified car's own powertrain lag is part of its file
    assert from_dict(VehicleParams, raw, 'vehicle').torque_lag == 0.14
    assert params_hash(from_dict(VehicleParams, raw, 'vehicle')) != params_hash(b)


def test_a_vehicle_without_its_own_lag_keeps_the_nmpc_one_and_its_map():
    from drift_control.ocp import NmpcParams, for_vehicle
    vp = load_vehicle()
    assert vp.torque_lag is None
    assert for_vehicle(NmpcParams(torque_lag=0.11), vp).torque_lag == 0.11
    own = copy.deepcopy(vp.__dict__)
    car = VehicleParams(**{**own, 'torque_lag': 0.16})
    assert for_vehicle(NmpcParams(torque_lag=0.11), car).torque_lag == 0.16
    # an unset optional field is not in the hash: the shipped maps stay valid
    assert params_hash(vp) == params_hash(VehicleParams(**{**own, 'torque_lag': None}))


def test_a_map_does_not_depend_on_the_powertrain_lag():
    from drift_control.eqmap import map_hash
    from drift_control.params import load_surface
    vp, dry = load_vehicle(), load_surface('dry')
    own = copy.deepcopy(vp.__dict__)
    lagged = VehicleParams(**{**own, 'torque_lag': 0.09})
    assert map_hash(lagged, dry) == map_hash(vp, dry) == params_hash(vp, dry)
    heavier = VehicleParams(**{**own, 'm': vp.m + 10.0})
    assert map_hash(heavier, dry) != map_hash(vp, dry)


def test_a_map_hashed_with_the_lag_stays_valid_for_that_lag(tmp_path):
    from drift_control.eqmap import MapError, _check_hash
    from drift_control.params import load_surface
    vp, dry = load_vehicle(), load_surface('dry')
    lagged = VehicleParams(**{**copy.deepcopy(vp.__dict__), 'torque_lag': 0.09})
    meta = {'params_hash': params_hash(lagged, dry)}   # built before the lag was left out
    _check_hash(meta, tmp_path / 'dry.json', lagged, dry, strict=True)
    slower = VehicleParams(**{**copy.deepcopy(vp.__dict__), 'torque_lag': 0.12, 'm': vp.m + 1})
    with pytest.raises(MapError, match='stale'):
        _check_hash(meta, tmp_path / 'dry.json', slower, dry, strict=True)


@pytest.mark.parametrize('text, value', [('5e-05', 5e-05), ('-2.5E+2', -250.0), ('1.5e3', 1500.0),
                                         ('3', 3), ('12e', '12e'), ('e5', 'e5')])
def test_a_number_in_exponent_form_is_a_number_in_files_and_overrides(tmp_path, text, value):
    """YAML 1.1 reads ``5e-05`` (how Python writes 0.00005) as a string without the dot."""
    assert split_override(f'a.b={text}') == ('a.b', value)
    file = tmp_path / 'x.yaml'
    file.write_text(f'a: {text}\n')
    assert load_yaml(file) == {'a': value}
