"""Randomized plants: ``config/sim/populations/<vehicle>.yaml`` loaded, checked and drawn from.

A population says how far a car may be from its nominal plant (``config/sim/plants/<vehicle>.
yaml``): each parameter is a uniform range, relative to the nominal value, an offset from it or
an absolute value, and names the plant keys it moves (``plant.body.m``), ``surface.mu`` or the
keys of the car's sensor units (``sensors.ins.channels.beta.std``, ``config/sim/sensors/``):
those apply in runs with the sensor units only (``load_population(sensors=...)``).

    population = load_population('gr86', scenario='steady_dry')
    plant = draw(population, index=7, seed=0)     # Draw(overrides, values)
    run_closed_loop('steady_dry', plant.overrides, vehicle='gr86')

Draw ``k`` depends on ``(seed, k)`` and the parameter's name only, so it is the same plant
whichever order a campaign runs its draws in, and in every scenario of the campaign.
"""
from __future__ import annotations

import fnmatch
import os
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from drift_control.params import ParamError, config_dir, load_surface, load_yaml, merge
from drift_control.scenario import load_scenario_spec, surface_mu
from drift_sim.params import load_plant_params, plant_yaml
from drift_sim.sensors import load_sensor_params, sensors_file

KINDS = ('relative', 'offset', 'absolute')   # nominal x (1 + u), nominal + u, u
SURFACE_MU = 'surface.mu'                    # the one drawn key outside the plant file
SENSORS = 'sensors.'                         # prefix of the sensor units' keys
DEFAULT_SENSORS = 'realistic'                # the set a population's sensor keys are checked on


@dataclass(frozen=True)
class Range:
    """One randomized parameter: ``u ~ U(low, high)`` applied to its keys as ``kind`` says."""

    name: str
    keys: tuple[str, ...]   # dotted override keys, wildcards expanded
    kind: str               # one of KINDS
    low: float              # [-] for 'relative', else the keys' SI unit
    high: float
    why: str                # the reason for the range, one line


@dataclass(frozen=True)
class Population:
    """A car's randomized plants around its nominal plant in one scenario."""

    vehicle: str
    file: Path
    ranges: tuple[Range, ...]
    nominal: dict            # dotted key -> nominal value of every drawn key
    not_modelled: dict       # parameter -> why it has no plant key and is not drawn
    sensors: str = ''        # the sensor set its ``sensors.`` keys apply to; '': none apply


class Draw(NamedTuple):
    """One plant of a population."""

    overrides: tuple[str, ...]   # ``key=value`` strings for ``run_closed_loop``
    values: dict                 # parameter name -> drawn ``u`` in its range's units
    sensor_set: tuple[str, ...] = ()   # ``unit.channels.x.std=value``: its ``sensor_set``


def population_file(vehicle: str, config: str | os.PathLike | None = None) -> Path:
    """``config/sim/populations/<vehicle>.yaml``."""
    return Path(config or config_dir()) / 'sim' / 'populations' / f'{vehicle}.yaml'


