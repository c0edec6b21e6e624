"""Reads a recorded bag back: per-topic lists of decoded messages with their receive times.

Two independent readers: ``rosbags`` (``AnyReader``; types come from the definitions stored in the
bag, so custom drift_msgs types need no build) and ``mcap`` (``mcap`` + ``mcap_ros2``). Both
return the same shape, so report and replay tools can build on :func:`read_bag`. A bag whose
recorder was killed (no MCAP summary) is read by ``drift_tools.bag_salvage``'s scanner, never
rewritten; ``scripts/bag.py recover`` writes a repaired copy.
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import yaml

logger = logging.getLogger(__name__)

BACKENDS = ('rosbags', 'mcap')


@dataclass(frozen=True)
class BagMessage:
    """One decoded message and when the recorder received it."""

    t: float          # receive (log) time [s since the epoch]
    msg: object       # decoded message; fields as attributes (``msg.header.stamp.sec``)
    pt: float = math.nan   # publish time [s since the epoch] (backend 'mcap' and salvage)


@dataclass(frozen=True)
class TopicInfo:
    """A topic as ``metadata.yaml`` lists it."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """What ``metadata.yaml`` says about a bag."""

    path: Path
    topics: dict            # name -> TopicInfo
    start: float            # first receive time [s since the epoch]
    duration: float         # last minus first receive time [s]
    message_count: int
    files: tuple            # the storage files, relative to ``path``


def bag_info(bag_dir) -> BagInfo:
    """Read ``metadata.yaml`` of a rosbag2 directory."""
    bag_dir = Path(bag_dir)
    try:
        with open(bag_dir / 'metadata.yaml', encoding='utf-8') as fh:
            info = yaml.safe_load(fh)['rosbag2_bagfile_information']
        topics = {}
        for entry in info.get('topics_with_message_count') or []:
            meta = entry['topic_metadata']
            topics[meta['name']] = TopicInfo(meta['name'], meta['type'],
                                             int(entry['message_count']))
        return BagInfo(bag_dir, topics,
                       start=info['starting_time']['nanoseconds_since_epoch'] * 1e-9,
                       duration=info['duration']['nanoseconds'] * 1e-9,
                       message_count=int(info['message_count']),
                       files=tuple(info.get('relative_file_paths') or ()))
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, ValueError) as err:
        raise ValueError(f'{bag_dir / "metadata.yaml"}: not a rosbag2 metadata file '
                         f'({type(err).__name__}: {err}); scripts/bag.py info reads the MCAP '
                         'without it') from None


def read_bag(bag_dir, topics=None, backend: str = 'rosbags') -> dict[str, list[BagMessage]]:
    """Decode a bag into ``{topic: [BagMessage, ...]}``, each list in receive-time order.

    Parameters
    ----------
    bag_dir : path
        rosbag2 directory (``metadata.yaml`` + ``.mcap``).
    topics : iterable of str, optional
        Only these topics (absolute names); default all.
    backend : {'rosbags', 'mcap'}
        Which library decodes.
    """
    if backend not in BACKENDS:
        raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
    wanted = None if topics is None else set(topics)
    if not is_finished(bag_dir):
        return _read_salvaged(bag_dir, wanted)
    try:
        return _read_whole(bag_dir, wanted, backend)
    except Exception as err:   # noqa: BLE001 - either library raises its own types on damage
        logger.warning('%s: %s (%s); reading what is intact', bag_dir, type(err).__name__, err)
        return _read_salvaged(bag_dir, wanted)


def _read_whole(bag_dir, wanted, backend: str) -> dict[str, list[BagMessage]]:
    out: dict[str, list[BagMessage]] = {}
    if backend == 'rosbags':
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
        with AnyReader([Path(bag_dir)],
                       default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            for c in conns:
                out.setdefault(c.topic, [])
            for conn, t_ns, raw in reader.messages(connections=conns):
                out[conn.topic].append(BagMessage(t_ns * 1e-9, reader.deserialize(raw, conn.msgtype)))
    else:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
        for name in bag_info(bag_dir).files:
            with open(Path(bag_dir) / name, 'rb') as fh:
                reader = make_reader(fh, decoder_factories=[DecoderFactory()])
                for channel in reader.get_summary().channels.values():
                    if wanted is None or channel.topic in wanted:
                        out.setdefault(channel.topic, [])
                for _, channel, message, decoded in reader.iter_decoded_messages(
                        topics=None if wanted is None else sorted(wanted)):
                    out[channel.topic].append(BagMessage(message.log_time * 1e-9, decoded,
                                                         message.publish_time * 1e-9))
        for msgs in out.values():
            msgs.sort(key=lambda m: m.t)
    return out


def is_finished(bag_dir) -> bool:
    """True when the bag's MCAP file ends with its footer (the recorder closed it)."""
    from drift_tools.bag_salvage import bag_file
    path = bag_file(bag_dir)
    if path.stat().st_size < 8 + 37:
        return False
    with open(path, 'rb') as fh:
        fh.seek(-8, os.SEEK_END)
        return fh.read(8) == b'\x89MCAP0\r\n'


def _read_salvaged(bag_dir, wanted) -> dict[str, list[BagMessage]]:
    """Decode what the salvage scanner reads of an unfinished or damaged bag (read-only)."""
    from mcap_ros2.decoder import DecoderFactory

    from drift_tools.bag_salvage import scan_bag
    scan = scan_bag(bag_dir)
    for line in scan.problems():
        logger.warning('%s: %s', bag_dir, line)
    factory, decoders, out = DecoderFactory(), {}, {}
    for cid, channel in scan.channels.items():
        if wanted is None or channel.topic in wanted:
            out.setdefault(channel.topic, [])
            decoders[cid] = factory.decoder_for(channel.message_encoding,
                                                scan.schemas.get(channel.schema_id))
    for m in sorted(scan.messages, key=lambda m: m.log_time):
        decode = decoders.get(m.channel_id)
        if decode is not None:
            out[scan.channels[m.channel_id].topic].append(BagMessage(m.log_time * 1e-9,
                                                                     decode(m.data),
                                                                     m.publish_time * 1e-9))
    return out
