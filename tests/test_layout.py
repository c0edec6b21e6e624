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
    """Under ``chrt -r 10`` the launcher drops to normal priority and hands 10 to its nodes: the
    bridge and a simulated car take real time at 20 after their start-up (the middleware's
    threads too), the controller's nodes at 10; the recorder and the view stay at normal
    priority, threads that exist already (the middleware's) included."""
    import subprocess
    import sys
    if subprocess.run(['chrt', '-r', '10', 'true'], capture_output=True).returncode != 0:
        pytest.skip('real-time priority not allowed here')
    node = ('import os, threading; from drift_control.nodes import priority as p; '
            'go = threading.Event(); t = threading.Thread(target=go.wait); t.start(); '
            'print(os.sched_getscheduler(0), p.launch_priority()); '
            'p.raise_real_time(); print(os.sched_getscheduler(0), '
            'os.sched_getparam(0).sched_priority, os.sched_getparam(t.native_id).sched_priority); '
            'p.leave_real_time(5); print(os.sched_getscheduler(t.native_id), '
            'os.getpriority(os.PRIO_PROCESS, t.native_id)); go.set()')
    launcher = ('import os, subprocess, sys; '
                'from drift_control.nodes.priority import leave_launch_real_time; '
                'env = leave_launch_real_time(); print(os.sched_getscheduler(0), env); '
                f'sys.stdout.flush(); subprocess.run([sys.executable, "-c", {node!r}], '
                'env={**os.environ, **env}, check=True)')
    out = subprocess.run(['chrt', '-r', '10', sys.executable, '-c', launcher],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    other, rr = str(os.SCHED_OTHER), str(os.SCHED_RR)
    assert out[0] == f"{other} {{'DRIFT_LAUNCH_RT_PRIORITY': '10'}}", out
    assert out[1] == f'{other} 10', "the node starts at normal priority, knows the launch's"
    assert out[2] == f'{rr} 20 20', 'link cycle at 20, the threads that exist too'
    assert out[3] == f'{other} 5', 'off real time at the nice given, every thread'


def test_priorities_do_not_change_outside_a_real_time_launch():
    from drift_control.nodes import priority
    env = dict(os.environ)
    os.environ.pop(priority.LAUNCH_RT_ENV, None)
    try:
        if priority.real_time_priority() is not None:
            pytest.skip('this test process runs at real-time priority')
        assert priority.leave_launch_real_time() == {}
        assert not priority.raise_real_time() and not priority.leave_real_time(-10)
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    finally:
        os.environ.clear()
        os.environ.update(env)


def test_a_real_time_launch_holds_the_cpu_wake_up_latency_while_it_runs(tmp_path):
    """The PM QoS request is the 32-bit number written to the device; it lasts while the file
    is open. Where the device cannot be opened (not root, not Linux) nothing is held."""
    import struct
    from drift_control.nodes.priority import hold_cpu_wakeup
    device = tmp_path / 'cpu_dma_latency'
    device.write_bytes(b'')
    held = hold_cpu_wakeup(0, str(device))
    assert held is not None and not held.closed
    assert struct.unpack('i', device.read_bytes()) == (0,)
    held.close()
    assert hold_cpu_wakeup(0, str(tmp_path / 'missing' / 'device')) is None
