"""A scenario with its simulator side: the vehicle's plant, the driver, the initial pose.

The scenario itself (``drift_control.scenario``) is read once for both sides; here it gains the
double-track plant of its vehicle (``config/sim/plants/<vehicle>.yaml`` merged with the
scenario's ``plant:`` overrides) and the driver model's parameters.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path as FsPath

import numpy as np

from drift_control.params import config_dir, from_dict, load_yaml, merge
from drift_control.path import Path
from drift_control.scenario import (Fault, InitialState, MetricWindows, Scenario,  # noqa: F401
                                    SurfaceSpec, load_scenario_spec, resolve_path,
                                    scenario_file, scenario_names, surface_mu)
from drift_sim.params import PlantParams, plant_yaml


@dataclass(frozen=True)
class LoadedScenario:
    """A scenario with everything resolved: its path, plant parameters and raw driver mapping."""

    scenario: Scenario
    path: Path
    plant: PlantParams
    driver_raw: dict
    config: FsPath
    mu: float                # the surface's mean friction, resolved in ``config`` [-]


def load_scenario(name: str, overrides=(), config: str | os.PathLike | None = None,
                  seed: int | None = None, vehicle: str | None = None,
                  spec: Scenario | None = None) -> LoadedScenario:
    """Load, override (``'key=value'`` strings) and validate a scenario with its plant.

    ``spec``: the scenario as ``drift_control.assembly.load_setup`` already read it.
    """
    config = FsPath(config or config_dir())
    scenario = spec or load_scenario_spec(name, overrides, config, seed, vehicle)
    plant = from_dict(PlantParams, merge(plant_yaml(config, scenario.vehicle), scenario.plant),
                      'plant')
    driver_file = config / 'sim' / 'driver.yaml'
    driver_raw = merge(load_yaml(driver_file) if driver_file.is_file() else {}, scenario.driver)
    where = scenario_file(name, config).name
    return LoadedScenario(scenario, resolve_path(scenario.path, config, where), plant,
                          driver_raw, config, surface_mu(scenario, config))


def initial_pose(scenario: Scenario, path: Path, wheelbase: float) -> dict:
    """Keyword arguments of ``Plant.reset`` for the scenario's initial state on ``path``."""
    ini = scenario.initial
    s = ini.s
    K = float(path.curvature_at(s))
    psi = float(path.heading_at(s))
    grid = np.arange(path.n + int(path.closed)) * path.ds
    xs, ys = (np.append(a, a[0]) if path.closed else a for a in (path.x, path.y))
    u = float(path.lap_position(s))
    x0 = float(np.interp(u, grid, xs)) - ini.e_y * math.sin(psi)
    y0 = float(np.interp(u, grid, ys)) + ini.e_y * math.cos(psi)
    beta = math.radians(ini.beta_deg)
    turning = 1.0 if ini.yaw_rate_from_path else 0.0
    return dict(V=ini.V, beta=beta, r=turning * ini.V * K, x=x0, y=y0,
                yaw=psi + math.radians(ini.heading_deg),
                delta=turning * math.atan(wheelbase * K) + math.radians(ini.delta_deg),
                drive_torque=ini.drive_torque, rear_slip=ini.rear_slip)
