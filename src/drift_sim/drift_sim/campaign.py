"""Campaigns: closed-loop runs as jobs (scenario x vehicle x plant draw x seed), run and stored.

    jobs = campaign_jobs(['steady_dry'], ['gr86'], seeds=[0, 1], plants=10)
    with make_executor(workers=2) as pool:                  # drift_sim.executor
        rows = run_jobs(jobs, pool, RunStore('runs/c.jsonl'))
    print(format_campaign(campaign_summary(rows)))          # drift_sim.sweep

A job is data: the hash of its configuration keys the store (``drift_sim.store``), so running
the same jobs again skips those already finished; the configuration counts by its values
(``config_digest``), so a run is redone when a value it reads changed, not when a comment did.
A row is the job's configuration with the run's outcome, metrics (``drift_sim.sweep.run_seed``)
and the command that replays it.
"""
from __future__ import annotations

import hashlib
import json
import shlex
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from drift_control.estimator import ESTIMATORS
from drift_control.assembly import maps_dir
from drift_control.params import ParamError, config_dir, load_yaml, require, vehicle_file
from drift_control.scenario import load_scenario_spec, scenario_file, scenario_names
from drift_sim.population import draw, load_population
from drift_sim.scenario import load_scenario
from drift_sim.sensors import load_sensor_params
from drift_sim.sweep import ERROR, outcome, run_seed


@dataclass(frozen=True)
class Job:
    """One closed loop: a scenario on a vehicle's plant (nominal or drawn) with a seed."""

    scenario: str
    vehicle: str
    seed: int                         # friction field, noise and driver
    overrides: tuple[str, ...] = ()   # the campaign's ``key=value``s, then the plant draw's
    draw: int | None = None           # index in the vehicle's population; None: nominal plant
    plant_seed: int | None = None     # the population's seed (with ``draw``)
    values: dict = field(default_factory=dict, compare=False)   # drawn u per parameter
    config: str | None = None         # config directory; None: the checkout's
    config_digest: str = ''           # its values and maps (``config_digest``)
    code: str = field(default='', compare=False)   # the checkout's commit (``code_version``)
    sensors: str = ''                 # the car's sensor units ('realistic'); '': plant's noise
    estimator: str = ''               # with sensors: 'ekf' or 'none'
    sensor_set: tuple[str, ...] = ()  # with sensors: the draw's sensor overrides
    identify: bool = False            # the controller's model identified from this plant's own
                                      # log first (``drift_sim.identified``): not the data sheet

    @property
    def key(self) -> str:
        """Hash of everything that decides the run (the drawn values are in the overrides,
        the configuration by its digest, not its directory's name); the sensors only when set,
        so that the keys of runs without them stay as they were."""
        fields = [self.scenario, self.vehicle, self.seed, list(self.overrides), self.draw,
                  self.plant_seed, self.config_digest]
        if self.sensors:
            fields += [self.sensors, self.estimator, list(self.sensor_set)]
        if self.identify:
            fields += ['identify']
        return hashlib.sha256(json.dumps(fields).encode()).hexdigest()[:16]

    def replay_command(self) -> str:
        """The ``scripts/simulate.py`` command line that runs this job alone."""
        words = ['.venv/bin/python', 'scripts/simulate.py', '--scenario', self.scenario,
                 '--vehicle', self.vehicle, '--seed', str(self.seed)]
        for item in self.overrides:
            words += ['--set', item]
        if self.config:
            words += ['--config-dir', self.config]
        if self.sensors:
            words += ['--sensors', self.sensors, '--estimator', self.estimator or 'none']
            for item in self.sensor_set:
                words += ['--sensor-set', item]
        return ' '.join(shlex.quote(w) for w in words)

    def row(self) -> dict:
        """The job's full configuration as a store row's head."""
        return {'key': self.key, 'scenario': self.scenario, 'vehicle': self.vehicle,
                'seed': self.seed, 'draw': self.draw, 'plant_seed': self.plant_seed,
                'overrides': list(self.overrides), 'values': dict(self.values),
                'config': self.config, 'config_digest': self.config_digest, 'code': self.code,
                'replay': self.replay_command(),
                **({'sensors': self.sensors, 'estimator': self.estimator,
                    'sensor_set': list(self.sensor_set)} if self.sensors else {}),
                **({'identify': True} if self.identify else {})}


