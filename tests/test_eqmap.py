"""Equilibrium map: committed maps are equilibria, lookup is smooth, clamped, mirrored, fast."""
import json
import logging
import time
from pathlib import Path

import numpy as np
import pytest

from drift_control.equilibrium import scaled_derivative, solve_equilibrium
from drift_control.eqmap import (KINDS, GridParams, MapError, MapParams, build_map, fill_holes,
                                 load_map, load_map_params, save_map)
from drift_control.assembly import map_file
from drift_control.params import (ParamError, Surface, default_vehicle, load_surface,
                                  load_vehicle)

from conftest import load_script
from drift_control.signals import Direction, Equilibrium
from drift_control.vehicle import VehicleModel

ROOT = Path(__file__).resolve().parents[1]
SURFACES = ('dry', 'wet')


@pytest.fixture(scope='module')
def vehicle():
    return load_vehicle()


@pytest.fixture(scope='module')
def model(vehicle):
    return VehicleModel(vehicle)


@pytest.fixture(scope='module', params=SURFACES)
def committed(request):
    return load_map(map_file(default_vehicle(), request.param))


@pytest.fixture(scope='module')
def small_map(vehicle):
    """A small grid built in the test, around the 30 deg drift."""
    params = MapParams(grid=GridParams(beta_deg=(20.0, 34.0, 2.0), radius_m=(12.0, 20.0, 4.0)))
    return build_map(vehicle, load_surface('dry'), params, jobs=1)


