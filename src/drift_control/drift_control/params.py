"""Parameters as data: YAML files under ``config/`` loaded into frozen, validated dataclasses.

This is the one place that reads configuration. Every error names the offending key with its full
path (``vehicle.rear_tyre.pKx1``) so a typo in a YAML file is found at start-up, not in a solver.
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import re
import types
import typing
from dataclasses import MISSING, asdict, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml


class ParamError(ValueError):
    """A parameter file or value is missing, unknown, of the wrong type or out of range."""


# In a checkout this file is <repo>/src/drift_control/drift_control/params.py; installed, it is
# <prefix>/lib/python3.X/site-packages/drift_control/params.py, with no config/ at parents[3].
_CHECKOUT = Path(__file__).resolve().parents[3]


def config_dir() -> Path:
    """The project's ``config/`` directory: ``$DRIFT_CONFIG_DIR``, else this checkout's, else the
    one installed in drift_control's share directory (found through the ament index)."""
    env = os.environ.get('DRIFT_CONFIG_DIR')
    if env:
        return Path(env)
    if (_CHECKOUT / 'config').is_dir():
        return _CHECKOUT / 'config'
    share = _share_dir()
    if share is not None and (share / 'config').is_dir():
        return share / 'config'
    raise ParamError('no config directory: set DRIFT_CONFIG_DIR, run from a checkout, or source '
                     'an install space that has drift_control (install/setup.bash)')


def cache_dir() -> Path:
    """Where compiled solvers are cached (``.codegen/`` below it): this checkout's root, else
    ``$XDG_CACHE_HOME/drift_stack`` (``~/.cache/drift_stack``), never an install space."""
    if (_CHECKOUT / 'config').is_dir():
        return _CHECKOUT
    return Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache') / 'drift_stack'


def _share_dir() -> Path | None:
    """drift_control's share directory in the ament index (AMENT_PREFIX_PATH), None without."""
    try:
        from ament_index_python.packages import (PackageNotFoundError,
                                                 get_package_share_directory)
    except ImportError:   # the core runs without ROS; then only a checkout or the variable
        return None
    try:
        return Path(get_package_share_directory('drift_control'))
    except (PackageNotFoundError, OSError):   # not indexed, or AMENT_PREFIX_PATH unset
        return None


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads ``5e-05`` as a number: YAML 1.1 wants a dot in the
    mantissa (``5.0e-05``) and gives the string '5e-05', which Python's own ``repr`` writes."""


YamlLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float', re.compile(r'^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$'),
    list('-+0123456789'))


def parse_yaml(text) -> Any:
    """``yaml.safe_load`` with ``YamlLoader``'s numbers; raises ``yaml.YAMLError``."""
    return yaml.load(text, Loader=YamlLoader)   # noqa: S506 - a SafeLoader


def load_yaml(path: str | os.PathLike) -> dict:
    """Read a YAML mapping; a missing file, bad YAML or a non-mapping is a ParamError."""
    path = Path(path)
    try:
        with open(path, encoding='utf-8') as fh:
            raw = parse_yaml(fh)
    except FileNotFoundError:
        raise ParamError(f'{path}: parameter file not found') from None
    except yaml.YAMLError as err:
        raise ParamError(f'{path}: not valid YAML: {err}') from None
    if not isinstance(raw, dict):
        raise ParamError(f'{path}: expected a mapping at the top level, got {type(raw).__name__}')
    return raw


