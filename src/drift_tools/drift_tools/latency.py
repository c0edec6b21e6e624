"""State -> command latency of a recorded real-time run, from the recorder's log times.

Each command is matched to the newest state the recorder had received before it: the newest
state the controller could have answered. The difference of their log times is the state path's
latency (DDS hops, the reference selector, the NMPC's solve), seen from one clock. In a lock-step
bag the log times are sim time: there it measures nothing and is refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATE_TOPIC = '/vehicle/state'
COMMAND_TOPIC = '/drift/command'


@dataclass(frozen=True)
class Latency:
    """Percentiles of the state -> command latency [s] over ``n`` commands."""

    n: int
    p50: float
    p99: float
    max: float

    def as_dict(self) -> dict:
        return {'commands': self.n, 'p50_ms': 1e3 * self.p50, 'p99_ms': 1e3 * self.p99,
                'max_ms': 1e3 * self.max}


def state_to_command(state_t, command_t) -> np.ndarray:
    """For each command log time [s], the time since the newest state logged before it [s];
    commands before the first state are left out."""
    state_t, command_t = np.asarray(state_t, float), np.asarray(command_t, float)
    newest = np.searchsorted(state_t, command_t, side='right') - 1
    ok = newest >= 0
    return command_t[ok] - state_t[newest[ok]]


def latency(messages: dict, skip: float = 1.0) -> Latency:
    """The latency of a read bag (``read_bag``), leaving out the first ``skip`` seconds of
    commands (start-up: discovery, the first solves). ValueError when it cannot be measured."""
    states = [m.t for m in messages.get(STATE_TOPIC, [])]
    commands = [m.t for m in messages.get(COMMAND_TOPIC, [])]
    if not states or not commands:
        raise ValueError(f'needs {STATE_TOPIC} and {COMMAND_TOPIC}; the log has '
                         f'{len(states)} states and {len(commands)} commands')
    commands = [t for t in commands if t >= commands[0] + skip]
    lat = state_to_command(states, commands)
    if lat.size == 0:
        raise ValueError(f'no command after the first {skip:g} s')
    return Latency(int(lat.size), float(np.percentile(lat, 50)), float(np.percentile(lat, 99)),
                   float(lat.max()))


__all__ = ['COMMAND_TOPIC', 'Latency', 'STATE_TOPIC', 'latency', 'state_to_command']
