"""The codebase's own rules: algorithm modules never import ROS; nodes live under nodes/."""
import ast
import os
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'
ROS_MODULES = {'rclpy', 'drift_msgs', 'std_msgs', 'nav_msgs', 'diagnostic_msgs', 'rosgraph_msgs',
               'builtin_interfaces', 'geometry_msgs', 'std_srvs'}
CORE_FILES = sorted(p for p in SRC.glob('*/*/**/*.py') if 'nodes' not in p.parts)


def imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split('.')[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split('.')[0])
    return roots


def test_there_are_core_modules_to_check():
    assert len(CORE_FILES) >= 5


@pytest.mark.parametrize('path', CORE_FILES, ids=lambda p: str(p.relative_to(SRC)))
def test_core_module_imports_no_ros(path):
    assert not imported_roots(path) & ROS_MODULES, f'{path} imports ROS outside nodes/'


def test_node_processes_freeze_their_start_up_objects():
    """A full garbage collection over a node's start-up objects pauses it for tens of ms (past
    the bridge's 30 ms frame timeout): run_node collects once and freezes them."""
    import gc
    from drift_control.nodes.spin import settle_garbage_collector
    before = gc.get_freeze_count()
    try:
        junk = [[{'k': i}] for i in range(1000)]
        settle_garbage_collector()
        assert gc.get_freeze_count() >= before + len(junk)
    finally:
        gc.unfreeze()


def test_link_nodes_run_above_and_the_recorder_below_a_real_time_launch():
    """Under ``chrt -r 10`` the bridge and a simulated car go to 20 (their 10 ms cycles are not
    held up by an equal-priority burst), the recorder and the view leave real time."""
    import subprocess
    import sys
    if subprocess.run(['chrt', '-r', '10', 'true'], capture_output=True).returncode != 0:
        pytest.skip('real-time priority not allowed here')
    code = ('import os, threading; '
            'from drift_control.nodes.spin import raise_real_time, leave_real_time; '
            'raise_real_time(); print(os.sched_getscheduler(0), os.sched_getparam(0).sched_priority); '
            'go = threading.Event(); t = threading.Thread(target=go.wait); t.start(); '
            'leave_real_time(); print(os.sched_getscheduler(0), os.sched_getscheduler(t.native_id)); '
            'go.set()')
    out = subprocess.run(['chrt', '-r', '10', sys.executable, '-c', code], capture_output=True,
                         text=True, check=True).stdout.split()
    # a thread started before (the middleware's) leaves real time too
    assert out == [str(os.SCHED_RR), '20', str(os.SCHED_OTHER), str(os.SCHED_OTHER)], out
