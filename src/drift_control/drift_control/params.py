"""Parameters as data: YAML files under ``config/`` loaded into frozen, validated dataclasses.

This is the one place that reads configuration. Every error names the offending key with its full
path (``vehicle.rear_tyre.pKx1``) so a typo in a YAML file is found at start-up, not in a solver.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import typing
from dataclasses import MISSING, asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml


class ParamError(ValueError):
    """A parameter file or value is missing, unknown, of the wrong type or out of range."""


def config_dir() -> Path:
    """The project's ``config/`` directory: ``$DRIFT_CONFIG_DIR`` or the one of this checkout."""
    env = os.environ.get('DRIFT_CONFIG_DIR')
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / 'config'


def load_yaml(path: str | os.PathLike) -> dict:
    """Read a YAML mapping; a missing file, bad YAML or a non-mapping is a ParamError."""
    path = Path(path)
    try:
        with open(path, encoding='utf-8') as fh:
            raw = yaml.safe_load(fh)
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
    """A stable short hash of parameter dataclasses (to tie a map file to the model it came from)."""
    text = json.dumps([asdict(o) for o in objs], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