def from_dict(cls, raw: Any, where: str):
    """Build the dataclass ``cls`` from a YAML mapping; every error names the key.

    Keys starting with ``_`` are documentation (provenance notes) and are ignored. Floats are
    checked to be finite; ints given for float fields are accepted.
    """
    if not isinstance(raw, dict):
        raise ParamError(f'{where}: expected a mapping, got {type(raw).__name__}')
    hints = typing.get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(k for k in raw if k not in names and not str(k).startswith('_'))
    if unknown:
        raise ParamError(f'{where}: unknown key(s) {unknown}')
    kwargs = {}
    for f in fields(cls):
        if f.name not in raw:
            continue
        kwargs[f.name] = _convert(hints[f.name], raw[f.name], f'{where}.{f.name}')
    try:
        return cls(**kwargs)
    except TypeError as err:   # "missing 1 required positional argument: 'D'"
        missing = [f.name for f in fields(cls) if f.name not in kwargs
                   and f.default is MISSING and f.default_factory is MISSING]
        detail = f'missing key(s) {missing}' if missing else str(err)
        raise ParamError(f'{where}: {detail}') from None
    except ParamError:
        raise
    except ValueError as err:
        raise ParamError(f'{where}: {err}') from None


def _convert(hint, value, where: str):
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):   # an optional field: ``float | None``
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None and len(args) < len(typing.get_args(hint)):
            return None
        return _convert(args[0], value, where)
    if is_dataclass(hint):
        return from_dict(hint, value, where)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(f'{where}: expected a number, got {value!r}')
        if not math.isfinite(value):
            raise ParamError(f'{where}: must be finite, got {value!r}')
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamError(f'{where}: expected an integer, got {value!r}')
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ParamError(f'{where}: expected true/false, got {value!r}')
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ParamError(f'{where}: expected a string, got {value!r}')
        return value
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ParamError(f'{where}: expected a list, got {value!r}')
        item = args[0]
        return tuple(_convert(item, v, f'{where}[{i}]') for i, v in enumerate(value))
    if origin is dict:
        key_t, val_t = typing.get_args(hint)
        if not isinstance(value, dict):
            raise ParamError(f'{where}: expected a mapping, got {value!r}')
        return {k: _convert(val_t, v, f'{where}.{k}') for k, v in value.items()}
    if origin is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ParamError(f'{where}: must be one of {list(allowed)}, got {value!r}')
        return value
    return value


def require(condition: bool, where: str, message: str) -> None:
    """Raise ParamError(``where: message``) unless ``condition`` holds (for ``__post_init__``)."""
    if not condition:
        raise ParamError(f'{where}: {message}')


def params_hash(*objs) -> str:
    """A stable short hash of parameter dataclasses (to tie a map file to the model it came from).

    Optional fields left unset (None) are not part of it: adding one keeps the hashes of the
    files that do not use it."""
    text = json.dumps([{k: v for k, v in asdict(o).items() if v is not None} for o in objs],
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --- overrides: --set key=value on every command line and node

def split_override(item: str) -> tuple[str, object]:
    """``'a.b=1.5'`` -> ``('a.b', 1.5)``; the value is parsed as YAML (numbers, lists, bools)."""
    if '=' not in item:
        raise ParamError(f'override {item!r}: expected key=value')
    key, text = item.split('=', 1)
    if not key.strip():
        raise ParamError(f'override {item!r}: expected key=value')
    try:
        value = parse_yaml(text)
    except yaml.YAMLError as err:
        raise ParamError(f'override {item!r}: value is not valid YAML: {err}') from None
    return key.strip(), value


def set_key(raw: dict, dotted: str, value, where: str = '') -> None:
    """Set ``raw[a][b][c] = value`` for ``dotted = 'a.b.c'``; intermediate maps must exist.

    A key that does not exist at its level is still set (the validator then names it if it is
    wrong), but an intermediate that is not a mapping is an error.
    """
    parts = dotted.split('.')
    node = raw
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part)
        if nxt is None:
            nxt = node[part] = {}
        if not isinstance(nxt, dict):
            raise ParamError(f"{where}: override {dotted}: {'.'.join(parts[:i + 1])} is not a "
                             'mapping')
        node = nxt
    node[parts[-1]] = value


