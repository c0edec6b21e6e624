"""How every node process runs: init, spin, a clean end on SIGINT, cleanup and an exit code."""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from drift_control.params import ParamError


def run_node(factory: Callable[[], Node], name: str, args=None) -> int:
    """Build the node with ``factory`` and spin it until shutdown; returns the exit code.

    A bad parameter (``ParamError``) is logged as one line and exits 1. SIGINT from the launcher
    shuts the context down, possibly while the executor is inside a callback or taking a
    message: rclpy then raises from there (``RCLError`` "publisher's context is invalid" on a
    publish, ``RuntimeError`` "Unable to convert call argument" on a take; each failed a
    lock-step run at its end in CI). The interrupt itself may surface inside a C extension
    as another error (``SystemError`` from casadi's ``DM.__array__``, caused by the
    ``KeyboardInterrupt``). An exception once the context is shut down, or caused by the
    interrupt, is the end of the run, not a failure; any other is raised. The node's ``close()``, if it
    has one, runs before the node is destroyed (flush a bag, release a CAN bus).
    """
    rclpy.init(args=args)
    node, code = None, 0
    try:
        node = factory()
        rclpy.spin(node)
    except ParamError as err:
        rclpy.logging.get_logger(name).error(str(err))
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:
        if rclpy.ok() and not _interrupted(err):   # a real failure while running
            raise
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
