"""run_node: the one way every node process runs (init, spin, clean end, exit code)."""
import subprocess

import pytest

from conftest import PYTHON, TESTS

pytestmark = pytest.mark.ros


def test_publish_racing_the_shutdown_ends_the_run_cleanly(node_env):
    """SIGINT shuts the context down while a callback publishes: exit 0, not a traceback
    (a lock-step run failed at its end this way)."""
    proc = subprocess.run([PYTHON, str(TESTS / 'nodes_for_tests' / 'publish_after_shutdown.py')],
                          env=node_env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert 'Traceback' not in proc.stderr


def test_a_failure_while_running_still_fails_the_run(node_env):
    proc = subprocess.run([PYTHON, str(TESTS / 'nodes_for_tests' / 'publish_after_shutdown.py'),
                           'fail'], env=node_env, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and 'a real failure while running' in proc.stderr


def test_an_interrupt_surfacing_as_another_error_ends_the_run_cleanly(node_env):
    """SIGINT inside casadi's DM.__array__ became a SystemError caused by the KeyboardInterrupt
    and failed a lock-step run at its end in CI."""
    proc = subprocess.run([PYTHON, str(TESTS / 'nodes_for_tests' / 'publish_after_shutdown.py'),
                           'interrupt'], env=node_env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_an_error_just_before_the_shutdown_lands_ends_the_run_cleanly(node_env):
    """rclpy's SIGINT handler shuts the context down from its own thread: a take can fail
    ("Unable to convert call argument") while the context is still up and failed a lock-step
    run at its end in CI."""
    proc = subprocess.run([PYTHON, str(TESTS / 'nodes_for_tests' / 'publish_after_shutdown.py'),
                           'early'], env=node_env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_the_process_ends_with_the_code_close_set_and_its_output_flushed(node_env):
    """A node process ends right after ``close()`` (no middleware teardown, which once hung
    until the launcher's SIGKILL): the exit code ``close()`` set and its buffered output stay."""
    buffered = {k: v for k, v in node_env.items() if k != 'PYTHONUNBUFFERED'}
    proc = subprocess.run([PYTHON, str(TESTS / 'nodes_for_tests' / 'publish_after_shutdown.py'),
                           'close'], env=buffered, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert 'closed: the bag is whole' in proc.stdout
