"""State -> command latency of a recorded real-time run, from the recorder's log times.

Each command is matched to the newest state the recorder had received before it: the newest
state the controller could have answered. The difference of their log times is the state path's
latency (DDS hops, the reference selector, the NMPC's solve), seen from one clock. With the
estimator stage (``run_stack --sensors``) the path starts at the sensor samples instead: each
command against the newest frame of samples. ``stages`` splits the path hop by hop, following
the reference each command waited for back to its state and sensor frame. With
``when='pt'`` the same from the publish times the recorder keeps (each message's DDS source
timestamp: the publisher's clock at publish), without the recorder's own delays. In a lock-step
bag the log times are sim time: there it measures nothing and is refused.
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


def _times(messages, when: str) -> np.ndarray:
    """Log (``'t'``) or publish (``'pt'``) times of messages, sorted [s]."""
    return np.sort(np.array([getattr(m, when) for m in messages], float))


def latency(messages: dict, skip: float = 1.0, when: str = 't') -> Latency:
    """The latency of a read bag (``read_bag``), leaving out the first ``skip`` seconds of
    commands (start-up: discovery, the first solves); from the sensor samples where the bag has
    them; on log times (``when='t'``) or publish times (``'pt'``). ValueError when it cannot be
    measured."""
    source = SENSORS_TOPIC if messages.get(SENSORS_TOPIC) else STATE_TOPIC
    states = _times(messages.get(source, []), when)
    commands = _times(messages.get(COMMAND_TOPIC, []), when)
    if np.isnan(states).any() or np.isnan(commands).any():
        raise ValueError('the log has no publish times (read it with the mcap backend)')
    if not states.size or not commands.size:
        raise ValueError(f'needs {STATE_TOPIC} and {COMMAND_TOPIC}; the log has '
                         f'{len(states)} states and {len(commands)} commands')
    commands = commands[commands >= commands[0] + skip]
    lat = state_to_command(states, commands)
    if lat.size == 0:
        raise ValueError(f'no command after the first {skip:g} s')
    return _summary(lat, source)


def _stamp(m) -> int:
    s = m.msg.header.stamp
    return s.sec * 1_000_000_000 + s.nanosec


STAMP_TOLERANCE_NS = 100_000   # a stamp carried as float seconds comes back ~0.2 us off


def _first_by_stamp(messages, when: str = 't') -> tuple[np.ndarray, np.ndarray]:
    """Sorted header stamps [ns] and the log (publish) time of the first message with each."""
    seen = {}
    for m in messages:
        seen.setdefault(_stamp(m), getattr(m, when))
    stamps = np.array(sorted(seen), dtype=np.int64)
    return stamps, np.array([seen[s] for s in stamps])


def _log_times_at(stamps: np.ndarray, times: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The log time of the message stamped nearest each of ``wanted`` [ns], NaN beyond
    ``STAMP_TOLERANCE_NS``."""
    i = np.clip(np.searchsorted(stamps, wanted), 1, len(stamps) - 1)
    i -= (wanted - stamps[i - 1]) < (stamps[i] - wanted)
    return np.where(np.abs(stamps[i] - wanted) <= STAMP_TOLERANCE_NS, times[i], np.nan)


def stages(messages: dict, skip: float = 1.0, when: str = 't') -> dict[str, Latency]:
    """The path of each command hop by hop: the reference it answered (the newest one stamped
    at or before the command's stamp: the NMPC stamps a command no earlier than its state), the
    state and the sensor frame stamped as that reference; the time differences 'sensors ->
    state', 'state -> reference', 'reference -> command' (negative where a node publishes the
    command first) and the whole chain. A command without its reference, or a reference whose
    state is not in the log, is left out of the hops it lacks."""
    commands = [m for m in messages.get(COMMAND_TOPIC, [])]
    refs = messages.get(REFERENCE_TOPIC, [])
    if not commands or not refs:
        return {}
    start = min(getattr(m, when) for m in commands) + skip
    commands = [m for m in commands if getattr(m, when) >= start]
    cmd_t = np.array([getattr(m, when) for m in commands], float)
    cmd_stamp = np.array([_stamp(m) for m in commands], dtype=np.int64)
    ref_stamp, ref_t = _first_by_stamp(refs, when)
    newest = np.searchsorted(ref_stamp, cmd_stamp + STAMP_TOLERANCE_NS, side='right') - 1
    ok = newest >= 0
    cmd_t, newest = cmd_t[ok], newest[ok]
    chain = [(REFERENCE_TOPIC, ref_t[newest]), (COMMAND_TOPIC, cmd_t)]
    for topic in (STATE_TOPIC, SENSORS_TOPIC):
        if len(messages.get(topic, ())) > 1:
            chain.insert(0, (topic, _log_times_at(*_first_by_stamp(messages[topic], when),
                                                  ref_stamp[newest])))
    out = {}
    for (a, ta), (b, tb) in [*zip(chain, chain[1:]), (chain[0], chain[-1])]:
        lat = (tb - ta)[np.isfinite(tb - ta)]
        if lat.size and a != b:
            out[f'{a} -> {b}'] = _summary(lat, a)
    return out


__all__ = ['COMMAND_TOPIC', 'Latency', 'REFERENCE_TOPIC', 'SENSORS_TOPIC', 'STATE_TOPIC',
           'latency', 'stages', 'state_to_command']
