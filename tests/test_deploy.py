"""Deployable the ROS way: each package.xml lists what its package imports, config/ and maps/ are
found in an install space, and a colcon build of src/ starts a node outside the checkout.

The colcon test installs colcon (``requirements-colcon.txt``, the lock file as constraints) into a
folder of its own under the venv, kept for later runs, and runs it with this interpreter on
``PYTHONPATH``: never into the venv, whose pytest would load the plugins colcon pulls in
(pytest-rerunfailures and others).
"""
import ast
import hashlib
import importlib.util
import json
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from drift_control import params
from drift_control.assembly import maps_dir
from drift_control.params import ParamError, cache_dir, config_dir

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ('drift_control', 'drift_sim', 'drift_vehicle_bridge', 'drift_tools')

# rosdep keys of the Python modules we import (ros/rosdistro rosdep/python.yaml); a ROS package's
# module is its own key. mcap-ros2-support's wheel pulls in mcap, which pulls in zstandard and lz4.
ROSDEP_KEYS = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'can': 'python3-can',
    'casadi': 'casadi-pip', 'cantools': 'python3-cantools-pip', 'crccheck': 'python-crccheck-pip',
    'rosbags': 'python3-rosbags-pip', 'mcap': 'mcap-ros2-support',
    'mcap_ros2': 'mcap-ros2-support', 'zstandard': 'mcap-ros2-support',
    'lz4': 'mcap-ros2-support',
}


def imported_roots(package: str) -> dict[str, str]:
    """Top-level module -> one file importing it, over every module of ``src/<package>``."""
    roots = {}
    for path in sorted((REPO / 'src' / package / package).rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                roots.setdefault(name.split('.')[0], path.name)
    return {m: f for m, f in roots.items()
            if m not in sys.stdlib_module_names and m not in (package, '__future__')}


def declared(package: str) -> tuple[set[str], str]:
    """The package.xml's dependency keys, and the text of its comments saying 'no rosdep key'."""
    tree = ET.parse(REPO / 'src' / package / 'package.xml',
                    ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    keys = {e.text.strip() for e in tree.getroot()
            if e.tag in ('depend', 'exec_depend', 'build_depend')}
    notes = ' '.join(e.text for e in tree.getroot()
                     if e.tag is ET.Comment and 'no rosdep key' in e.text)
    return keys, notes


@pytest.mark.parametrize('package', PACKAGES)
def test_package_xml_lists_every_import(package):
    keys, notes = declared(package)
    missing = [f'{module} ({where}): {ROSDEP_KEYS.get(module, module)}'
               for module, where in sorted(imported_roots(package).items())
               if ROSDEP_KEYS.get(module, module) not in keys
               and not re.search(rf'\b{module}\b', notes)]
    assert not missing, (f'src/{package}/package.xml lacks a dependency (or a "no rosdep key" '
                         f'comment) for: {", ".join(missing)}')


# --- where config/, maps/ and the compiled solvers are found ------------------------------------

@pytest.fixture
def installed(tmp_path, monkeypatch):
    """An install prefix with drift_control indexed and config/, maps/ in its share directory, and
    this module seen as installed (no checkout at its parents[3])."""
    share = tmp_path / 'install' / 'share' / 'drift_control'
    (share / 'config').mkdir(parents=True)
    shutil.copy(REPO / 'config' / 'defaults.yaml', share / 'config')
    (share / 'maps').mkdir()
    index = tmp_path / 'install' / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'drift_control').touch()
    monkeypatch.setattr(params, '_CHECKOUT', tmp_path / 'lib')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'install'))
    monkeypatch.delenv('DRIFT_CONFIG_DIR', raising=False)
    return share


def test_installed_config_and_maps_are_found_in_the_share_directory(installed):
    assert config_dir() == installed / 'config'
    assert maps_dir() == (installed / 'maps').resolve()


def test_config_dir_prefers_the_variable_then_the_checkout(installed, monkeypatch, tmp_path):
    monkeypatch.setattr(params, '_CHECKOUT', REPO)
    assert config_dir() == REPO / 'config'
    monkeypatch.setenv('DRIFT_CONFIG_DIR', str(tmp_path))
    assert config_dir() == tmp_path


def test_no_config_anywhere_is_one_line(installed, monkeypatch):
    monkeypatch.delenv('AMENT_PREFIX_PATH')
    with pytest.raises(ParamError, match='no config directory: set DRIFT_CONFIG_DIR'):
        config_dir()


def test_compiled_solvers_stay_out_of_the_install_space(installed, monkeypatch, tmp_path):
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    assert cache_dir() == tmp_path / 'cache' / 'drift_stack'
    monkeypatch.setattr(params, '_CHECKOUT', REPO)
    assert cache_dir() == REPO   # a checkout keeps its .codegen/, as scripts/setup.sh builds it


def test_colcon_plugins_stay_out_of_the_test_environment():
    """colcon pulls in pytest-rerunfailures: in .venv it would load; a flaky test is fixed, never
    retried."""
    assert importlib.util.find_spec('pytest_rerunfailures') is None


# --- a colcon build of src/, and a node started from its install space --------------------------