def _eq_at(m, i, j) -> Equilibrium:
    return Equilibrium(*(float(m.data[k][i, j]) for k in
                         ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta', 'T_R')))


def test_every_converged_point_is_an_equilibrium(committed, model):
    mu = committed.meta['mu']
    idx = np.argwhere(committed.converged)
    assert len(idx) > 0.5 * committed.converged.size, 'most of the grid converges'
    worst = max(np.max(np.abs(scaled_derivative(_eq_at(committed, i, j), model, mu)))
                for i, j in idx)
    assert worst <= 1e-8, f'worst scaled |x_dot| {worst:.2e}'
    V, r = committed.data['V'], committed.data['r']
    R = np.broadcast_to(committed.radius, V.shape)
    ok = committed.converged
    np.testing.assert_allclose(V[ok] / r[ok], R[ok], rtol=1e-9, err_msg='R = V / r')
    beta = np.broadcast_to(-committed.beta_abs[:, None], V.shape)
    np.testing.assert_allclose(committed.data['beta'][ok], beta[ok], atol=1e-12)


def test_drift_points_at_30_deg_counter_steer(committed):
    i = int(np.abs(committed.beta_abs - np.radians(30.0)).argmin())
    ok = committed.converged[i]
    assert ok.sum() >= 0.9 * ok.size, 'the 30 deg row is (nearly) all equilibria'
    assert np.all(committed.data['kind'][i, ok] == KINDS.index('drift'))
    delta, r = committed.data['delta'][i, ok], committed.data['r'][i, ok]
    assert np.all(np.sign(delta) == -np.sign(r)), 'sign(delta) == -sign(r)'


def test_grip_points_steer_into_the_turn(committed):
    grip = committed.converged & (committed.data['kind'] == KINDS.index('grip'))
    assert grip.any()
    assert np.all(committed.data['delta'][grip] > 0), 'grip: delta has the sign of r'
    deep = committed.converged & (committed.beta_abs[:, None] >= np.radians(20.0))
    assert np.all(committed.data['kind'][deep] == KINDS.index('drift'))
    assert np.all(committed.data['delta'][deep] < 0), 'full drift: counter-steer'


def test_speed_grows_with_radius_and_wheels_diverge(committed):
    """What the paper reports (section III-A): V up with R; omega_R - omega_F up with beta."""
    i = int(np.abs(committed.beta_abs - np.radians(25.0)).argmin())
    ok = committed.converged[i]
    assert np.all(np.diff(committed.data['V'][i, ok]) > 0)
    j = int(np.abs(committed.radius - 15.0).argmin())
    gap = committed.data['omega_R'][:, j] - committed.data['omega_F'][:, j]
    rows = committed.converged[:, j] & (committed.beta_abs > np.radians(15.0))
    assert np.all(np.diff(gap[rows]) > 0)


def test_committed_maps_match_current_parameters(recwarn):
    for name in SURFACES:
        m = load_map(map_file(default_vehicle(), name))
        assert m.meta['surface'] == name
    assert not [w for w in recwarn if 'stale' in str(w.message)]


def test_lookup_at_grid_nodes_returns_the_stored_equilibrium(small_map):
    m = small_map
    for i, j in np.argwhere(m.converged)[::3]:
        eq, clamped = m.lookup(m.beta_abs[i], m.radius[j], Direction.LEFT)
        assert not clamped
        assert eq.V == pytest.approx(m.data['V'][i, j], rel=1e-9)
        assert eq.delta == pytest.approx(m.data['delta'][i, j], abs=1e-9)
        assert eq.V / eq.r == pytest.approx(m.radius[j], rel=1e-12)


def test_lookup_between_nodes_is_close_to_a_solved_equilibrium(committed, vehicle, model):
    mu = committed.meta['mu']
    beta_abs, R = np.radians(27.3), 17.6
    eq, clamped = committed.lookup(beta_abs, R, Direction.LEFT)
    exact = solve_equilibrium(-beta_abs, R, vehicle, mu, guess=eq, model=model)
    assert not clamped and exact.converged
    assert eq.V == pytest.approx(exact.eq.V, rel=1e-3)
    assert eq.delta == pytest.approx(exact.eq.delta, abs=np.radians(0.1))
    assert eq.T_R == pytest.approx(exact.eq.T_R, rel=1e-2)


@pytest.mark.parametrize('beta_deg, R', [(0.0, 8.0), (12.5, 13.3), (30.0, 15.0), (33.7, 39.9)])
def test_lookup_is_mirror_symmetric(committed, beta_deg, R):
    left, c_l = committed.lookup(np.radians(beta_deg), R, Direction.LEFT)
    right, c_r = committed.lookup(np.radians(beta_deg), R, Direction.RIGHT)
    assert right == left.mirrored() and c_l == c_r
    assert left.r > 0 and right.r < 0
    assert left.beta <= 0 <= right.beta


@pytest.mark.parametrize('beta_abs, R', [(np.radians(60.0), 15.0), (np.radians(30.0), 3.0),
                                         (np.radians(30.0), 100.0), (-0.1, 15.0),
                                         (np.nan, 15.0), (np.radians(30.0), np.inf)])
def test_lookup_outside_the_grid_clamps_and_stays_finite(committed, beta_abs, R):
    eq, clamped = committed.lookup(beta_abs, R, Direction.LEFT)
    assert clamped
    assert eq.is_finite()
    assert committed.radius[0] - 1e-9 <= eq.V / eq.r <= committed.radius[-1] + 1e-9


def test_lookup_in_a_hole_is_flagged_and_finite(committed):
    i, j = np.argwhere(~committed.converged)[0]
    eq, clamped = committed.lookup(committed.beta_abs[i], committed.radius[j], Direction.LEFT)
    assert clamped and eq.is_finite()
    for k in ('V', 'omega_F', 'omega_R', 'delta', 'T_R'):
        assert np.all(np.isfinite(committed.filled(k)))


def test_clamping_warning_is_rate_limited(small_map, caplog):
    with caplog.at_level(logging.WARNING, logger='drift_control.eqmap'):
        for _ in range(20):
            small_map.lookup(np.radians(80.0), 15.0, Direction.LEFT)
    assert len([r for r in caplog.records if 'clamped' in r.getMessage()]) == 1


def test_lookup_rejects_no_direction(small_map):
    with pytest.raises(ValueError):
        small_map.lookup(0.5, 15.0, Direction.NONE)


def test_lookup_is_fast(committed):
    rng = np.random.default_rng(1)
    queries = zip(rng.uniform(0, 0.8, 500), rng.uniform(8, 40, 500))
    t0 = time.perf_counter()
    for b, R in queries:
        committed.lookup(b, R, Direction.LEFT)
    per_call = (time.perf_counter() - t0) / 500
    assert per_call < 1e-3, f'{per_call * 1e6:.0f} us per lookup (budget: well under 1 ms)'


def test_casadi_interpolant_matches_the_grid_and_the_lookup(small_map, committed):
    f = small_map.casadi_interpolant()
    i, j = 3, 1
    values = np.asarray(f([small_map.beta_abs[i], small_map.radius[j]])).ravel()
    assert values[0] == pytest.approx(small_map.data['V'][i, j], rel=1e-6)
    assert values[3] == pytest.approx(small_map.data['delta'][i, j], abs=1e-6)
    b, R = np.radians(24.4), 21.3
    eq, _ = committed.lookup(b, R, Direction.LEFT)
    values = np.asarray(committed.casadi_interpolant()([b, R])).ravel()
    assert values[0] == pytest.approx(eq.V, rel=1e-3)
    assert values[3] == pytest.approx(eq.delta, abs=1e-3)


def test_save_load_round_trip(small_map, tmp_path, vehicle):
    npz, meta = save_map(small_map, tmp_path / 'dry')
    assert npz.name == 'dry.npz' and meta.name == 'dry.json'
    m = load_map(tmp_path / 'dry.npz', vehicle=vehicle)
    np.testing.assert_array_equal(m.data['V'], small_map.data['V'])
    np.testing.assert_array_equal(m.converged, small_map.converged)
    info = json.loads(meta.read_text())
    assert info['grid']['n_beta'] == 8 and info['units']['V'] == 'm/s'
    assert 0.0 < info['converged_fraction'] <= 1.0 and info['build_time_s'] >= 0.0


def test_hash_mismatch_warns_loudly(small_map, tmp_path, vehicle, caplog):
    save_map(small_map, tmp_path / 'dry')
    other = Surface('dry', 0.9)
    with caplog.at_level(logging.WARNING, logger='drift_control.eqmap'):
        with pytest.warns(RuntimeWarning, match='stale'):
            m = load_map(tmp_path / 'dry', vehicle=vehicle, surface=other)
    assert any('parameter hash' in r.getMessage() for r in caplog.records)
    assert m.converged.any()   # still usable, just flagged


def test_missing_map_is_a_clear_error(tmp_path):
    with pytest.raises(MapError, match='nowhere.npz.*not found'):
        load_map(tmp_path / 'nowhere')


@pytest.mark.parametrize('damage', ['garbage npz', 'garbage json', 'missing array',
                                    'pickled array', 'wrong shape', 'nan at converged'])
def test_corrupt_map_is_a_clear_error(small_map, tmp_path, damage):
    npz, meta = save_map(small_map, tmp_path / 'dry')
    arrays = {'beta_abs': small_map.beta_abs, 'radius': small_map.radius, **small_map.data}
    if damage == 'garbage npz':
        npz.write_bytes(b'not a zip file at all')
    elif damage == 'garbage json':
        meta.write_text('{"version": 1,')
    else:
        if damage == 'missing array':
            del arrays['T_R']
        elif damage == 'pickled array':
            arrays['T_R'] = np.array([{'x': 1}], dtype=object)
        elif damage == 'wrong shape':
            arrays['T_R'] = arrays['T_R'][:-1]
        elif damage == 'nan at converged':
            arrays['V'] = np.full_like(arrays['V'], np.nan)
        np.savez(npz, **arrays)
    with pytest.raises(MapError) as err:
        load_map(tmp_path / 'dry')
    assert 'dry.' in str(err.value)


def test_fill_holes_is_linear_inside_and_held_outside():
    beta = np.arange(5.0)
    radius = np.array([1.0, 2.0, 3.0])
    values = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3], [4, 4, 4]], float)
    valid = np.ones_like(values, bool)
    valid[2, 0] = valid[0, 1] = False
    valid[:, 2] = False
    values[~valid] = np.nan
    out = fill_holes(values, valid, beta, radius)
    assert out[2, 0] == pytest.approx(2.0)     # linear between converged neighbours
    assert out[0, 1] == pytest.approx(1.0)     # held at the row's end
    np.testing.assert_allclose(out[:, 2], out[:, 1])   # empty row from the nearest row


def test_map_config_loads_and_rejects_unknown_keys(tmp_path):
    params = load_map_params()
    assert params.grid.beta_abs()[-1] == pytest.approx(np.radians(45.0))
    assert len(params.grid.radius()) == 33
    bad = tmp_path / 'maps.yaml'
    bad.write_text('grid:\n  beta_deg: [0, 45, 1]\n  radius: [8, 40, 1]\n')
    with pytest.raises(ParamError, match='radius'):
        load_map_params(bad)


def test_build_script_writes_both_files(tmp_path, capsys):
    script = load_script('build_maps')
    assert script.main(['--surface', 'wet', '--beta-deg', '26:30:2', '--radius', '14:16:2',
                        '--jobs', '2', '--out', str(tmp_path)]) == 0
    assert 'converged' in capsys.readouterr().out
    m = load_map(tmp_path / 'wet')
    assert m.converged.shape == (3, 2) and m.meta['mu'] == load_surface('wet').mu
