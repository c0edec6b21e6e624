"""Reads a recorded bag back: per-topic lists of decoded messages with their receive times.

Two independent readers: ``rosbags`` (``AnyReader``; types come from the definitions stored in the
bag, so custom drift_msgs types need no build) and ``mcap`` (``mcap`` + ``mcap_ros2``). Both
return the same shape, so report and replay tools can build on :func:`read_bag`. A bag whose
recorder was killed (no MCAP summary) is repaired in place by :func:`reindex`.
"""
from __future__ import annotations

import logging
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
    with open(bag_dir / 'metadata.yaml', encoding='utf-8') as fh:
        info = yaml.safe_load(fh)['rosbag2_bagfile_information']
    topics = {}
    for entry in info.get('topics_with_message_count') or []:
        meta = entry['topic_metadata']
        topics[meta['name']] = TopicInfo(meta['name'], meta['type'], int(entry['message_count']))
    return BagInfo(bag_dir, topics,
                   start=info['starting_time']['nanoseconds_since_epoch'] * 1e-9,
                   duration=info['duration']['nanoseconds'] * 1e-9,
                   message_count=int(info['message_count']),
                   files=tuple(info.get('relative_file_paths') or ()))


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
                    out[channel.topic].append(BagMessage(message.log_time * 1e-9, decoded))
        for msgs in out.values():
            msgs.sort(key=lambda m: m.t)
    return out


def reindex(bag_dir) -> int:
    """Rewrite a bag whose recorder died (truncated MCAP, stale metadata) into a complete one.

    Reads every whole record up to the truncation, writes a new MCAP with summary and index, and
    a fresh ``metadata.yaml``. Returns the number of messages kept. A complete bag is left as is.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    from drift_tools.bag_writer import write_metadata

    bag_dir = Path(bag_dir)
    mcaps = sorted(bag_dir.glob('*.mcap'))
    if len(mcaps) != 1:
        raise FileNotFoundError(f'{bag_dir}: expected one .mcap file, found {len(mcaps)}')
    src = mcaps[0]
    if _has_footer(src):
        return bag_info(bag_dir).message_count
    schemas, schema_names, channels, counts = {}, {}, {}, {}
    t_min = t_max = None
    tmp = src.with_suffix('.mcap.reindex')
    with open(src, 'rb') as fin, open(tmp, 'wb') as fout:
        writer = Writer(fout)
        writer.start(profile='ros2', library='drift_tools.bag.reindex')
        ids = {}
        try:
            for record in StreamReader(fin, skip_magic=False).records:
                if isinstance(record, Schema) and record.id not in schemas:
                    schemas[record.id] = writer.register_schema(record.name, record.encoding,
                                                                record.data)
                    schema_names[record.id] = record.name
                elif isinstance(record, Channel) and record.id not in ids:
                    ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schemas.get(record.schema_id, 0),
                        record.metadata)
                    channels[record.id] = record
                    counts[record.id] = 0
                elif isinstance(record, Message) and record.channel_id in ids:
                    writer.add_message(ids[record.channel_id], record.log_time, record.data,
                                       record.publish_time, record.sequence)
                    counts[record.channel_id] += 1
                    t_min = record.log_time if t_min is None else min(t_min, record.log_time)
                    t_max = record.log_time if t_max is None else max(t_max, record.log_time)
        except (McapError, EOFError, ValueError, IndexError, OSError) as err:
            logger.info('%s: truncated (%s); kept what came before', src.name, type(err).__name__)
        writer.finish()
    os.replace(tmp, src)
    topics = [(ch.topic, schema_names.get(ch.schema_id, ''), counts[cid], '')
              for cid, ch in channels.items()]
    write_metadata(bag_dir, src.name, topics, t_min, t_max)
    return sum(counts.values())


def _has_footer(path: Path) -> bool:
    size = path.stat().st_size
    if size < 8 + 37:
        return False
    with open(path, 'rb') as fh:
        fh.seek(-8, os.SEEK_END)
        return fh.read(8) == b'\x89MCAP0\r\n'

