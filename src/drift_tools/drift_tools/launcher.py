"""Runs a set of node processes: prefixed, coloured logs; clean shutdown; failure on a crash.

No rclpy here: each node is its own OS process, started in its own session so a terminal's Ctrl-C
reaches only the launcher, which stops the nodes with SIGTERM in a defined order (recorders last)
and escalates to SIGKILL after a timeout. SIGTERM, not SIGINT: CasADi polls and clears a pending
SIGINT inside its calls (the simulator building its plant), so a SIGINT could be lost. Before the
SIGKILL a node gets ``DUMP_SIGNAL``: the node processes print every thread's Python stack on it
(``drift_control.nodes.stops``), so the log says where it hung.
"""
from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

from drift_control.nodes.priority import hold_cpu_wakeup, leave_launch_real_time
from drift_control.nodes.stops import DUMP_SIGNAL   # a node prints its threads' stacks on it

logger = logging.getLogger(__name__)

COLOURS = (36, 33, 35, 32, 34, 91, 96, 93)   # ANSI foreground codes, one per node
_PR_SET_PDEATHSIG = 1
STOP_SIGNAL = signal.SIGTERM
DUMP_WAIT_S = 0.5              # for the stacks to reach the log before the SIGKILL [s]
# what a node may return after our stop signal (or a terminal's SIGINT)
CLEAN_EXIT_CODES = (0, -signal.SIGINT, 130, -signal.SIGTERM, 128 + signal.SIGTERM)


@dataclass
class Proc:
    """One started node process."""

    name: str
    argv: list
    popen: subprocess.Popen
    stop_last: bool = False              # stopped after the others (recorders)
    log_path: str | None = None          # the node's output also goes here, unprefixed
    reader: threading.Thread | None = None
    expected_exit: bool = False
    critical: bool = True                # its exit stops the others; else reported, run goes on


@dataclass
class Outcome:
    """How a launch ended: the reason, and each node's return code (None = was killed)."""

    reason: str                          # 'duration', 'signal', 'node-exit', 'node-crash'
    returncodes: dict = field(default_factory=dict)
    killed: list = field(default_factory=list)
    failed_node: str | None = None
    lost: list = field(default_factory=list)    # non-critical nodes that died during the run

    @property
    def ok(self) -> bool:
        """True when no node crashed and every node stopped cleanly when asked."""
        return self.reason != 'node-crash' and not self.killed and all(
            rc in CLEAN_EXIT_CODES for rc in self.returncodes.values())

    @property
    def exit_code(self) -> int:
        """The launcher's exit status: 0 when ``ok``, else the crashed (or lost) node's code
        or 1."""
        if self.ok:
            return 0
        node = self.failed_node or (self.lost[0] if self.lost else None)
        rc = self.returncodes.get(node) if node else None
        return rc if isinstance(rc, int) and 0 < rc < 256 else 1


