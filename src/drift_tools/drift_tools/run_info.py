"""What a recorded run was: its settings, configuration and code version, kept inside the bag.

``scripts/run_stack.py`` collects it before any node starts and the recorder writes it into the
bag as an MCAP metadata record named ``drift_run`` (string values; lists and the configuration
as JSON). ``report.py`` and ``replay.py`` read the scenario and vehicle from it, so a bag can be
judged without remembering how it was made.
"""
from __future__ import annotations

import hashlib
import json
import shlex
import subprocess
from pathlib import Path

RECORD_NAME = 'drift_run'
CONFIG_SUFFIXES = ('.yaml', '.yml', '.dbc', '.arxml', '.tir', '.csv')


KEEP_BYTES = 64 * 1024   # a larger file (a generated ARXML) is kept as its hash, not its text


def config_files(config_dir) -> dict[str, str]:
    """Relative path -> text of every configuration file under ``config_dir`` (a file over
    ``KEEP_BYTES``: ``sha256:<hex>`` and its size, so a bag on a small disk stays small)."""
    root = Path(config_dir)
    return {str(p.relative_to(root)): _text_or_hash(p)
            for p in sorted(root.rglob('*')) if p.is_file() and p.suffix in CONFIG_SUFFIXES}


def _text_or_hash(path: Path) -> str:
    data = path.read_bytes()
    if len(data) > KEEP_BYTES:
        return f'sha256:{hashlib.sha256(data).hexdigest()} ({len(data)} bytes, not kept)'
    return data.decode('utf-8', errors='replace')


def git_version(repo) -> tuple[str, bool | None]:
    """(commit, dirty) of the checkout at ``repo``; ('', None) outside a git checkout."""
    def git(*args):
        return subprocess.run(['git', '-C', str(repo), *args], capture_output=True, text=True,
                              timeout=10)
    try:
        head = git('rev-parse', 'HEAD')
        if head.returncode != 0:
            return '', None
        status = git('status', '--porcelain', '--untracked-files=no')
        return head.stdout.strip(), bool(status.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return '', None


def collect(config_dir, *, scenario: str, vehicle: str, seed: int | None, overrides=(),
            graph: str = '', clock: str = '', argv=(), sensors: str = '', estimator: str = '',
            sensor_faults=()) -> dict[str, str]:
    """The ``drift_run`` record of a run about to start (all values strings)."""
    files = config_files(config_dir)
    blob = json.dumps(files, sort_keys=True).encode()
    commit, dirty = git_version(Path(config_dir).resolve().parent)
    return {
        'scenario': scenario, 'vehicle': vehicle,
        'seed': '' if seed is None else str(seed),
        'overrides': json.dumps(list(overrides)),
        'graph': graph, 'clock': clock,
        'sensors': sensors, 'estimator': estimator,   # '': the plant's measured state
        'sensor_faults': json.dumps(list(sensor_faults)),
        'command_line': shlex.join(str(a) for a in argv),
        'commit': commit, 'dirty': '' if dirty is None else str(dirty).lower(),
        'config_dir': str(Path(config_dir).resolve()),
        'config_sha256': hashlib.sha256(blob).hexdigest(),
        'config': blob.decode(),
    }


def read_run_info(bag_dir) -> dict[str, str] | None:
    """The bag's ``drift_run`` record, or None (a bag from elsewhere, or recorded before it)."""
    from drift_tools.bag import is_finished
    from drift_tools.bag_salvage import bag_file, scan_bag
    if is_finished(bag_dir):
        from mcap.reader import make_reader
        try:
            with open(bag_file(bag_dir), 'rb') as fh:
                for record in make_reader(fh).iter_metadata():
                    if record.name == RECORD_NAME:
                        return dict(record.metadata)
            return None
        except Exception:   # noqa: BLE001 - a damaged index: fall back to the scanner
            pass
    for record in scan_bag(bag_dir).metadata:
        if record.name == RECORD_NAME:
            return dict(record.metadata)
    return None


def run_scenario(info: dict | None, config=None):
    """The scenario a recorded run drove (its overrides and vehicle applied), or None."""
    if not info or not info.get('scenario'):
        return None
    from drift_control.params import ParamError
    from drift_control.scenario import load_scenario_spec
    try:
        overrides = json.loads(info.get('overrides') or '[]')
        return load_scenario_spec(info['scenario'], overrides, config,
                                  vehicle=info.get('vehicle') or None)
    except (ParamError, ValueError):
        return None
