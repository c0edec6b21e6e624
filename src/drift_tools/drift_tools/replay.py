"""Replaying a bag: its raw messages in recorded order, paced like the recording or faster.

No rclpy here: ``scripts/replay.py`` publishes what this module yields. Messages stay CDR bytes
end to end (rclpy publishes ``bytes`` as a serialized message), so a bag from a car replays without
decoding, and types unknown to this checkout still replay as long as the receiving node knows them.
"""
from __future__ import annotations

import importlib
import logging
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
    from mcap.reader import make_reader
    for name in bag_info(bag_dir).files:
        with open(bag_dir / name, 'rb') as fh:
            reader = make_reader(fh)
            for schema, channel, message in reader.iter_messages(
                    topics=None if wanted is None else sorted(wanted), log_time_order=True):
                yield RawMessage(channel.topic, _msgtype(schema), message.log_time,
                                 bytes(message.data))


def _msgtype(schema) -> str:
    """``pkg/msg/Name`` from an MCAP schema name (``pkg/msg/Name`` or ``pkg/Name``)."""
    msgtype = schema.name if schema is not None else ''
    if '/msg/' not in msgtype and msgtype.count('/') == 1:
        msgtype = msgtype.replace('/', '/msg/')
    return msgtype


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
