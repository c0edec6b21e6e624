"""Dynamic referencing closed loop (paper Sec. IV): selector + NMPC + the controller's own model.

A 30 deg left drift on the R = 15 m circle, the plant's friction 5 % below the map's, measurement
noise: with the path-following correction the car stays within the paper's 1 m of the path after
the entry transient; the same run with no path following (neither the selector's correction nor
the NMPC's lateral error, ``cost.e_y``) drifts away from it.
"""
import dataclasses

import numpy as np
import pytest

from drift_control.assembly import map_file
from drift_control.eqmap import load_map
from drift_control.model_plant import ModelPlant
from drift_control.nmpc import Nmpc
from drift_control.ocp import load_nmpc_params
from drift_control.params import config_dir, default_vehicle, load_vehicle, load_yaml
from drift_control.path import load_path
from drift_control.reference import ReferenceSelector, load_reference_params
from drift_control.vehicle import NX, X

pytestmark = pytest.mark.slow
TRANSIENT_S, DURATION_S = 20.0, 40.0


def run(correction: bool) -> np.ndarray:
    cfg = config_dir()
    vp = load_vehicle()
    path = load_path(load_yaml(cfg / 'paths' / 'circle_left_15.yaml')['path'])
    params = load_reference_params(cfg / 'reference.yaml')
    if not correction:
        params = dataclasses.replace(params, k_p=0.0, k_d=0.0, k_i=0.0)
    selector = ReferenceSelector(load_map(map_file(default_vehicle(), 'dry')).lookup, path, params)
    nmpc_params = load_nmpc_params(cfg / 'nmpc.yaml')
    if not correction:
        nmpc_params = dataclasses.replace(
            nmpc_params, cost=dataclasses.replace(nmpc_params.cost, e_y=0.0))
    nmpc = Nmpc(vp, nmpc_params)
    plant = ModelPlant(vp, mu=0.95, noise={'V': 0.05, 'beta': 0.003, 'r': 0.005}, seed=2)
    x0 = np.zeros(NX)
    x0[[X.V, X.OMEGA_F, X.OMEGA_R]] = 11.0, 11.0 / vp.R_F, 11.0 / vp.R_R
    state = plant.reset(x0)
    e_y = []
    for _ in range(int(DURATION_S / 0.02)):
        ref = selector.select(state)
        state = plant.step(nmpc.step(state, ref, state.stamp).command, 0.02)
        e_y.append((state.stamp, ref.e_y, plant.x[X.BETA]))
    return np.array(e_y)


def test_path_following_correction_keeps_the_car_on_the_path():
    on, off = run(True), run(False)
    late_on, late_off = on[on[:, 0] > TRANSIENT_S], off[off[:, 0] > TRANSIENT_S]
    max_on, max_off = np.abs(late_on[:, 1]).max(), np.abs(late_off[:, 1]).max()
    print(f'\nmax |e_y| after {TRANSIENT_S:.0f} s: correction on {max_on:.2f} m, '
          f'off {max_off:.2f} m; mean |beta| on {np.degrees(np.abs(late_on[:, 2])).mean():.1f} '
          f'deg, off {np.degrees(np.abs(late_off[:, 2])).mean():.1f} deg')
    assert max_on <= 1.0, 'the paper: within 1 m of the path after the entry'
    assert max_off > 3.0 * max_on and max_off > 2.0, 'without the correction the car drifts away'
    assert np.degrees(np.abs(late_on[:, 2])).mean() == pytest.approx(30.0, abs=2.0)
