"""State -> command latency of a recorded real-time run, from the recorder's log times.

Each command is matched to the newest state the recorder had received before it: the newest
state the controller could have answered. The difference of their log times is the state path's
latency (DDS hops, the reference selector, the NMPC's solve), seen from one clock. With the
estimator stage (``run_stack --sensors``) the path starts at the sensor samples instead: each
command against the newest frame of samples. ``stages`` splits the path hop by hop, following
one stamp (a frame's arrival stamp is its state's, its reference's and its command's). In a
lock-step bag the log times are sim time: there it measures nothing and is refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATE_TOPIC = '/vehicle/state'
SENSORS_TOPIC = '/vehicle/sensors'
REFERENCE_TOPIC = '/drift/reference'
COMMAND_TOPIC = '/drift/command'


@dataclass(frozen=True)
class Latency:
    """Percentiles of the state -> command latency [s] over ``n`` commands."""

    n: int
    p50: float
    p99: float
    max: float
    source: str = STATE_TOPIC   # where the path starts: the state, or the sensor samples

    def as_dict(self) -> dict:
        return {'commands': self.n, 'p50_ms': 1e3 * self.p50, 'p99_ms': 1e3 * self.p99,
                'max_ms': 1e3 * self.max, 'from': self.source}


def state_to_command(state_t, command_t) -> np.ndarray:
    """For each command log time [s], the time since the newest state logged before it [s];
    commands before the first state are left out."""
    state_t, command_t = np.asarray(state_t, float), np.asarray(command_t, float)
    newest = np.searchsorted(state_t, command_t, side='right') - 1
    ok = newest >= 0
    return command_t[ok] - state_t[newest[ok]]


def _summary(lat: np.ndarray, source: str) -> Latency:
    return Latency(int(lat.size), float(np.percentile(lat, 50)), float(np.percentile(lat, 99)),
                   float(lat.max()), source)


def latency(messages: dict, skip: float = 1.0) -> Latency:
    """The latency of a read bag (``read_bag``), leaving out the first ``skip`` seconds of
    commands (start-up: discovery, the first solves); from the sensor samples where the bag has
    them. ValueError when it cannot be measured."""
    source = SENSORS_TOPIC if messages.get(SENSORS_TOPIC) else STATE_TOPIC
    states = [m.t for m in messages.get(source, [])]
    commands = [m.t for m in messages.get(COMMAND_TOPIC, [])]
    if not states or not commands:
        raise ValueError(f'needs {STATE_TOPIC} and {COMMAND_TOPIC}; the log has '
                         f'{len(states)} states and {len(commands)} commands')
    commands = [t for t in commands if t >= commands[0] + skip]
    lat = state_to_command(states, commands)
    if lat.size == 0:
        raise ValueError(f'no command after the first {skip:g} s')
    return _summary(lat, source)


def _stamp(m) -> int:
    s = m.msg.header.stamp
    return s.sec * 1_000_000_000 + s.nanosec


def stages(messages: dict, skip: float = 1.0) -> dict[str, Latency]:
    """Hop by hop along each command's stamp (the state it was solved on): log time of the
    first message of each topic with that stamp, differences between consecutive topics of the
    path ('/vehicle/sensors -> /vehicle/state', ..., '-> /drift/command'). Commands whose stamp
    a topic lacks (a timer-triggered NMPC, a lost message) are left out of that hop."""
    path = [t for t in (SENSORS_TOPIC, STATE_TOPIC, REFERENCE_TOPIC) if messages.get(t)]
    first = {}
    for topic in path:
        seen = first[topic] = {}
        for m in messages[topic]:
            seen.setdefault(_stamp(m), m.t)
    commands = messages.get(COMMAND_TOPIC, [])
    if not commands:
        raise ValueError(f'needs {COMMAND_TOPIC}')
    start = commands[0].t + skip
    cmd = {_stamp(m): m.t for m in reversed(commands) if m.t >= start}
    first[COMMAND_TOPIC] = cmd
    out = {}
    hops = list(zip(path, path[1:] + [COMMAND_TOPIC]))
    if len(path) > 1:
        hops.append((path[0], COMMAND_TOPIC))
    for a, b in hops:
        lat = np.array([first[b][s] - first[a][s] for s in cmd if s in first[a] and s in first[b]])
        if lat.size:
            out[f'{a} -> {b}'] = _summary(lat, a)
    return out


__all__ = ['COMMAND_TOPIC', 'Latency', 'REFERENCE_TOPIC', 'SENSORS_TOPIC', 'STATE_TOPIC',
           'latency', 'stages', 'state_to_command']