class Launcher:
    """Start node processes, stream their output, stop them together.

    Parameters
    ----------
    out : text stream
        Where prefixed node output goes (default ``sys.stdout``).
    colour : bool or None
        Colour the prefixes; ``None`` colours when ``out`` is a terminal.
    kill_timeout : float
        Seconds a node gets to exit after SIGTERM before SIGKILL [s].
    """

    def __init__(self, out=None, colour: bool | None = None, kill_timeout: float = 8.0):
        self._out = out or sys.stdout
        self._colour = self._out.isatty() if colour is None else colour
        self._kill_timeout = kill_timeout
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._stop_reason = 'signal'
        self._kill_now = False           # a second Ctrl-C: do not wait for clean exits
        self.procs: list[Proc] = []
        # under chrt: the launcher and its nodes start at normal priority; each node learns the
        # launch's real-time priority from its environment (drift_control.nodes.priority)
        self._priority_env = leave_launch_real_time()
        # a real-time launch also keeps the CPUs from deep idle while it runs (closed at exit)
        self._wakeup = hold_cpu_wakeup(0) if self._priority_env else None
        if self._priority_env:
            self._say('CPU wake-up latency held at 0 us while the stack runs' if self._wakeup
                      else 'CPU wake-up latency not held (/dev/cpu_dma_latency: not allowed)')

    # --- output ---------------------------------------------------------------------------
    def _prefix(self, name: str, index: int, width: int) -> str:
        text = f'[{name}]'.ljust(width + 2)
        if self._colour:
            return f'\033[{COLOURS[index % len(COLOURS)]}m{text}\033[0m '
        return text + ' '

    def emit(self, prefix: str, line: str) -> None:
        """Write one line with its prefix, whole, however many threads print."""
        with self._lock:
            self._out.write(prefix + line.rstrip('\n') + '\n')
            self._out.flush()

    def _pump(self, proc: Proc, index: int) -> None:
        log = open(proc.log_path, 'w', encoding='utf-8') if proc.log_path else None
        try:
            for raw in iter(proc.popen.stdout.readline, b''):
                line = raw.decode('utf-8', 'replace')
                width = max(len(p.name) for p in self.procs)   # all names known by now
                self.emit(self._prefix(proc.name, index, width), line)
                if log:
                    log.write(line)
                    log.flush()
        finally:
            proc.popen.stdout.close()
            if log:
                log.close()

    # --- lifecycle ------------------------------------------------------------------------
    def start(self, name: str, argv: list, env: dict, stop_last: bool = False,
              log_path: str | None = None, critical: bool = True) -> Proc:
        """Start one node; its stdout and stderr are merged, prefixed and streamed.

        The node gets SIGTERM if the launcher dies without stopping it (killed), so no orphan
        keeps publishing into the next run. A node that is not ``critical`` (the recorder on a
        car) may die without stopping the others.
        """
        if self._priority_env:
            env = {**(os.environ if env is None else env), **self._priority_env}
        popen = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, start_new_session=True,
                                 preexec_fn=_term_with_parent)
        proc = Proc(name, list(argv), popen, stop_last, log_path, critical=critical)
        self.procs.append(proc)
        proc.reader = threading.Thread(target=self._pump, args=(proc, len(self.procs) - 1),
                                       daemon=True)
        proc.reader.start()
        self._say(f'started {name} (pid {popen.pid}): {" ".join(argv)}')
        return proc

    def request_stop(self, reason: str = 'signal') -> None:
        """Ask :meth:`wait` to stop all nodes (safe from a signal handler)."""
        self._stop_reason = reason
        self._stop.set()

    def install_signal_handlers(self) -> None:
        """SIGINT and SIGTERM stop the stack cleanly; a second one kills what is left."""
        def handler(signum, frame):
            if self._stop.is_set():
                self._kill_now = True
            self.request_stop('signal')
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, handler)

    def wait(self, duration: float | None = None, poll: float = 0.05) -> Outcome:
        """Block until ``duration`` passes, a stop is requested or a node exits; then stop all.

        A node exiting non-zero on its own is a crash (``node-crash``); exiting 0 on its own
        ends the run normally (``node-exit``, e.g. a scenario that finished). A node that is not
        critical is reported when it dies and the others run on; its exit code still counts in
        the outcome.
        """
        deadline = None if not duration else time.monotonic() + duration
        reason, failed, lost = None, None, set()
        while reason is None:
            if self._stop.wait(poll):
                reason = self._stop_reason
            elif deadline is not None and time.monotonic() >= deadline:
                reason = 'duration'
            for p in self.procs:
                rc = p.popen.poll()
                if rc is None or reason is not None or p.name in lost:
                    continue
                if not p.critical:
                    lost.add(p.name)
                    self._say(f'{p.name} exited with code {rc}; it is not critical: '
                              'the others run on without it')
                    continue
                failed = p.name
                reason = 'node-exit' if rc == 0 else 'node-crash'
                self._say(f'{p.name} exited with code {rc}; stopping the stack')
        outcome = self.stop_all()
        outcome.reason, outcome.failed_node = reason, failed
        outcome.lost = sorted(lost)
        return outcome

    def stop_all(self) -> Outcome:
        """SIGTERM every node (recorders last), SIGKILL what outlives the timeout; reap all."""
        outcome = Outcome('signal')
        first = [p for p in self.procs if not p.stop_last]
        last = [p for p in self.procs if p.stop_last]
        for group in (first, last):
            for p in group:
                if p.popen.poll() is None:
                    p.expected_exit = True
                    p.popen.send_signal(STOP_SIGNAL)
            deadline = time.monotonic() + self._kill_timeout
            for p in group:
                while p.popen.poll() is None and not self._kill_now \
                        and time.monotonic() < deadline:
                    time.sleep(0.02)
                if p.popen.poll() is None:
                    if self._kill_now:
                        self._say(f'{p.name}: second interrupt: SIGKILL')
                    else:
                        self._say(f'{p.name}: no exit {self._kill_timeout:g} s after SIGTERM: '
                                  f'its stacks, then SIGKILL')
                        self._dump_stacks(p)
                    p.popen.kill()
                    p.popen.wait()
                    outcome.killed.append(p.name)
        for p in self.procs:
            if p.reader is not None:
                p.reader.join(timeout=2.0)
            outcome.returncodes[p.name] = p.popen.returncode
        return outcome

    def _dump_stacks(self, p: Proc) -> None:
        """Ask a hung node for its threads' stacks (``DUMP_SIGNAL``) and give them time to be
        logged; a process without the handler dies of the signal instead."""
        try:
            p.popen.send_signal(DUMP_SIGNAL)
        except ProcessLookupError:
            return
        time.sleep(DUMP_WAIT_S)

    def _say(self, text: str) -> None:
        prefix = '\033[1m[launch]\033[0m ' if self._colour else '[launch] '
        self.emit(prefix, text)


def _term_with_parent() -> None:
    """In the child before exec: ask Linux for SIGTERM when the launcher dies."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):      # not Linux: the launcher's own handlers must do
        pass
