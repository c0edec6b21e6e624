"""A recorded run as numpy time series: what the report, the replay check and the tests compute on.

Times are the header stamps of the messages (sim time in lock-step runs, wall time otherwise),
relative to the first vehicle state. Works on the output of ``drift_tools.bag.read_bag`` with
either backend: messages are read by field name only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

STATE = '/vehicle/state'
TRUTH = '/sim/state'
REFERENCE = '/drift/reference'
COMMAND = '/drift/command'
STATUS = '/drift/nmpc/status'
PATH = '/drift/path'


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _columns(msgs, getters: dict) -> dict:
    out = {name: np.array([get(m.msg) for m in msgs], dtype=float) for name, get in getters.items()}
    out['t'] = np.array([_stamp(m.msg) for m in msgs], dtype=float)
    return out


@dataclass
class RunSeries:
    """Time series of one run; each group is a dict of equal-length arrays with a ``t`` key."""

    state: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    reference: dict = field(default_factory=dict)
    command: dict = field(default_factory=dict)
    status: dict = field(default_factory=dict)
    path_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    t0: float = 0.0

    @property
    def duration(self) -> float:
        t = self.state.get('t', np.zeros(0))
        return float(t[-1] - t[0]) if len(t) > 1 else 0.0


def _state_columns(msgs) -> dict:
    return _columns(msgs, {
        'V': lambda m: m.v, 'beta': lambda m: m.beta, 'r': lambda m: m.r,
        'omega_F': lambda m: 0.5 * (m.wheel_speeds[0] + m.wheel_speeds[1]),
        'omega_R': lambda m: 0.5 * (m.wheel_speeds[2] + m.wheel_speeds[3]),
        'delta': lambda m: m.delta, 'drive_torque': lambda m: m.drive_torque,
        'x': lambda m: m.x, 'y': lambda m: m.y, 'yaw': lambda m: m.yaw,
        'validity': lambda m: m.validity,
    })


def series_from_bag(messages: dict) -> RunSeries:
    """Build the time series of a run from ``read_bag`` output (``{topic: [BagMessage]}``)."""
    run = RunSeries()
    if messages.get(STATE):
        run.state = _state_columns(messages[STATE])
    if messages.get(TRUTH):
        run.truth = _state_columns(messages[TRUTH])
    if messages.get(REFERENCE):
        run.reference = _columns(messages[REFERENCE], {
            'V': lambda m: m.target.v, 'beta': lambda m: m.target.beta, 'r': lambda m: m.target.r,
            'omega_F': lambda m: m.target.omega_f, 'omega_R': lambda m: m.target.omega_r,
            'delta': lambda m: m.target.delta, 'drive_torque': lambda m: m.target.drive_torque,
            'curvature': lambda m: m.curvature, 'curvature_cmd': lambda m: m.curvature_cmd,
            's': lambda m: m.s, 'e_y': lambda m: m.e_y, 'heading_error': lambda m: m.heading_error,
            'direction': lambda m: m.direction, 'clamped': lambda m: m.clamped,
        })
    if messages.get(COMMAND):
        run.command = _columns(messages[COMMAND], {
            'delta': lambda m: m.delta, 'delta_rate': lambda m: m.delta_rate,
            'drive_torque': lambda m: m.drive_torque, 'mode': lambda m: m.mode,
        })
    if messages.get(STATUS):
        run.status = _columns(messages[STATUS], {
            'status': lambda m: m.status, 'iterations': lambda m: m.iterations,
            'solve_time': lambda m: m.solve_time, 'cost': lambda m: m.cost,
            'consecutive_failures': lambda m: m.consecutive_failures,
        })
    if messages.get(PATH):
        poses = messages[PATH][-1].msg.poses
        run.path_xy = np.array([[p.pose.position.x, p.pose.position.y] for p in poses], dtype=float)
    t0 = run.state['t'][0] if len(run.state.get('t', ())) else 0.0
    for group in (run.state, run.truth, run.reference, run.command, run.status):
        if 't' in group:
            group['t'] = group['t'] - t0
    run.t0 = t0
    return run


def resample(group: dict, t: np.ndarray, key: str) -> np.ndarray:
    """Zero-order hold of ``group[key]`` at times ``t`` (the last value at or before each time)."""
    if not len(group.get('t', ())):
        return np.full(len(t), np.nan)
    idx = np.searchsorted(group['t'], t, side='right') - 1
    out = group[key][np.clip(idx, 0, None)].astype(float)
    out[idx < 0] = np.nan
    return out