def colcon_site() -> Path:
    """colcon installed for this interpreter into its own folder under the venv, by the hash of
    requirements-colcon.txt and the lock file: pip runs once, later runs reuse the folder."""
    reqs, lock = REPO / 'requirements-colcon.txt', REPO / 'requirements-lock.txt'
    digest = hashlib.sha256(reqs.read_bytes() + lock.read_bytes()).hexdigest()[:16]
    site = Path(sys.prefix) / '.drift_colcon' / digest
    if (site / 'colcon_core').is_dir():
        return site
    site.parent.mkdir(exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=site.parent, prefix='partial-'))
    try:
        proc = subprocess.run([sys.executable, '-m', 'pip', 'install', '--quiet', '--target',
                               str(tmp), '-r', str(reqs), '-c', str(lock)],
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f'pip install of colcon failed:\n{proc.stderr[-3000:]}'
        tmp.rename(site)   # whole or not at all: an interrupted install is never reused
    except OSError:        # another run got there first
        pass
    finally:
        shutil.rmtree(tmp, ignore_errors=True)   # what is left of a failed install
    return site


def source_and_run(install: Path, argv: list[str], env: dict, cwd: Path):
    """``argv`` started by sh after sourcing ``install/setup.sh``, as a user's shell would."""
    script = f'. "{install}/setup.sh" && exec "$@"'
    return subprocess.Popen(['sh', '-c', script, 'sh', *argv], env=env, cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def wait_for(proc, pattern: str, timeout: float) -> tuple[bool, str]:
    """Whether ``proc`` printed ``pattern`` before it ended or ``timeout`` [s] passed, and what
    it printed until then."""
    out, deadline = b'', time.monotonic() + timeout
    fd = proc.stdout.fileno()
    while time.monotonic() < deadline:
        if select.select([fd], [], [], 0.1)[0]:
            chunk = os.read(fd, 65536)
            if not chunk:   # it ended
                break
            out += chunk
            if re.search(pattern, out.decode(errors='replace')):
                return True, out.decode(errors='replace')
    return False, out.decode(errors='replace')


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.no_rates   # a build, and one node's first line: runs beside the other tests
def test_colcon_build_runs_a_node_from_its_install_space(tmp_path, tools_domain_id):
    pytest.importorskip('drift_msgs.msg')
    if shutil.which('cmake') is None:
        pytest.skip('cmake not found: drift_msgs cannot be built')
    site = colcon_site()
    ws, outside = tmp_path / 'ws', tmp_path / 'elsewhere'
    outside.mkdir()
    base = {k: v for k, v in os.environ.items() if not k.startswith('COLCON_')
            and k not in ('DRIFT_CONFIG_DIR', 'PYTHONPATH', 'AMENT_PREFIX_PATH')}
    base['AMENT_PREFIX_PATH'] = sys.prefix   # the underlay, as /opt/ros/jazzy on a car

    build = subprocess.run(
        [sys.executable, '-m', 'colcon', '--log-base', str(ws / 'log'), 'build',
         '--base-paths', str(REPO / 'src'), '--build-base', str(ws / 'build'),
         '--install-base', str(ws / 'install'),
         '--cmake-args', '-DBUILD_TESTING=OFF', f'-DPython3_EXECUTABLE={sys.executable}'],
        env={**base, 'PYTHONPATH': str(site), 'COLCON_HOME': str(ws / 'colcon_home')},
        cwd=outside, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-4000:] + build.stderr[-2000:]
    for package in ('drift_msgs', *PACKAGES):
        assert f'Finished <<< {package}' in build.stdout, build.stdout[-2000:]
    install = ws / 'install'
    share = install / 'drift_control' / 'share' / 'drift_control'

    # the node's environment: the install space sourced over the underlay (PYTHONPATH,
    # AMENT_PREFIX_PATH, LD_LIBRARY_PATH for drift_msgs), nothing of the checkout; compiled
    # solvers (none for this node) would go to a cache of the test's own
    env = {**base, 'XDG_CACHE_HOME': str(tmp_path / 'cache'), 'PYTHONUNBUFFERED': '1'}
    probe = source_and_run(install, [sys.executable, '-c', '''if True:
        import json, drift_control, drift_msgs.msg
        from drift_control.assembly import maps_dir
        from drift_control.params import cache_dir, config_dir
        print(json.dumps({'control': drift_control.__file__, 'msgs': drift_msgs.msg.__file__,
                          'config': str(config_dir()), 'maps': str(maps_dir()),
                          'cache': str(cache_dir())}))'''], env, outside)
    out = probe.communicate(timeout=60)[0].decode()
    assert probe.returncode == 0, out
    where = json.loads(out.strip().splitlines()[-1])
    assert Path(where['control']).is_relative_to(install), where
    assert Path(where['msgs']).is_relative_to(install), where
    assert where['config'] == str(share / 'config')
    assert where['maps'] == str((share / 'maps').resolve())
    assert Path(where['cache']) == tmp_path / 'cache' / 'drift_stack'

    # the reference node loads the scenario's car, path and map; its first line names them
    node = source_and_run(install, [str(install / 'drift_control' / 'lib' / 'drift_control' /
                                        'reference'), '--ros-args', '-p', 'scenario:=steady_dry'],
                          env, outside)
    try:
        started, out = wait_for(node, r'm3_competition on dry, path \w+: [\d.]+ m', 60.0)
    finally:
        node.terminate()
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()
    assert started, out[-3000:]
