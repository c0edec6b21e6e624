"""A plant's controller model identified from the plant's own log, as a team does with its car.

    config, name = identified_car('m3_competition', draw=7, plant_seed=0)
    run_seed('alternating_dry', overrides, 0, config, vehicle=name)   # the drawn plant, its model

The plant (a population draw, or the nominal one) drives the three-minute identification
manoeuvre (``scripts/sysid_drive.py``, ``sysid_dry``: the draw's road friction on the dry pad);
``scripts/identify.py`` fits the tyres and the powertrain lag to that log from the data sheet
(``config/vehicle/<car>.yaml``); the maps are built for the identified car. The result is a
config directory with the car as ``<car>_id<draw>`` (and a copy of the plant file under that
name, so the same drawn plant is simulated), prepared once per plant and configuration and
kept under ``cache_root()``; concurrent workers wait for one another on a lock.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from drift_control.params import ParamError, config_dir, load_defaults
from drift_control.sysid import DEFAULT_FIT

SYSID_SCENARIO = 'sysid_dry'
SURFACES = ('dry', 'wet')
#: what is fitted when the log cannot identify the front tyre (the rear alone, the lag)
REAR_FIT = tuple(name for name in DEFAULT_FIT if name.startswith('rear_tyre.'))


class IdentificationFailed(RuntimeError):
    """The plant's log could not identify a controller model: the message says why."""


def cache_root() -> Path:
    """Where identified cars are kept: ``$DRIFT_IDENTIFIED_DIR``, else the user's cache."""
    if os.environ.get('DRIFT_IDENTIFIED_DIR'):
        return Path(os.environ['DRIFT_IDENTIFIED_DIR'])
    base = Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache')
    return base / 'drift_stack' / 'identified'


def sysid_overrides(vehicle: str, draw: int | None, plant_seed: int | None,
                    config: str | None = None) -> tuple[str, ...]:
    """The plant draw's overrides on the identification manoeuvre's scenario (its road
    friction relative to the dry pad's): () for the nominal plant."""
    if draw is None:
        return ()
    from drift_sim.population import draw as draw_plant, load_population
    population = load_population(vehicle, SYSID_SCENARIO, (), config)
    return draw_plant(population, draw, plant_seed or 0).overrides


def identified_name(vehicle: str, draw: int | None) -> str:
    """The identified car's name: ``<car>_id<draw>`` (``<car>_id`` for the nominal plant)."""
    return f'{vehicle}_id{"" if draw is None else draw}'


def identified_car(vehicle: str, draw: int | None, plant_seed: int | None,
                   config: str | None = None, digest: str = '') -> tuple[str, str]:
    """(config directory, vehicle name) of ``vehicle``'s plant ``draw`` with its controller
    model identified from that plant's own log; prepared on first use.

    ``digest`` (the configuration's, ``campaign.config_digest``) keys the cache with the
    plant's overrides and the parameters fitted: another configuration, draw or fit is another
    car.
    """
    source = Path(config or config_dir())
    overrides = sysid_overrides(vehicle, draw, plant_seed, config)
    key = hashlib.sha256(json.dumps([vehicle, list(overrides), digest, list(DEFAULT_FIT)])
                         .encode()).hexdigest()[:12]
    name = identified_name(vehicle, draw)
    home = cache_root() / f'{name}_{key}'
    out = home / 'config'
    if (home / 'ready').is_file():
        return str(out), name
    home.parent.mkdir(parents=True, exist_ok=True)
    with open(home.parent / f'{home.name}.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)          # another worker may be preparing it
        if not (home / 'ready').is_file():
            _prepare(home, source, vehicle, name, overrides)
    return str(out), name


def _prepare(home: Path, source: Path, vehicle: str, name: str, overrides) -> None:
    shutil.rmtree(home, ignore_errors=True)
    out = home / 'config'
    shutil.copytree(source, out, ignore=shutil.ignore_patterns('.codegen'))
    maps = (out / load_defaults(out)['maps']).resolve()
    if not str(maps).startswith(str(home.resolve())):
        raise ParamError(f'{source}/defaults.yaml: maps must lie beside the config directory '
                         'for an identified copy (maps: ../maps)')
    maps.mkdir(parents=True, exist_ok=True)
    for sub in ('sim/plants', 'sim/populations'):
        if (out / sub / f'{vehicle}.yaml').is_file():
            shutil.copy(out / sub / f'{vehicle}.yaml', out / sub / f'{name}.yaml')
    scripts = config_dir().parent / 'scripts'
    sets = [word for item in overrides for word in ('--set', item)]
    _script(scripts / 'sysid_drive.py', '--scenario', SYSID_SCENARIO, '--vehicle', vehicle,
            '--seed', '0', *sets, '--config-dir', str(out), '--bag', str(home / 'bag'))
    identify = [scripts / 'identify.py', str(home / 'bag'), '--vehicle', vehicle, '--out',
                str(out / 'vehicle' / f'{name}.yaml'), '--config-dir', str(out),
                '--report', str(home / 'report'), '--no-figures']
    try:
        _script(*identify)
    except IdentificationFailed:   # e.g. the front never near its limit: the rear and the lag
        _script(*identify, '--fit', ','.join(REAR_FIT))
    for surface in SURFACES:
        _script(scripts / 'build_maps.py', '--vehicle', name, '--surface', surface, '--jobs',
                '1', '--config-dir', str(out))
    (home / 'ready').write_text(name + '\n')


def _script(script, *args) -> None:
    done = subprocess.run([sys.executable, str(script), *map(str, args)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ['(no message)'])[-1]
        raise IdentificationFailed(f'{Path(script).name}: {last}')


__all__ = ['IdentificationFailed', 'REAR_FIT', 'SYSID_SCENARIO', 'cache_root', 'identified_car',
           'identified_name', 'sysid_overrides']
