"""Scenarios: path, surface, initial state, duration, control mode, faults and plant overrides.

A scenario is ``config/scenarios/<name>.yaml``, loaded into a frozen ``Scenario``. Its ``path:``
is the format of ``drift_control.path.load_path`` (a mapping) or the name of a file under
``config/paths/`` -- the same rule the reference node applies, so sim and controller drive the
same path. ``plant:`` holds overrides merged into ``config/sim/plant.yaml``; ``--set key=value``
changes any key of either (``surface.mu=0.55``, ``plant.lsd.locking=1.0``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Literal

import numpy as np

from drift_control.params import (ParamError, config_dir, from_dict, load_surface, load_yaml,
                                  require)
from drift_control.path import Path, load_path
from drift_sim.params import PlantParams, merge, plant_yaml, set_key, split_override


@dataclass(frozen=True)
class SurfaceSpec:
    """The surface: a name from ``config/vehicle/surfaces.yaml``, optionally another mu."""

    name: str
    mu: float = -1.0     # [-]; negative: the named surface's mu

    def __post_init__(self):
        require(self.mu == -1.0 or 0.0 < self.mu <= 2.0, 'surface.mu', 'must be in (0, 2]')


@dataclass(frozen=True)
class InitialState:
    """Where and how the car starts, relative to the path at arc length ``s``."""

    V: float                     # speed [m/s]
    s: float = 0.0               # arc length on the path [m]
    e_y: float = 0.0             # lateral offset, positive left [m]
    heading_deg: float = 0.0     # yaw relative to the path tangent [deg]
    beta_deg: float = 0.0        # sideslip [deg]
    yaw_rate_from_path: bool = True   # r = V K(s), delta = atan(L K(s)) + delta_deg; else 0
    delta_deg: float = 0.0       # road-wheel angle (added to the kinematic one) [deg]
    drive_torque: float = 0.0    # rear axle torque [Nm]
    rear_slip: float = 0.0       # rear wheels' longitudinal slip [-] (a drift: they spin)

    def __post_init__(self):
        require(self.V >= 0.0, 'initial.V', 'must be >= 0')


@dataclass(frozen=True)
class Fault:
    """A fault active on ``start <= t < end``.

    kind: ``mu_scale`` (surface mu times ``value``), ``signal_dropout`` (measurements marked
    invalid), ``steering_freeze`` (steering held), ``torque_cut`` (drive torque request 0),
    ``command_loss`` (commands dropped; the last one is held).
    """

    kind: Literal['mu_scale', 'signal_dropout', 'steering_freeze', 'torque_cut', 'command_loss']
    start: float
    end: float
    value: float = 1.0

    def __post_init__(self):
        require(0.0 <= self.start < self.end, 'faults', 'need 0 <= start < end')

    def active(self, t: float) -> bool:
        return self.start <= t < self.end


@dataclass(frozen=True)
class MetricWindows:
    """Where the metrics look: windows of steady drift and the end of the entry transient."""

    steady: tuple[tuple[float, ...], ...] = ()   # [[t0, t1], ...] steady drift windows [s]
    transient_end: float = 0.0    # e_y is judged after this time [s]
    drift_beta_deg: float = 10.0  # |beta| above this counts as drifting [deg]


@dataclass(frozen=True)
class Scenario:
    """One simulated run."""

    name: str
    duration: float                      # [s]
    control_mode: Literal['full', 'torque_only']
    surface: SurfaceSpec
    initial: InitialState
    path: Any                            # load_path mapping or a config/paths name
    map_file: str = ''                   # equilibrium map, relative to the checkout root
    description: str = ''
    seed: int = 0
    expect_spin: bool = False            # the paper's outcome (eps_limited_dry: the car spins)
    faults: tuple[Fault, ...] = ()
    metrics: MetricWindows = field(default_factory=MetricWindows)
    plant: dict[str, Any] = field(default_factory=dict)    # overrides of config/sim/plant.yaml
    driver: dict[str, Any] = field(default_factory=dict)   # overrides of config/sim/driver.yaml

    def __post_init__(self):
        require(self.duration > 0, f'scenario {self.name}.duration', 'must be positive')
        for w in self.metrics.steady:
            require(len(w) == 2 and w[0] < w[1], f'scenario {self.name}.metrics.steady',
                    'each window is [t0, t1] with t0 < t1')

    @property
    def mu(self) -> float:
        """Mean friction of the surface [-]."""
        return self.surface.mu if self.surface.mu > 0 else load_surface(self.surface.name).mu


@dataclass(frozen=True)
class LoadedScenario:
    """A scenario with everything resolved: its path, plant parameters and raw driver mapping."""

    scenario: Scenario
    path: Path
    plant: PlantParams
    driver_raw: dict
    config: FsPath


def scenario_file(name: str, config: str | os.PathLike | None = None) -> FsPath:
    """``config/scenarios/<name>.yaml``, or ``name`` itself when it is a file."""
    if os.path.isfile(name):
        return FsPath(name)
    return FsPath(config or config_dir()) / 'scenarios' / f'{name}.yaml'


def scenario_names(config: str | os.PathLike | None = None) -> list[str]:
    """Names of the scenarios under ``config/scenarios``."""
    return sorted(p.stem for p in (FsPath(config or config_dir()) / 'scenarios').glob('*.yaml'))


def resolve_path(section, config: FsPath, where: str) -> Path:
    """A ``path:`` section: a ``load_path`` mapping or the name of a ``config/paths`` file."""
    if isinstance(section, dict):
        return load_path(section, f'{where}.path')
    if not isinstance(section, str) or not section:
        raise ParamError(f'{where}.path: expected a mapping or a config/paths name')
    file = config / 'paths' / (section if section.endswith('.yaml') else f'{section}.yaml')
    raw = load_yaml(file)
    return load_path(raw.get('path', raw), file.name)


def load_scenario(name: str, overrides=(), config: str | os.PathLike | None = None,
                  seed: int | None = None) -> LoadedScenario:
    """Load, override (``'key=value'`` strings) and validate a scenario with its plant."""
    config = FsPath(config or config_dir())
    file = scenario_file(name, config)
    raw = load_yaml(file)
    raw.setdefault('name', file.stem)
    for item in overrides:
        key, value = split_override(item)
        set_key(raw, key, value, where=file.name)
    if seed is not None:
        raw['seed'] = int(seed)
    scenario = from_dict(Scenario, raw, f'scenarios/{file.name}')
    plant = from_dict(PlantParams, merge(plant_yaml(config), scenario.plant), 'plant')
    driver_file = config / 'sim' / 'driver.yaml'
    driver_raw = merge(load_yaml(driver_file) if driver_file.is_file() else {}, scenario.driver)
    return LoadedScenario(scenario, resolve_path(scenario.path, config, file.name), plant,
                          driver_raw, config)


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