def merge(base: dict, extra: dict | None) -> dict:
    """Deep merge of two mappings (``extra`` wins); neither is modified."""
    out = copy.deepcopy(base)
    for key, value in (extra or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_overrides(items, where: str = 'override') -> dict:
    """``['a.b=1', 'c=x']`` -> ``{'a': {'b': 1}, 'c': 'x'}``; empty items are ignored."""
    out: dict = {}
    for item in items or ():
        if item:
            key, value = split_override(item)
            set_key(out, key, value, where=where)
    return out


# --- vehicle and tyres -----------------------------------------------------------------------

@dataclass(frozen=True)
class SimpleMF:
    """Simplified Magic Formula coefficients for one slip direction (paper section II-B)."""

    B: float   # stiffness factor [-]
    C: float   # shape factor [-]
    D: float   # peak friction coefficient on a mu = 1 surface [-]
    E: float = 0.0   # curvature factor [-], <= 1

    def __post_init__(self):
        require(self.B > 0 and self.C > 0 and self.D > 0, 'SimpleMF', 'B, C, D must be positive')
        require(self.E <= 1.0, 'SimpleMF.E', f'must be <= 1, got {self.E}')


@dataclass(frozen=True)
class FrontTyreParams:
    """Front axle: simplified Magic Formula, lateral and longitudinal."""

    lateral: SimpleMF
    longitudinal: SimpleMF


@dataclass(frozen=True)
class CombinedTyreParams:
    """Magic Formula 5.2-style combined-slip coefficients (no shifts, no camber), one axle or wheel.

    Names follow MF 5.2: p* pure slip, r* combined-slip weighting. ``Fz0`` is the nominal load the
    load-sensitivity terms are relative to.
    """

    Fz0: float
    pCx1: float
    pDx1: float
    pDx2: float
    pEx1: float
    pKx1: float
    pKx2: float
    pKx3: float
    pCy1: float
    pDy1: float
    pDy2: float
    pEy1: float
    pKy1: float
    pKy2: float
    rBx1: float
    rBx2: float
    rCx1: float
    rBy1: float
    rBy2: float
    rBy3: float
    rCy1: float

    def __post_init__(self):
        require(self.Fz0 > 0, 'CombinedTyreParams.Fz0', 'must be positive')
        for name in ('pCx1', 'pDx1', 'pKx1', 'pCy1', 'pDy1', 'pKy1', 'pKy2'):
            require(getattr(self, name) > 0, f'CombinedTyreParams.{name}', 'must be positive')
        require(self.pEx1 <= 1 and self.pEy1 <= 1, 'CombinedTyreParams', 'pEx1, pEy1 must be <= 1')


@dataclass(frozen=True)
class ActuatorLimits:
    """Bounds of the controller's inputs and of the steering state."""

    delta_max: float       # road-wheel steering angle [rad]
    delta_dot_max: float   # road-wheel steering rate [rad/s]
    T_R_min: float         # rear axle drive torque [Nm]
    T_R_max: float         # rear axle drive torque [Nm]

    def __post_init__(self):
        require(0 < self.delta_max < 1.5, 'limits.delta_max', 'must be in (0, 1.5) rad')
        require(self.delta_dot_max > 0, 'limits.delta_dot_max', 'must be positive')
        require(self.T_R_min < self.T_R_max, 'limits', 'T_R_min must be below T_R_max')


@dataclass(frozen=True)
class VehicleParams:
    """Single-track model parameters (paper notation: a, b, I_z; per-axle tyres)."""

    m: float          # total mass [kg]
    L: float          # wheelbase [m]
    a: float          # CoG to front axle [m]; b = L - a
    h: float          # CoG height [m]
    I_z: float        # yaw inertia [kg m^2]
    c_drag: float     # 0.5 rho c_d A [kg/m]
    g: float          # gravity [m/s^2]
    R_F: float        # front rolling radius [m]
    R_R: float        # rear rolling radius [m]
    I_wF: float       # front axle spin inertia [kg m^2]
    I_wR: float       # rear axle spin inertia incl. reflected driveline [kg m^2]
    v_eps: float      # slip regularisation speed [m/s]
    limits: ActuatorLimits
    front_tyre: FrontTyreParams
    rear_tyre: CombinedTyreParams
    torque_lag: float | None = None   # this car's request -> wheel torque lag, delay included
                                      # [s] (identified); None: the NMPC's nmpc.torque_lag

    def __post_init__(self):
        for name in ('m', 'L', 'h', 'I_z', 'g', 'R_F', 'R_R', 'I_wF', 'I_wR', 'v_eps'):
            require(getattr(self, name) > 0, f'vehicle.{name}', 'must be positive')
        require(0 < self.a < self.L, 'vehicle.a', f'must lie between 0 and L={self.L}')
        require(self.c_drag >= 0, 'vehicle.c_drag', 'must be >= 0')
        require(self.torque_lag is None or self.torque_lag >= 0, 'vehicle.torque_lag',
                'must be >= 0 (or absent: the NMPC\'s nmpc.torque_lag)')

    @property
    def b(self) -> float:
        """CoG to rear axle [m]."""
        return self.L - self.a


@dataclass(frozen=True)
class Surface:
    """A road surface: the peak friction coefficient the tyre models scale with."""

    name: str
    mu: float

    def __post_init__(self):
        require(0 < self.mu <= 2.0, f'surface {self.name}.mu', f'must be in (0, 2], got {self.mu}')


def load_defaults(config: str | os.PathLike | None = None) -> dict:
    """``config/defaults.yaml``: ``vehicle`` (the default car) and ``maps`` (where maps live,
    relative to the config dir; default ``../maps``), both non-empty strings."""
    path = Path(config or config_dir()) / 'defaults.yaml'
    raw = {'maps': '../maps', **load_yaml(path)}
    unknown = sorted(set(raw) - {'vehicle', 'maps'})
    if unknown:
        raise ParamError(f'{path}: unknown key(s) {unknown}')
    for key in ('vehicle', 'maps'):
        if not isinstance(raw.get(key), str) or not raw[key]:
            raise ParamError(f'{path}: {key}: expected a non-empty string, got {raw.get(key)!r}')
    return raw


def default_vehicle(config: str | os.PathLike | None = None) -> str:
    """The vehicle a run uses when neither its scenario nor the command line names one."""
    return load_defaults(config)['vehicle']


def vehicle_names(config: str | os.PathLike | None = None) -> list[str]:
    """Names of the vehicles under ``config/vehicle`` (every YAML there but ``surfaces.yaml``)."""
    folder = Path(config or config_dir()) / 'vehicle'
    return sorted(p.stem for p in folder.glob('*.yaml') if p.stem != 'surfaces')


def vehicle_file(name: str | None = None, config: str | os.PathLike | None = None) -> Path:
    """``config/vehicle/<name>.yaml`` (default: ``default_vehicle``); unknown names are refused."""
    name = name or default_vehicle(config)
    path = Path(config or config_dir()) / 'vehicle' / f'{name}.yaml'
    if name == 'surfaces' or '/' in name or not path.is_file():
        raise ParamError(f'vehicle {name!r}: no {path}; known vehicles: '
                         f'{", ".join(vehicle_names(config)) or "none"}')
    return path


def load_vehicle(vehicle: str | os.PathLike | None = None,
                 config: str | os.PathLike | None = None) -> VehicleParams:
    """The controller's vehicle parameters: a vehicle name, a YAML file, or the default vehicle."""
    if vehicle is None or (isinstance(vehicle, str) and not vehicle.endswith('.yaml')):
        path = vehicle_file(vehicle, config)
    else:
        path = Path(vehicle)
    return from_dict(VehicleParams, load_yaml(path), f'{path.name}')


def load_surface(name: str, path: str | os.PathLike | None = None) -> Surface:
    """Load a named surface (``dry``, ``wet``) from ``config/vehicle/surfaces.yaml``."""
    path = Path(path) if path else config_dir() / 'vehicle' / 'surfaces.yaml'
    raw = load_yaml(path)
    if name not in raw:
        raise ParamError(f'{path.name}: no surface {name!r}; known: {sorted(raw)}')
    return from_dict(Surface, {'name': name, **raw[name]}, f'{path.name}.{name}')
