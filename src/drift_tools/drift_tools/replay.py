"""Replaying a bag: its raw messages in recorded order, paced like the recording or faster.

No rclpy here: ``scripts/replay.py`` publishes what this module yields. Messages stay CDR bytes
end to end (rclpy publishes ``bytes`` as a serialized message), so a bag from a car replays without
decoding, and types unknown to this checkout still replay as long as the receiving node knows them.
"""
from __future__ import annotations

import importlib
import logging
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from drift_tools.bag import bag_info, is_finished
from drift_tools.bag_salvage import scan_bag

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RawMessage:
    """One recorded message as it was on the wire."""

    topic: str
    msgtype: str      # 'pkg/msg/Name'
    t_ns: int         # receive time [ns]
    data: bytes       # CDR


def iter_raw(bag_dir, topics=None) -> Iterator[RawMessage]:
    """Yield the bag's messages in receive-time order, optionally only ``topics``.

    An unfinished or damaged bag (a killed recorder) is read by the salvage scanner, read-only;
    what it could not read is logged.
    """
    bag_dir = Path(bag_dir)
    wanted = None if topics is None else set(topics)
    if is_finished(bag_dir):
        yield from _iter_indexed(bag_dir, wanted)
        return
    scan = scan_bag(bag_dir)
    for line in scan.problems():
        logger.warning('%s: %s', bag_dir, line)
    for m in sorted(scan.messages, key=lambda m: m.log_time):
        channel = scan.channels[m.channel_id]
        if wanted is None or channel.topic in wanted:
            schema = scan.schemas.get(channel.schema_id)
            yield RawMessage(channel.topic, _msgtype(schema), m.log_time, bytes(m.data))


def _iter_indexed(bag_dir: Path, wanted) -> Iterator[RawMessage]:
    """In log-time order, ties in the order they were written: a lock-step bag logs several
    states at one sim time, and they must replay in their own order."""
    from mcap.reader import make_reader
    out = []
    for name in bag_info(bag_dir).files:
        with open(bag_dir / name, 'rb') as fh:
            reader = make_reader(fh)
            for schema, channel, message in reader.iter_messages(
                    topics=None if wanted is None else sorted(wanted), log_time_order=False):
                out.append(RawMessage(channel.topic, _msgtype(schema), message.log_time,
                                      bytes(message.data)))
    out.sort(key=lambda m: m.t_ns)     # stable: file order among equal times
    yield from out


def _msgtype(schema) -> str:
    """``pkg/msg/Name`` from an MCAP schema name (``pkg/msg/Name`` or ``pkg/Name``)."""
    msgtype = schema.name if schema is not None else ''
    if '/msg/' not in msgtype and msgtype.count('/') == 1:
        msgtype = msgtype.replace('/', '/msg/')
    return msgtype


def topic_qos(bag_dir) -> dict[str, tuple[bool, bool]]:
    """Topic -> (reliable, latched) as recorded; the stack's own list where the bag is silent."""
    from drift_tools.bag_writer import parse_qos_yaml
    from drift_tools.recording import STACK_TOPICS
    bag_dir = Path(bag_dir)
    channels = scan_bag(bag_dir).channels.values() if not is_finished(bag_dir) else None
    if channels is None:
        from mcap.reader import make_reader
        from drift_tools.bag_salvage import bag_file
        with open(bag_file(bag_dir), 'rb') as fh:
            channels = list(make_reader(fh).get_summary().channels.values())
    known = {('/' + t.lstrip('/')): latched for t, (_, latched) in STACK_TOPICS.items()}
    out = {}
    for ch in channels:
        qos = parse_qos_yaml(ch.metadata.get('offered_qos_profiles', ''))
        out[ch.topic] = qos if qos is not None else (True, known.get(ch.topic, False))
    return out


