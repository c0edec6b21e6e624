"""How every node process runs: init, spin, a clean end on SIGINT, cleanup and an exit code."""
from __future__ import annotations

import ctypes
import gc
import os
import signal
import sys
import time
from typing import Callable, NoReturn

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node

from drift_control.nodes import stops
from drift_control.nodes.logs import route_python_logging
from drift_control.params import ParamError

# a context shut down from another thread can make a callback fail just before rclpy.ok() turns
# false: wait this long for the shutdown before calling the error a failure [s]
SHUTDOWN_GRACE_S = 0.5
STOP_POLL_S = 0.1   # a signal ends the spin at the latest this long after it came [s]


def run_node(factory: Callable[[], Node], name: str, args=None) -> NoReturn:
    """Build the node with ``factory``, spin it until it is stopped and end the process with
    its exit code.

    SIGINT and SIGTERM are ours, not rclpy's (``drift_control.nodes.stops``): a stop is
    remembered whenever it comes, from the node module's first import on, and ends the spin
    within ``STOP_POLL_S`` (exit 0). A node with a ``finished`` future (the simulator at the end
    of its scenario) ends the run when it completes: exit 0 with the result True, 1 with False
    (a failed run, its reason logged). A bad parameter (``ParamError``, or a value of the wrong
    type for rclpy) is one line, exit 1.
    A context shut down while a callback runs (``rclpy.shutdown`` from elsewhere) makes rclpy
    raise from there (``RCLError`` on a publish, ``RuntimeError`` on a take), possibly just
    before the shutdown lands: an exception caused by an interrupt, or followed by the shutdown
    within ``SHUTDOWN_GRACE_S``, is the end of the run, not a failure; any other is raised. The
    node's ``close()``, if it has one, runs before the node is destroyed (flush a bag, release a
    CAN bus); a node that sets ``exit_code`` there (a recording that failed) exits with it.

    A node process ends right after ``close()``, through ``end_process``, without the
    middleware's teardown (see there why); only an error that is raised returns.
    """
    stops.install()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node, code, ended = None, 0, False
    try:
        node = factory()
        route_python_logging(node)   # the core modules' lines on /rosout, with severity and time
        settle_garbage_collector()
        finished = getattr(node, 'finished', None)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stops.STOPS and rclpy.ok() and not (finished is not None and finished.done()):
            executor.spin_once(timeout_sec=STOP_POLL_S)
        if stops.STOPS:
            node.get_logger().info(f'stopping on {signal.Signals(stops.STOPS[0]).name}')
        if finished is not None and finished.done() and finished.result() is False:
            code = 1   # the node ended the run for a reason it logged
        ended = True
    except (ParamError, InvalidParameterTypeException, InvalidParameterValueException) as err:
        rclpy.logging.get_logger(name).error(str(err))
        code, ended = 1, True
    except (KeyboardInterrupt, ExternalShutdownException):
        ended = True
    except Exception as err:
        if not (_interrupted(err) or _shut_down_within(SHUTDOWN_GRACE_S)):
            raise   # a real failure while running
        ended = True
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            code = code or int(getattr(node, 'exit_code', 0) or 0)
        if ended:
            end_process(code)
        if node is not None:   # a failure on its way up: the usual teardown, then its traceback
            node.destroy_node()
        rclpy.try_shutdown()


def end_process(code: int) -> NoReturn:
    """End this process now with ``code``: stdio flushed, no interpreter or middleware teardown.

    What a node owns is released by its ``close()``; what is left is the DDS teardown (its
    entities, participant, static objects and threads), which can hang after a clean stop until
    the launcher's SIGKILL. Peers see the participant go when its lease ends, not at once.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # closed, or a broken pipe: nothing more to say
            pass
    try:
        ctypes.CDLL(None).fflush(None)   # the C streams too: rcutils' log lines
    except (OSError, AttributeError):
        pass
    os._exit(code)


def settle_garbage_collector() -> None:
    """Collect once, then freeze what the start-up built (modules, CasADi, the node).

    A full collection of a node's ~10^5 start-up objects takes 20-40 ms here, and Python runs one
    now and then on its own: a pause past the bridge's 30 ms frame timeout or its 60 ms
    heartbeat. Frozen objects are never scanned again; what the loop allocates still is.
    """
    gc.collect()
    gc.freeze()


def _interrupted(err: BaseException | None) -> bool:
    """Whether ``err`` was caused, directly or through its chain, by a KeyboardInterrupt."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def _shut_down_within(seconds: float) -> bool:
    """Whether the default context is, or goes, down within ``seconds``."""
    deadline = time.monotonic() + seconds
    while rclpy.ok():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True
