"""Tyre forces: hand-computed points, symmetry, bounds, combined-slip interaction."""
import math

import casadi as ca
import numpy as np
import pytest

from drift_control.params import SimpleMF, load_vehicle
from drift_control.tyre import (combined_forces, front_forces, lateral_peak_slip,
                                longitudinal_peak_slip, magic_formula, simple_force)


@pytest.fixture(scope='module')
def vehicle():
    return load_vehicle()


def test_simplified_magic_formula_matches_hand_computation():
    p = SimpleMF(B=10.0, C=1.9, D=1.0, E=0.97)
    alpha, f_z, mu = 0.05, 4000.0, 0.8
    # by hand: Bx = 0.5, atan(0.5) = 0.463648, Bx - E (Bx - atan Bx) = 0.464738
    inner = 0.5 - 0.97 * (0.5 - 0.4636476090008061)
    expected = 0.8 * 4000.0 * math.sin(1.9 * math.atan(inner))
    assert simple_force(alpha, f_z, p, mu) == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(2354.0, abs=0.5)   # 3200 sin(1.9 atan(0.46474))


def test_combined_pure_lateral_matches_hand_computation(vehicle):
    p = vehicle.rear_tyre
    f_z, alpha = p.Fz0, 0.05   # nominal load: dfz = 0, so mu_y = pDy1
    q = 1.0 / p.pKy2
    B_y = 2 * p.pKy1 / (p.pKy2 * (1 + q * q)) / (p.pCy1 * p.pDy1)
    x = B_y * alpha
    expected = p.pDy1 * f_z * math.sin(p.pCy1 * math.atan(x - p.pEy1 * (x - math.atan(x))))
    assert combined_forces(alpha, 0.0, f_z, p, 1.0).Fy == pytest.approx(expected, rel=1e-12)
    # the MF 5.2 cornering stiffness pKy1 Fz0 sin(2 atan(Fz / (pKy2 Fz0))) is the slope at 0
    slope = combined_forces(1e-7, 0.0, f_z, p, 1.0).Fy / 1e-7
    k_y = p.pKy1 * p.Fz0 * math.sin(2 * math.atan(f_z / (p.pKy2 * p.Fz0)))
    assert slope == pytest.approx(k_y, rel=1e-5)


@pytest.mark.parametrize('alpha', [0.01, 0.1, 0.5, 1.2])
@pytest.mark.parametrize('kappa', [0.0, 0.1, -0.3])
def test_lateral_force_is_odd_in_slip_angle_and_bounded(vehicle, alpha, kappa):
    p = vehicle.rear_tyre
    f = combined_forces(alpha, kappa, 5000.0, p, 1.0)
    g = combined_forces(-alpha, kappa, 5000.0, p, 1.0)
    assert g.Fy == pytest.approx(-f.Fy, rel=1e-12)
    assert g.Fx == pytest.approx(f.Fx, rel=1e-12)   # longitudinal force even in alpha
    assert abs(f.Fy) <= (p.pDy1 + abs(p.pDy2)) * 5000.0
    front = front_forces(alpha, 0.0, 5000.0, vehicle.front_tyre, 1.0)
    assert front_forces(-alpha, 0.0, 5000.0, vehicle.front_tyre, 1.0).Fy == pytest.approx(-front.Fy)


def test_combined_slip_reduces_lateral_force_as_longitudinal_slip_grows(vehicle):
    p = vehicle.rear_tyre
    alpha = math.radians(20.0)
    fy = [combined_forces(alpha, k, 8000.0, p, 1.0).Fy for k in np.linspace(0.0, 1.0, 21)]
    assert all(b < a for a, b in zip(fy, fy[1:])), 'F_y must fall monotonically with kappa'
    assert fy[-1] < 0.6 * fy[0], 'a spinning wheel must lose a large part of its lateral grip'
    fx = [combined_forces(a, 0.1, 8000.0, p, 1.0).Fx for a in np.linspace(0.0, 0.6, 13)]
    assert all(b < a for a, b in zip(fx, fx[1:])), 'F_x must fall as the slip angle grows'


def test_peak_grows_sublinearly_with_load(vehicle):
    p = vehicle.rear_tyre
    peak = [max(combined_forces(a, 0.0, fz, p, 1.0).Fy for a in np.linspace(0, 0.5, 200))
            for fz in (4000.0, 8000.0, 12000.0)]
    mu_eff = [f / fz for f, fz in zip(peak, (4000.0, 8000.0, 12000.0))]
    assert peak[0] < peak[1] < peak[2]
    assert mu_eff[0] > mu_eff[1] > mu_eff[2], 'load sensitivity: friction coefficient falls with load'


def test_surface_friction_scales_the_peak(vehicle):
    p = vehicle.rear_tyre
    dry = max(combined_forces(a, 0.0, 8000.0, p, 1.0).Fy for a in np.linspace(0, 0.6, 300))
    wet = max(combined_forces(a, 0.0, 8000.0, p, 0.6).Fy for a in np.linspace(0, 0.6, 300))
    assert wet / dry == pytest.approx(0.6, rel=1e-3)


def test_peak_slips_are_plausible_for_a_car_tyre(vehicle):
    kappa_peak = longitudinal_peak_slip(8000.0, vehicle.rear_tyre)
    alpha_peak = lateral_peak_slip(8000.0, vehicle.rear_tyre)
    assert 0.05 < kappa_peak < 0.2
    assert math.radians(4) < alpha_peak < math.radians(12)


def test_same_body_for_floats_and_symbols(vehicle):
    a, k, fz, mu = ca.SX.sym('a'), ca.SX.sym('k'), ca.SX.sym('fz'), ca.SX.sym('mu')
    fun = ca.Function('t', [a, k, fz, mu], [ca.vertcat(*combined_forces(a, k, fz, vehicle.rear_tyre, mu))])
    rng = np.random.default_rng(1)
    for _ in range(50):
        args = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(500, 15000), rng.uniform(0.3, 1.2))
        numeric = combined_forces(args[0], args[1], args[2], vehicle.rear_tyre, args[3])
        symbolic = np.asarray(fun(*args)).ravel()
        assert np.allclose(numeric, symbolic, rtol=1e-12, atol=1e-9)
    assert magic_formula(0.0, 10.0, 1.9, 0.97) == 0.0
