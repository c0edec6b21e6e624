"""Stop signals of a node process, remembered from its first import on.

A node started with ``python -m <package>.nodes.<node>`` imports for a second or more (CasADi,
numpy, rclpy) and then builds itself (the simulator compiles its plant). A SIGINT in that time
raised a KeyboardInterrupt that some import swallowed, or met rclpy's handler, which only wakes
an executor already spinning: the stop was lost and the launcher killed the node 8 s later.
So SIGINT and SIGTERM only append to ``STOPS``; ``spin.run_node`` ends the spin on it.
SIGUSR1 prints every thread's Python stack to stderr (``faulthandler``, which needs no GIL): the
launcher sends it to a node that does not stop, before its SIGKILL.
"""
from __future__ import annotations

import faulthandler
import signal
import sys

STOPS: list[int] = []
DUMP_SIGNAL = signal.SIGUSR1   # prints every thread's stack (the launcher's, before a SIGKILL)


def _remember(signum, frame) -> None:
    STOPS.append(signum)


def install() -> None:
    """Remember SIGINT and SIGTERM instead of raising, print the stacks on ``DUMP_SIGNAL``
    (the main thread only)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _remember)
    faulthandler.register(DUMP_SIGNAL, all_threads=True, chain=False)


def install_if_node_process() -> None:
    """``install`` while ``python -m`` is still importing a node module's packages (argv[0] is
    '-m' until runpy runs the module); a test process importing a node keeps its handlers."""
    if sys.argv and sys.argv[0] == '-m':
        install()