def config_digest(config=None) -> str:
    """Digest of what runs read from a configuration directory: every file under it (a YAML
    file by its values: comments and layout do not count) and the equilibrium maps it uses.
    Copies with the same values share it; a changed value changes it. A file that does not
    parse counts by its bytes: refusing it is for the run that reads it, if any."""
    root = Path(config or config_dir())
    digest = hashlib.sha256()
    for base in (root, maps_dir(root)):
        for path in sorted(p for p in base.rglob('*') if p.is_file()):
            data = path.read_bytes()
            if path.suffix in ('.yaml', '.yml'):
                try:
                    data = json.dumps(load_yaml(path), sort_keys=True, default=str).encode()
                except ParamError:
                    pass
            digest.update(path.relative_to(base).as_posix().encode() + b'\0' + data + b'\0')
    return digest.hexdigest()[:16]


def code_version() -> str:
    """The checkout's commit, ``+dirty`` with uncommitted changes to tracked files; '' outside
    a git checkout. Not in a run's key (most commits change no result): it shows a store that
    was resumed on other code."""
    def git(*args):
        return subprocess.run(['git', '-C', str(config_dir()), *args], capture_output=True,
                              text=True, timeout=10)
    try:
        head = git('rev-parse', '--short', 'HEAD')
        if head.returncode != 0:
            return ''
        dirty = git('status', '--porcelain', '--untracked-files=no').stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ''
    return head.stdout.strip() + ('+dirty' if dirty else '')


def scenario_vehicle(scenario: str, overrides=(), config=None) -> str:
    """The vehicle a scenario runs with these overrides (``vehicle:``, else the default)."""
    return load_scenario_spec(scenario, overrides, config).vehicle


def check_run(scenario: str, vehicle: str, overrides=(), config=None) -> None:
    """Refuse an unknown scenario or vehicle, or bad overrides, before any run starts."""
    file = scenario_file(scenario, config)
    if not file.is_file():
        raise ParamError(f'scenario {scenario!r}: no {file}; known scenarios: '
                         f'{", ".join(scenario_names(config)) or "none"}')
    vehicle_file(vehicle, config)
    load_scenario(scenario, overrides, config, vehicle=vehicle)   # with its plant and path


def campaign_jobs(scenarios, vehicles, seeds, plants: int | Sequence[int] = 0, overrides=(),
                  plant_seed: int = 0, config: str | None = None, sensors: str = '',
                  estimator: str = '', identify: bool = False) -> list[Job]:
    """Every scenario x vehicle x plant x seed; ParamError names bad input.

    Ordered plant by plant (then seed), each with every scenario and vehicle: a campaign
    stopped part way has covered every scenario and car alike.

    Parameters
    ----------
    plants : int or sequence of int
        Draws ``0 .. plants - 1`` of each vehicle's population
        (``config/sim/populations/<vehicle>.yaml``), or the draws listed; 0 or none: the
        nominal plant only.
    overrides : iterable of str
        ``key=value`` for every run (``duration=2``); the draws are relative to the plant they
        leave.
    identify : bool
        Each plant's controller model identified from its own log (``drift_sim.identified``).
    """
    overrides = tuple(overrides)
    draws = range(plants) if isinstance(plants, int) else sorted(set(plants))
    if isinstance(plants, int) and plants < 0 or any(d < 0 for d in draws):
        raise ParamError(f'plants: expected draws >= 0, got {plants}')
    if estimator and not sensors:
        raise ParamError('estimator: needs sensors (the estimator fuses the sensor units)')
    if sensors:
        load_sensor_params(sensors, config)
        require(estimator in ESTIMATORS, 'estimator',
                f'{estimator!r} is not one of {list(ESTIMATORS)}')
    sensed = {'sensors': sensors, 'estimator': estimator, 'config_digest': config_digest(config),
              'code': code_version(), 'identify': identify}
    runs = {}   # (draw, seed) -> the jobs of every scenario and vehicle
    for scenario in scenarios:
        for vehicle in vehicles:
            check_run(scenario, vehicle, overrides, config)
            if not draws:
                for seed in seeds:
                    runs.setdefault((None, seed), []).append(
                        Job(scenario, vehicle, seed, overrides, config=config, **sensed))
                continue
            population = load_population(vehicle, scenario, overrides, config, sensors=sensors)
            for index in draws:
                plant = draw(population, index, plant_seed)
                for seed in seeds:
                    runs.setdefault((index, seed), []).append(
                        Job(scenario, vehicle, seed, overrides + plant.overrides, index,
                            plant_seed, plant.values, config, **sensed,
                            sensor_set=plant.sensor_set))
    return [job for batch in runs.values() for job in batch]