def load_population(vehicle: str, scenario: str | None = None, overrides=(),
                    config: str | os.PathLike | None = None,
                    file: str | os.PathLike | None = None, sensors: str = '') -> Population:
    """Load and check a vehicle's population; every error names the file and the key.

    Parameters
    ----------
    vehicle : str
        ``config/vehicle/<name>.yaml`` car; its plant file gives the nominal values.
    scenario : str, optional
        The scenario's ``plant:`` section and ``overrides`` move the nominal plant, its surface
        gives the nominal road friction; without one, the plant file on the dry surface
        (``load_setup``'s default surface).
    file : path, optional
        Another population file (default ``population_file(vehicle, config)``).
    sensors : str, optional
        The runs' sensor set (``config/sim/sensors/<name>.yaml``): the ``sensors.`` keys are
        drawn relative to its values. Without one they are checked on ``DEFAULT_SENSORS`` and
        not drawn (the plant's measurement model stands in for the sensor units).
    """
    config = Path(config or config_dir())
    file = Path(file) if file else population_file(vehicle, config)
    if not file.is_file():
        raise ParamError(f'vehicle {vehicle!r}: no plant population {file}')
    where = file.name
    params, not_modelled = _read(file)
    plant_raw, nominal = _nominal(vehicle, scenario, overrides, config)
    nominal.update(_numeric_leaves(load_yaml(sensors_file(sensors or DEFAULT_SENSORS, config)),
                                   SENSORS.rstrip('.')))
    ranges = tuple(_range(name, raw, nominal, f'{where}: parameters.{name}')
                   for name, raw in params.items())
    drawn_by: dict[str, str] = {}
    for r in ranges:
        for key in r.keys:
            if key in drawn_by:
                raise ParamError(f'{where}: parameters.{r.name}: {key} is drawn by '
                                 f'{drawn_by[key]} already')
            drawn_by[key] = r.name
    population = Population(vehicle, file, ranges, {k: nominal[k] for k in drawn_by},
                            not_modelled, sensors or DEFAULT_SENSORS)
    _check_ends(population, plant_raw, where, config)
    if sensors:
        return population
    # checked, but not drawn: these runs have no sensor units
    ranges = tuple(replace(r, keys=tuple(k for k in r.keys if not k.startswith(SENSORS)))
                   for r in ranges)
    return replace(population, ranges=ranges, sensors='',
                   nominal={k: v for k, v in population.nominal.items()
                            if not k.startswith(SENSORS)})


def _read(file: Path) -> tuple[dict, dict]:
    """The file's ``parameters`` and ``not_modelled`` mappings, their shapes checked."""
    raw = load_yaml(file)
    unknown = sorted(k for k in raw if k not in ('parameters', 'not_modelled')
                     and not str(k).startswith('_'))
    if unknown:
        raise ParamError(f'{file.name}: unknown key(s) {unknown}; expected parameters, '
                         'not_modelled')
    params = raw.get('parameters')
    if not isinstance(params, dict) or not params:
        raise ParamError(f'{file.name}: parameters: expected a mapping of parameter ranges')
    not_modelled = raw.get('not_modelled') or {}
    if not isinstance(not_modelled, dict) or not all(isinstance(v, str) and v.strip()
                                                     for v in not_modelled.values()):
        raise ParamError(f'{file.name}: not_modelled: expected parameter: reason lines')
    return params, dict(not_modelled)


def _nominal(vehicle: str, scenario: str | None, overrides, config: Path) -> tuple[dict, dict]:
    """The raw plant mapping a run starts from, and every number in it by dotted key (with
    ``surface.mu``, the scenario's surface friction)."""
    if scenario:
        spec = load_scenario_spec(scenario, overrides, config, vehicle=vehicle)
        plant_raw = merge(plant_yaml(config, vehicle), spec.plant)
        mu = surface_mu(spec, config)
    else:
        plant_raw = plant_yaml(config, vehicle)
        mu = load_surface('dry', config / 'vehicle' / 'surfaces.yaml').mu
    return plant_raw, dict(_numeric_leaves(plant_raw, 'plant'), **{SURFACE_MU: mu})


def draw(population: Population, index: int, seed: int = 0) -> Draw:
    """Plant ``index`` of ``population``: the same overrides for the same ``(seed, index)``.

    Each parameter has its own stream, seeded by ``(seed, index, crc32(name))``: adding or
    removing a parameter leaves the others' draws as they were.
    """
    if index < 0 or seed < 0:
        raise ValueError(f'draw: index and seed must be >= 0, got {index}, {seed}')
    overrides, sensor_set, values = [], [], {}
    for r in population.ranges:
        rng = np.random.default_rng([seed, index, zlib.crc32(r.name.encode())])
        u = float(f'{rng.uniform(r.low, r.high):.6g}')
        values[r.name] = u
        for key in r.keys:
            item = f'{key}={_apply(r.kind, population.nominal[key], u):.6g}'
            if key.startswith(SENSORS):
                sensor_set.append(item.removeprefix(SENSORS))
            else:
                overrides.append(item)
    return Draw(tuple(overrides), values, tuple(sensor_set))