def iter_replay(bag_dir, topics=None, start: float = 0.0, end: float | None = None,
                loops: int = 1) -> Iterator[RawMessage]:
    """The messages of ``[start, end]`` (seconds after the first message), ``loops`` times.

    Time never runs backwards for a subscriber: pass ``k`` is shifted by ``k`` times the window's
    length plus its mean message spacing, in the log time and in the stamp of every message that
    begins with one (a ``std_msgs/Header``, or ``/clock``'s time). ``loops=0`` repeats until
    the caller stops.
    """
    messages = list(iter_raw(bag_dir, topics))
    if not messages:
        return
    t0 = messages[0].t_ns
    lo = t0 + int(round(start * 1e9))
    hi = None if end is None else t0 + int(round(end * 1e9))
    if lo > messages[-1].t_ns or (hi is not None and hi < lo):
        raise ValueError(f'time window {start:g}..{end if end is not None else "end"} s is '
                         f'outside the bag (0..{(messages[-1].t_ns - t0) * 1e-9:.3f} s)')
    window = [m for m in messages if m.t_ns >= lo and (hi is None or m.t_ns <= hi)]
    if not window:
        raise ValueError(f'time window {start:g}..{end:g} s holds no message')
    span = window[-1].t_ns - window[0].t_ns
    period = span // max(len({m.t_ns for m in window}) - 1, 1)
    k = 0
    while loops <= 0 or k < loops:
        shift = k * (span + max(period, 1))
        for m in window:
            yield m if shift == 0 else RawMessage(m.topic, m.msgtype, m.t_ns + shift,
                                                  restamp(m.data, m.msgtype, shift))
        k += 1


_STAMPED_FIRST: dict[str, bool] = {}


def restamp(data: bytes, msgtype: str, shift_ns: int) -> bytes:
    """CDR ``data`` with its leading time (a Header's stamp, a Clock's clock) moved by
    ``shift_ns``; other messages unchanged. The time is the first field: bytes 4-12."""
    if not _stamped_first(msgtype) or len(data) < 12:
        return data
    little = data[1] == 1            # encapsulation: CDR_LE = 0x0001, CDR_BE = 0x0000
    fmt = '<iI' if little else '>iI'
    sec, nsec = struct.unpack_from(fmt, data, 4)
    sec, nsec = divmod(sec * 1_000_000_000 + nsec + shift_ns, 1_000_000_000)
    out = bytearray(data)
    struct.pack_into(fmt, out, 4, sec, nsec)
    return bytes(out)


def _stamped_first(msgtype: str) -> bool:
    """Whether the type's first field is a std_msgs/Header or a builtin_interfaces/Time."""
    if msgtype not in _STAMPED_FIRST:
        from drift_tools.msgdef import MsgDefError, msg_text
        try:
            fields = [line.split('#')[0].split() for line in msg_text(msgtype).splitlines()]
            first = next(f for f in fields if len(f) >= 2 and '=' not in ''.join(f))
            _STAMPED_FIRST[msgtype] = first[0] in ('std_msgs/Header', 'Header',
                                                   'builtin_interfaces/Time', 'Time')
        except (MsgDefError, StopIteration, OSError):
            _STAMPED_FIRST[msgtype] = False
    return _STAMPED_FIRST[msgtype]


def message_class(msgtype: str):
    """The Python class of a ROS message type name (``pkg/msg/Name`` or ``pkg/Name``)."""
    parts = msgtype.strip('/').split('/')
    pkg, name = parts[0], parts[-1]
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise LookupError(f'message type {msgtype} is not installed in this environment') from None


class Pacer:
    """Sleeps so that recorded time advances ``rate`` times faster than wall time.

    ``rate <= 0`` means as fast as possible.
    """

    def __init__(self, rate: float = 1.0, clock=time.monotonic, sleep=time.sleep):
        self.rate = rate
        self._clock = clock
        self._sleep = sleep
        self._origin: tuple[float, int] | None = None

    def wait_until(self, t_ns: int) -> None:
        if self.rate <= 0:
            return
        if self._origin is None:
            self._origin = (self._clock(), t_ns)
            return
        wall0, rec0 = self._origin
        due = wall0 + (t_ns - rec0) * 1e-9 / self.rate
        delay = due - self._clock()
        if delay > 0:
            self._sleep(delay)
