"""The selector on the default vehicle's real dry equilibrium map (scripts/build_maps.py)."""
import math
import os

import numpy as np
import pytest

from drift_control.assembly import map_file
from drift_control.params import config_dir, default_vehicle, load_yaml
from drift_control.path import load_path
from drift_control.reference import ReferenceSelector, load_reference_params
from drift_control.signals import Direction, VehicleState

eqmap = pytest.importorskip('drift_control.eqmap')
MAP = map_file(default_vehicle(), 'dry')


@pytest.fixture(scope='module')
def dry():
    return eqmap.load_map(MAP)


def test_alternating_manoeuvre_on_the_real_map(dry):
    """A kinematic car driven at the reference speed along the paper's manoeuvre."""
    cfg = str(config_dir())
    path = load_path(load_yaml(os.path.join(cfg, 'paths', 'alternating_15.yaml'))['path'])
    p = load_reference_params(os.path.join(cfg, 'reference.yaml'))
    sel = ReferenceSelector(dry.lookup, path, p)
    sel.reset(s_hint=0.0)
    x, y, course, dt, V, yaw_rate = 0.0, -0.5, 0.0, 0.02, 8.0, 0.0
    refs = []
    for k in range(4000):
        beta = refs[-1].target.beta if refs else 0.0
        ref = sel.select(VehicleState(stamp=k * dt, V=V, beta=beta, r=yaw_rate, x=x, y=y,
                                      yaw=course - beta))
        assert ref.is_finite() and len(ref.horizon) == p.horizon_steps
        refs.append(ref)
        if ref.s > path.length - 2.0:
            break
        V = ref.target.V                      # the car drives the equilibrium speed
        turn = V * ref.curvature_cmd * dt
        x += V * dt * math.cos(course + 0.5 * turn)
        y += V * dt * math.sin(course + 0.5 * turn)
        course += turn
        yaw_rate = turn / dt                  # the selector learns r / V
    s = np.array([r.s for r in refs])
    assert s[-1] > path.length - 2.0, 'drove the whole manoeuvre'
    left = [r for r in refs if 110.0 < r.s < 130.0]   # past the grip phase and the 80 m ramp
    right = [r for r in refs if r.s > path.length - 40.0]
    for group, sign in ((left, 1), (right, -1)):
        for r in group:
            assert r.direction == Direction(sign)
            assert r.target.beta == pytest.approx(-sign * math.radians(30.0), abs=1e-9)
            assert r.target.V / r.target.r == pytest.approx(1.0 / r.curvature_cmd, rel=1e-6)
            assert abs(r.e_y) < 0.3 and not r.clamped
            assert np.sign(r.target.delta) == -sign, 'a 30 deg drift counter-steers'
    for field in ('V', 'beta', 'r', 'delta', 'T_R'):
        steps = np.abs(np.diff([getattr(r.target, field) for r in refs]))
        scale = max(abs(getattr(r.target, field)) for r in refs)
        assert steps.max() < 0.1 * scale, f'{field} jumps at s={s[np.argmax(steps)]:.1f} m'
