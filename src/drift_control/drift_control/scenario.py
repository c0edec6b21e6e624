"""Scenarios: vehicle, path, surface, initial state, duration, control mode, faults, overrides.

A scenario is ``config/scenarios/<name>.yaml``, loaded into a frozen ``Scenario``. Its ``path:``
is the format of ``drift_control.path.load_path`` (a mapping), the name of a file under
``config/paths/``, or ``{file: <name>, ...}`` (that file with keys laid over it). ``plant:``
and ``driver:`` hold the simulator's overrides (``drift_sim`` applies them); ``--set
key=value`` changes any key (``surface.mu=0.55``, ``vehicle=gr86``, ``plant.lsd.locking=1.0``).
The controller side reads the same file through
``drift_control.assembly``, the simulator through ``drift_sim.scenario``: one parser for both.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Literal

from drift_control.params import (ParamError, config_dir, default_vehicle, from_dict,
                                  load_surface, load_yaml, require, set_key, split_override)
from drift_control.path import Path, load_path, load_path_file


@dataclass(frozen=True)
class SurfaceSpec:
    """The surface: a name from ``config/vehicle/surfaces.yaml``, optionally another mu."""

    name: str
    mu: float = 0.0      # [-]; 0 (not given): the named surface's mu

    def __post_init__(self):
        require(self.mu == 0.0 or 0.0 < self.mu <= 2.0, 'surface.mu',
                f'must be in (0, 2] (or left out for the named surface\'s), got {self.mu}')


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
    settle: float = 0.0           # > 0: no fixed windows; steady where the sideslip reference
                                  # has held one drift value this long [s] (a course with
                                  # flips), e_y judged from the first such window on
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
    vehicle: str = ''                    # config/vehicle/<name>.yaml; '': config/defaults.yaml's
    description: str = ''
    seed: int = 0
    expect_spin: bool = False            # the paper's outcome (eps_limited_dry: the car spins)
    faults: tuple[Fault, ...] = ()
    metrics: MetricWindows = field(default_factory=MetricWindows)
    plant: dict[str, Any] = field(default_factory=dict)    # overrides of the vehicle's plant file
    driver: dict[str, Any] = field(default_factory=dict)   # overrides of config/sim/driver.yaml

    @property
    def is_manoeuvre(self) -> bool:
        """A scripted identification manoeuvre (``driver.manoeuvre``): no controller drives it."""
        return bool(self.driver.get('manoeuvre'))

    def __post_init__(self):
        require(self.duration > 0, f'scenario {self.name}.duration', 'must be positive')
        for w in self.metrics.steady:
            require(len(w) == 2 and w[0] < w[1], f'scenario {self.name}.metrics.steady',
                    'each window is [t0, t1] with t0 < t1')
        require(self.metrics.settle >= 0.0, f'scenario {self.name}.metrics.settle',
                'must not be negative')
        require(not (self.metrics.settle > 0.0 and self.metrics.steady),
                f'scenario {self.name}.metrics', 'give steady windows or settle, not both')



def scenario_file(name: str, config: str | os.PathLike | None = None) -> FsPath:
    """``config/scenarios/<name>.yaml``, or ``name`` itself when it is a file."""
    if os.path.isfile(name):
        return FsPath(name)
    return FsPath(config or config_dir()) / 'scenarios' / f'{name}.yaml'


def scenario_names(config: str | os.PathLike | None = None) -> list[str]:
    """Names of the scenarios under ``config/scenarios``."""
    return sorted(p.stem for p in (FsPath(config or config_dir()) / 'scenarios').glob('*.yaml'))


def control_scenario_names(config: str | os.PathLike | None = None) -> list[str]:
    """The scenarios the controller drives: all but the identification manoeuvres."""
    return [n for n in scenario_names(config)
            if not load_scenario_spec(n, config=config).is_manoeuvre]


def resolve_path(section, config: FsPath, where: str) -> Path:
    """A ``path:`` section: a ``load_path`` mapping, the name of a ``config/paths`` file, or
    ``{file: <name>, ...}``: that file with the other keys laid over it (``sideslip:`` key by
    key; e.g. the wet pad's longer entry ramp on a dry scenario's path)."""
    overlay = None
    if isinstance(section, dict) and 'file' in section:
        overlay = {k: v for k, v in section.items() if k != 'file'}
        section = section['file']
    elif isinstance(section, dict):
        return load_path(section, f'{where}.path')
    if not isinstance(section, str) or not section:
        raise ParamError(f'{where}.path: expected a mapping or a config/paths name')
    file = config / 'paths' / (section if section.endswith('.yaml') else f'{section}.yaml')
    return load_path_file(file, overlay, f'{where}.path ({file.name})' if overlay else None)


def surface_mu(scenario: Scenario, config: str | os.PathLike | None = None) -> float:
    """The scenario's mean friction: its ``surface.mu``, else its named surface's in ``config``."""
    if scenario.surface.mu > 0:
        return scenario.surface.mu
    return load_surface(scenario.surface.name,
                        FsPath(config or config_dir()) / 'vehicle' / 'surfaces.yaml').mu


def load_scenario_spec(name: str, overrides=(), config: str | os.PathLike | None = None,
                       seed: int | None = None, vehicle: str | None = None) -> Scenario:
    """Read ``name`` (a scenario name or file), apply ``key=value`` overrides, validate.

    ``vehicle`` (a command line's ``--vehicle``) wins over the scenario's ``vehicle:``; with
    neither, the vehicle is ``config/defaults.yaml``'s.
    """
    config = FsPath(config or config_dir())
    file = scenario_file(name, config)
    raw = load_yaml(file)
    raw.setdefault('name', file.stem)
    for item in overrides:
        key, value = split_override(item)
        set_key(raw, key, value, where=file.name)
    if seed is not None:
        raw['seed'] = int(seed)
    if vehicle:
        raw['vehicle'] = vehicle
    if not raw.get('vehicle'):
        raw['vehicle'] = default_vehicle(config)
    return from_dict(Scenario, raw, f'scenarios/{file.name}')


__all__ = ['Fault', 'InitialState', 'MetricWindows', 'Scenario', 'SurfaceSpec',
           'control_scenario_names', 'load_scenario_spec', 'resolve_path', 'scenario_file',
           'scenario_names', 'surface_mu']
