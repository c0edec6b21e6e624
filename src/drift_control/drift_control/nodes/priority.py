"""Scheduling of the node processes in a real-time launch (the launcher run under ``chrt``).

Linux gives real-time tasks at most 95 % of each CPU per second (``sched_rt_runtime_us``):
with every node at real-time priority from its start, the start-up imports and builds and the
solves used that up (``rt_time`` reached 950 ms), and all of them were stopped for the rest of
the second
(the bridge then lost frames and heartbeats). So the launcher drops to normal priority and
hands its real-time priority to the nodes in ``LAUNCH_RT_ENV``; each node starts at normal
priority and takes real time after its start-up: the link cycles (the bridge, a simulated car;
30 ms frame timeouts) ``LINK_ABOVE`` the launch's priority, the controller's nodes at it. The
recorder and the live view stay at normal priority. No ROS import here: the launcher uses it.
"""
from __future__ import annotations

import os
import struct

LAUNCH_RT_ENV = 'DRIFT_LAUNCH_RT_PRIORITY'   # the launch's real-time priority, for its nodes
LINK_ABOVE = 10         # the link cycles run this much above the launch's priority
CPU_LATENCY = '/dev/cpu_dma_latency'   # the kernel's PM QoS request for every CPU's wake-up
_REAL_TIME = (getattr(os, 'SCHED_FIFO', -1), getattr(os, 'SCHED_RR', -1))


def real_time_priority() -> int | None:
    """This process's real-time priority, None if it runs at normal priority."""
    try:
        if os.sched_getscheduler(0) in _REAL_TIME:
            return os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        pass
    return None


def launch_priority() -> int | None:
    """The real-time priority of the launch this node belongs to (None: not a real-time one)."""
    value = os.environ.get(LAUNCH_RT_ENV, '')
    if value.isdigit():
        return int(value)
    return real_time_priority()   # started under chrt directly


def leave_launch_real_time() -> dict[str, str]:
    """For a launcher under ``chrt``: drop to normal priority (its nodes inherit that) and return
    the environment that tells them the launch's priority ({} outside a real-time launch)."""
    prio = real_time_priority()
    if prio is None or not _set_all(None, 0):
        return {}
    return {LAUNCH_RT_ENV: str(prio)}


def hold_cpu_wakeup(us: int = 0, device: str = CPU_LATENCY):
    """Ask the kernel to wake every CPU within ``us`` microseconds (no deep idle states) while
    the returned file stays open, as cyclictest does: an idle (virtual) CPU halts and is woken
    late, and the controller's frame waits for it (docs/estimator.md). None where not allowed
    (it needs root) or not there."""
    try:
        held = open(device, 'wb', buffering=0)
    except OSError:
        return None
    try:
        held.write(struct.pack('i', us))
    except OSError:
        held.close()
        return None
    return held


def raise_real_time(by: int = LINK_ABOVE) -> bool:
    """After start-up: every thread ``by`` above the launch's real-time priority (the link
    cycles; 0 for the controller's nodes). The middleware's threads too: they deliver the
    node's messages and hold locks its publishes wait on, and below the node they would wait
    for the controller's solves. Nothing changes outside a real-time launch or where it is
    not allowed. True if raised."""
    base = launch_priority()
    if base is None:
        return False
    policy = os.SCHED_RR
    return _set_all((policy, min(base + by, os.sched_get_priority_max(policy))), 0)


def leave_real_time(nice: int = 0) -> bool:
    """Every thread at normal priority and ``nice`` in a real-time launch, for the nodes no
    control loop waits on (the recorder, the live view: a chunk compressed at real-time
    priority would hold a core as long as it likes). True if changed."""
    if launch_priority() is None:
        return False
    return _set_all(None, nice)


def _set_all(policy: tuple[int, int] | None, nice: int) -> bool:
    """Every thread of this process to ``policy`` ((policy, priority), None: normal) and
    ``nice``; False where not allowed."""
    ok = True
    for tid in _threads() or [0]:
        ok &= _set_thread(tid, policy, nice)
    return ok


def _set_thread(tid: int, policy: tuple[int, int] | None, nice: int) -> bool:
    try:
        if policy is None:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            try:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            except PermissionError:   # a negative nice not allowed: normal priority
                pass
        else:
            os.sched_setscheduler(tid, policy[0], os.sched_param(policy[1]))
        return True
    except ProcessLookupError:   # a thread that ended meanwhile
        return True
    except (AttributeError, OSError):   # no such call here, or not allowed
        return False


def _threads() -> list[int]:
    """This process's thread IDs (Linux), [] where there is no /proc."""
    try:
        return [int(t) for t in os.listdir('/proc/self/task')]
    except OSError:
        return []