def run_job(job: Job) -> dict:
    """Run one job in this process: its store row (``outcome`` is drift_sim.sweep's).

    With ``identify`` the run's controller drives the identified copy of the car (prepared on
    first use; its config directory and name are in the row, and the replay command uses them).
    """
    config, vehicle, extra = job.config, job.vehicle, {}
    if job.identify:
        from drift_sim.identified import identified_car
        config, vehicle = identified_car(job.vehicle, job.draw, job.plant_seed, job.config,
                                         job.config_digest)
        replay = replace(job, vehicle=vehicle, config=config, identify=False)
        extra = {'identified': {'vehicle': vehicle, 'config': config},
                 'replay': replay.replay_command()}
    metrics, wall = run_seed(job.scenario, job.overrides, job.seed, config,
                             vehicle=vehicle, sensors=job.sensors, estimator=job.estimator,
                             sensor_set=job.sensor_set)
    return {**job.row(), **extra, 'outcome': outcome(metrics), 'wall_s': wall,
            'host': socket.gethostname(), 'finished': time.time(), 'metrics': metrics}


def error_row(job: Job, err: BaseException) -> dict:
    """The row of a job whose worker failed (not the closed loop: ``run_seed`` catches that)."""
    first = (str(err).strip().splitlines() or [''])[0]
    metrics = {'error': f'{type(err).__name__}: {first}'}
    return {**job.row(), 'outcome': ERROR, 'wall_s': None, 'host': None,
            'finished': time.time(), 'metrics': metrics}


def run_jobs(jobs: list[Job], executor, store, progress: bool = True,
             on_row=None) -> list[dict]:
    """Run the jobs the store has not finished; return every job's row, in the jobs' order.

    Each row is in the store before the next is looked at, so an interruption (Ctrl-C raises
    KeyboardInterrupt here) loses no finished run. ``on_row(row)`` sees each new row.
    """
    todo = list({job.key: job for job in jobs if job.key not in store}.values())
    if todo:
        from tqdm import tqdm
        done = len({job.key for job in jobs}) - len(todo)
        counts: dict[str, int] = {}
        with tqdm(total=done + len(todo), initial=done, unit='run', file=sys.stderr,
                  disable=not progress, dynamic_ncols=True, smoothing=0.1) as bar:
            results = executor.map_unordered(run_job, todo)
            try:
                for job, result in results:
                    row = result if isinstance(result, dict) else error_row(job, result)
                    store.add(row)
                    counts[row['outcome']] = counts.get(row['outcome'], 0) + 1
                    bar.set_postfix(counts, refresh=False)
                    bar.update(1)
                    if on_row is not None:
                        on_row(row)
            finally:   # interrupted: the executor stops what still runs, now
                results.close()
    return [store.get(job.key) for job in jobs]


def default_config(config: str | Path | None) -> str | None:
    """A job's ``config``: None for the checkout's own directory (hashes stay portable)."""
    if config is None or Path(config).resolve() == config_dir().resolve():
        return None
    return str(Path(config).resolve())


__all__ = ['Job', 'campaign_jobs', 'check_run', 'default_config', 'error_row', 'run_job',
           'run_jobs', 'scenario_vehicle']