def _apply(kind: str, nominal: float, u: float) -> float:
    if kind == 'relative':
        return nominal * (1.0 + u)
    if kind == 'offset':
        return nominal + u
    return u


def _numeric_leaves(raw: dict, prefix: str):
    """``('plant.body.m', 1830.0)`` for every number of a nested mapping ("_" keys are notes)."""
    for key, value in raw.items():
        if str(key).startswith('_'):
            continue
        dotted = f'{prefix}.{key}'
        if isinstance(value, dict):
            yield from _numeric_leaves(value, dotted)
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield dotted, float(value)


def _range(name: str, raw, leaves: dict, where: str) -> Range:
    if not isinstance(raw, dict):
        raise ParamError(f'{where}: expected a mapping with keys, one of {list(KINDS)} and why')
    unknown = sorted(set(raw) - {'keys', 'why', *KINDS})
    if unknown:
        raise ParamError(f'{where}: unknown key(s) {unknown}')
    kinds = [k for k in KINDS if k in raw]
    if len(kinds) != 1:
        raise ParamError(f'{where}: needs exactly one of {list(KINDS)}, got {kinds or "none"}')
    kind = kinds[0]
    bounds = raw[kind]
    if (not isinstance(bounds, list) or len(bounds) != 2
            or not all(isinstance(b, (int, float)) and not isinstance(b, bool) for b in bounds)
            or not bounds[0] <= bounds[1]):
        raise ParamError(f'{where}.{kind}: expected [low, high] numbers with low <= high, '
                         f'got {bounds!r}')
    if kind == 'relative' and bounds[0] <= -1.0:
        raise ParamError(f'{where}.relative: low must be above -1 (a factor 1 + low > 0)')
    why = raw.get('why')
    if not isinstance(why, str) or not why.strip():
        raise ParamError(f'{where}.why: the reason for the range is missing')
    patterns = raw.get('keys')
    if not isinstance(patterns, list) or not patterns or not all(isinstance(p, str)
                                                                 for p in patterns):
        raise ParamError(f'{where}.keys: expected a list of plant.* or {SENSORS}* keys or '
                         f'{SURFACE_MU}')
    keys = []
    for pattern in patterns:
        if not (pattern.startswith(('plant.', SENSORS)) or pattern == SURFACE_MU):
            raise ParamError(f'{where}.keys: {pattern}: only plant.* and {SENSORS}* keys and '
                             f'{SURFACE_MU} are drawn')
        found = sorted(k for k in leaves if fnmatch.fnmatchcase(k, pattern))
        if not found:
            what = 'the sensor units' if pattern.startswith(SENSORS) else 'the plant'
            raise ParamError(f'{where}.keys: {pattern} names no number of {what}')
        keys += found
    return Range(name, tuple(keys), kind, float(bounds[0]), float(bounds[1]), why.strip())


def _check_ends(population: Population, plant_raw: dict, where: str, config: Path) -> None:
    """Each range's two ends must give a plant (and sensor units) their own validation
    accepts."""
    for r in population.ranges:
        for u in (r.low, r.high):
            values = {k: _apply(r.kind, population.nominal[k], u) for k in r.keys}
            mu = values.pop(SURFACE_MU, None)
            if mu is not None and not 0.0 < mu <= 2.0:
                raise ParamError(f'{where}: parameters.{r.name}: {SURFACE_MU}={mu:g} at '
                                 f'u = {u:g} is outside (0, 2]')
            items = [f'{k.removeprefix("plant.")}={v!r}' for k, v in values.items()
                     if k.startswith('plant.')]
            sensed = [f'{k.removeprefix(SENSORS)}={v!r}' for k, v in values.items()
                      if k.startswith(SENSORS)]
            try:
                load_plant_params(plant_raw, items)
                if sensed:
                    load_sensor_params(population.sensors, config, sensed)
            except ParamError as err:
                raise ParamError(f'{where}: parameters.{r.name} at u = {u:g}: {err}') from None


__all__ = ['DEFAULT_SENSORS', 'Draw', 'KINDS', 'Population', 'Range', 'SENSORS', 'draw',
           'load_population', 'population_file']
