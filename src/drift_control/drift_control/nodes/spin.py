"""How every node process runs: init, spin, a clean end on SIGINT, cleanup and an exit code."""
from __future__ import annotations

import time
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from drift_control.params import ParamError

# rclpy's SIGINT handler shuts the context down from its own thread, so an error the interrupt
# caused in the executor can come before the context is down: wait this long for it [s]
SHUTDOWN_GRACE_S = 0.5


def run_node(factory: Callable[[], Node], name: str, args=None) -> int:
    """Build the node with ``factory`` and spin it until shutdown; returns the exit code.

    A bad parameter (``ParamError``) is logged as one line and exits 1. SIGINT from the launcher
    shuts the context down, possibly while the executor is inside a callback or taking a
    message: rclpy then raises from there (``RCLError`` "publisher's context is invalid" on a
    publish, ``RuntimeError`` "Unable to convert call argument" on a take; each failed a
    lock-step run at its end in CI). The interrupt itself may surface inside a C extension
    as another error (``SystemError`` from casadi's ``DM.__array__``, caused by the
    ``KeyboardInterrupt``). The handler shuts the context down from its own thread, so such an
    error can also come just before the shutdown lands (a take failed that way). An exception
    caused by the interrupt, or followed by the shutdown within ``SHUTDOWN_GRACE_S``, is the end
    of the run, not a failure; any other is raised (that much later). The node's ``close()``, if it
    has one, runs before the node is destroyed (flush a bag, release a CAN bus). A node with a
    ``finished`` future (the simulator at the end of its scenario) ends the run when it
    completes: exit 0 with the result True, 1 with False (a failed run, its reason logged).
    """
    rclpy.init(args=args)
    node, code = None, 0
    try:
        node = factory()
        finished = getattr(node, 'finished', None)
        if finished is None:
            rclpy.spin(node)
        else:
            rclpy.spin_until_future_complete(node, finished)
            if finished.done() and finished.result() is False:
                code = 1   # the node ended the run for a reason it logged
    except ParamError as err:
        rclpy.logging.get_logger(name).error(str(err))
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:
        if not (_interrupted(err) or _shut_down_within(SHUTDOWN_GRACE_S)):
            raise   # a real failure while running
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


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
