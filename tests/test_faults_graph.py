"""Faults on the node graph: runs that would pass with nothing run now fail, with the reason."""
import os
import subprocess
import sys

import pytest

from conftest import REPO

pytest.importorskip('drift_msgs.msg')
pytestmark = pytest.mark.ros


def test_a_lockstep_simulator_whose_controller_never_commands_ends_the_run_non_zero():
    """Without an NMPC the lock-step loop would wait forever and the run 'pass' with nothing."""
    env = {**os.environ, 'ROS_DOMAIN_ID': '124', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.run(
        [sys.executable, '-m', 'drift_sim.nodes.sim_node', '--ros-args', '-p',
         'clock_mode:=lockstep', '-p', 'scenario:=steady_dry', '-p', 'startup_timeout:=1.0'],
        env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert 'the controller never commanded' in proc.stdout + proc.stderr


def test_lockstep_on_a_graph_without_its_clock_owner_is_refused_at_launch(capsys):
    from conftest import load_script
    rc = load_script('run_stack').main(['--graph', 'vehicle', '--clock', 'lockstep',
                                        '--duration', '1'])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "has no clock owner 'sim'" in err and len(err.splitlines()) == 1, err


def test_a_stop_during_start_up_is_honoured_without_sigkill():
    """--duration 1 stops the graph while the simulator still builds its plant (CasADi clears a
    pending SIGINT there; the launcher's SIGTERM is remembered from the first import on)."""
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    for _ in range(2):
        proc = subprocess.run([sys.executable, str(REPO / 'scripts' / 'run_stack.py'),
                               '--duration', '1', '--domain-id', '125'], env=env,
                              capture_output=True, text=True, timeout=60)
        out = proc.stdout + proc.stderr
        assert proc.returncode == 0 and 'SIGKILL' not in out, out[-2000:]
        assert 'exit codes: sim=0, reference=0, nmpc=0' in out, out[-2000:]


def _stack_with(tmp_path, recorder_critical: bool, **recorder_params):
    """config/stack.yaml with the sim graph's recorder (non-)critical and its parameters set."""
    import yaml
    stack = yaml.safe_load((REPO / 'config' / 'stack.yaml').read_text())
    stack['graphs']['sim']['recorder'] = {'module': 'drift_tools.nodes.recorder_node',
                                          'critical': recorder_critical}
    stack['recorder']['ros__parameters'].update(recorder_params)
    path = tmp_path / 'stack.yaml'
    path.write_text(yaml.safe_dump(stack))
    return path


def _run_stack_argv(stack, bag, domain, sim_duration):
    return [sys.executable, str(REPO / 'scripts' / 'run_stack.py'), '--stack', str(stack),
            '--bag', str(bag), '--sim-duration', str(sim_duration), '--domain-id', str(domain),
            '--no-summary']


def test_a_killed_non_critical_recorder_does_not_end_the_drive(tmp_path):
    """As on a car: the recorder dies (SIGKILL) mid-run; the loop runs to the scenario's end, the
    launcher says what died and exits non-zero, and what the recorder flushed is readable."""
    import signal
    import time

    from drift_tools.bag import read_bag
    bag = tmp_path / 'bag'
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.Popen(_run_stack_argv(_stack_with(tmp_path, False, flush_period=0.2), bag,
                                            126, 6.0),
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 90
    pid = None
    for line in proc.stdout:                     # '[launch] started recorder (pid N): ...'
        if pid is None and 'started recorder (pid ' in line:
            pid = int(line.split('(pid ')[1].split(')')[0])
        if 'recording /drift/command' in line:
            break
        assert time.monotonic() < deadline
    time.sleep(1.0)                              # a few flushes with commands in them
    os.kill(pid, signal.SIGKILL)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 1, out[-3000:]
    assert 'recorder exited with code -9; it is not critical' in out, out[-3000:]
    assert 'stopped (node-exit)' in out and "died during the run: ['recorder']" in out, out[-3000:]
    assert 'sim=0' in out and 'nmpc=0' in out, out[-3000:]
    commands = read_bag(bag, topics=['/drift/command'])['/drift/command']
    assert len(commands) >= 20, 'the flushed commands must be readable'


def test_a_full_disk_stops_the_recording_not_the_run(tmp_path):
    """The bag on a 1 MiB file system (tmpfs in a private mount namespace): the recorder reports
    the write failure and stays up, the run ends normally, the launcher exits non-zero, and what
    was flushed before the disk filled is readable."""
    from drift_tools.bag import read_bag
    mnt = tmp_path / 'small_disk'
    mnt.mkdir()
    probe = subprocess.run(['unshare', '-m', 'sh', '-c', f'mount -t tmpfs -o size=64k tmpfs {mnt}'],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f'no private mount namespace here: {probe.stderr.strip()}')
    bag = mnt / 'bag'
    stack = _stack_with(tmp_path, True, flush_period=0.2, disk_stop_free_mb=0.0,
                        disk_warn_free_mb=0.5)
    argv = ' '.join(_run_stack_argv(stack, bag, 127, 8.0))
    # the bag is copied out before the namespace (and its tmpfs) goes away
    script = (f'mount -t tmpfs -o size=1m tmpfs {mnt} && {argv}; rc=$?; '
              f'cp -r {bag} {tmp_path}/bag_copy; exit $rc')
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.run(['unshare', '-m', 'sh', '-c', script], env=env, capture_output=True,
                          text=True, timeout=180)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    assert 'recording stopped: write failed: No space left on device' in out, out[-3000:]
    assert 'stopped (node-exit)' in out and 'recorder=1' in out, out[-3000:]
    assert 'sim=0' in out and 'nmpc=0' in out, out[-3000:]
    assert 'Traceback' not in out, out[-3000:]
    states = read_bag(tmp_path / 'bag_copy', topics=['/vehicle/state'])['/vehicle/state']
    assert len(states) > 50


@pytest.mark.parametrize('param, says', [
    ('duration:=-1.0', 'sim: duration must be a time > 0 s'),
    ('duration:=6', "Trying to set parameter 'duration' to '6' of type 'INTEGER'")])
def test_a_bad_node_parameter_is_one_line_and_exit_1(param, says):
    env = {**os.environ, 'ROS_DOMAIN_ID': '128', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.run([sys.executable, '-m', 'drift_sim.nodes.sim_node', '--ros-args', '-p',
                           param], env=env, capture_output=True, text=True, timeout=60)
    out = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 1 and says in out and 'Traceback' not in out, out
    assert len(out.splitlines()) == 1, out
