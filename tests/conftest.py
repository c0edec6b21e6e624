"""Shared test fixtures: ROS isolation (own domain id, localhost discovery) and the repo paths.

Tests marked ``ros`` are skipped, with the reason, where rclpy or the built drift_msgs is missing.
Under pytest-xdist (``make test``: a worker per core, at most four) tests marked ``ros`` or ``realtime`` run alone
(``run_alone.py``).
"""
import importlib.util
import itertools
import os
import sys
from pathlib import Path

import pytest

from run_alone import RoomLock, keep_after, run_alone_first, runs_alone, scheduling

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / 'tests'
PYTHON = sys.executable



def load_script(name: str):
    """``scripts/<name>.py`` imported as a module, so a test can call its ``main(argv)``."""
    spec = importlib.util.spec_from_file_location(name, REPO / 'scripts' / f'{name}.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# Domain ids 10..29 belong to the drift_tools / drift_msgs tests; each ros test gets the next one.
_TOOLS_DOMAINS = itertools.cycle(range(10, 30))


def _ros_missing() -> str:
    for module in ('rclpy', 'drift_msgs'):
        if importlib.util.find_spec(module) is None:
            return f'{module} not importable'
    return ''


def pytest_collection_modifyitems(config, items):
    reason = _ros_missing()
    if reason:
        skip = pytest.mark.skip(reason=f'ros test: {reason}')
        for item in items:
            if 'ros' in item.keywords:
                item.add_marker(skip)
    if _ROOM is not None:
        run_alone_first(items, _ROOM.ids_file)


_ROOM = None        # this xdist worker's RoomLock; None outside xdist
_OWN_LOCK_DIR = None   # the lock's directory, made by the xdist controller for its workers
_LOCK_DIR = 'DRIFT_TESTS_LOCK_DIR'


def pytest_configure(config):
    global _ROOM, _OWN_LOCK_DIR
    if hasattr(config, 'workerinput'):              # an xdist worker (never a nested pytest)
        if os.environ.get(_LOCK_DIR):
            _ROOM = RoomLock(Path(os.environ[_LOCK_DIR]) / 'room')
    elif getattr(config.option, 'numprocesses', None):
        import tempfile
        _OWN_LOCK_DIR = os.environ[_LOCK_DIR] = tempfile.mkdtemp(prefix='drift-tests-')


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``: the tests that run alone as the first unit (run_alone.py)."""
    if _OWN_LOCK_DIR is not None and config.getvalue('dist') == 'loadfile':
        return scheduling(config, log, Path(_OWN_LOCK_DIR) / 'room.alone')
    return None


def pytest_unconfigure(config):
    if _ROOM is not None:
        _ROOM.close()
    if _OWN_LOCK_DIR is not None:
        import shutil
        shutil.rmtree(_OWN_LOCK_DIR, ignore_errors=True)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Around setup, call and teardown: alone for ``ros``/``realtime`` tests, else beside others."""
    if _ROOM is None:
        return (yield)
    _ROOM.enter(runs_alone(item))
    try:
        return (yield)
    finally:
        if not keep_after(item, nextitem):
            _ROOM.leave()


@pytest.fixture
def tools_domain_id(monkeypatch):
    """A ROS domain id from 10..29 for this test, set (with LOCALHOST discovery) in os.environ."""
    domain = next(_TOOLS_DOMAINS)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return domain


@pytest.fixture
def node_env(tools_domain_id):
    """Environment for child node processes: the test domain, and tests/ importable."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(TESTS), env.get('PYTHONPATH', '')]))
    env['PYTHONUNBUFFERED'] = '1'
    return env


# --- the default car's NMPC, shared by the NMPC and fault tests (built once per module) ---------

@pytest.fixture(scope='module')
def vp():
    """The default vehicle's controller parameters."""
    from drift_control.params import load_vehicle
    return load_vehicle()


@pytest.fixture(scope='module')
def eq30(vp):
    """The 30 deg left drift equilibrium on R = 15 m, dry."""
    import math
    from drift_control.equilibrium import solve_equilibrium
    sol = solve_equilibrium(math.radians(-30.0), 15.0, vp)
    assert sol.converged
    return sol.eq


@pytest.fixture(scope='module')
def nmpc(vp):
    """The configured (compiled, cached under .codegen/) solver."""
    from drift_control.nmpc import Nmpc
    from drift_control.ocp import load_nmpc_params
    return Nmpc(vp, load_nmpc_params())
