"""Writes a rosbag2-layout MCAP bag (``metadata.yaml`` + one ``.mcap``) from serialized CDR.

The recorder hands over CDR bytes exactly as they came off the wire; nothing is deserialized.
Chunks are small and :meth:`BagWriter.flush` closes the open one and rewrites ``metadata.yaml``, so
a recorder killed with SIGKILL loses at most what arrived since the last flush (the file then lacks
its summary; ``drift_tools.bag_salvage`` reads it and writes a repaired copy).
:meth:`BagWriter.close` writes the summary and the final metadata.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from drift_tools.msgdef import message_definition, normalize

logger = logging.getLogger(__name__)

ROSBAG2_VERSION = 9
DEFAULT_CHUNK_SIZE = 256 * 1024   # [bytes]


class BagExistsError(FileExistsError):
    """The bag directory already holds a bag."""


@dataclass
class _Topic:
    name: str
    msgtype: str
    channel_id: int
    type_hash: str
    qos: str = ''          # offered_qos_profiles (rosbag2 YAML text)
    count: int = 0


class BagWriter:
    """Write CDR messages of any number of topics into one rosbag2 MCAP directory.

    Parameters
    ----------
    bag_dir : path
        Directory to create (may exist if it holds no bag yet).
    chunk_size : int
        Uncompressed chunk size before a chunk is closed [bytes].
    compression : bool
        zstd-compress chunks.
    """

    def __init__(self, bag_dir, chunk_size: int = DEFAULT_CHUNK_SIZE, compression: bool = False):
        self.bag_dir = Path(bag_dir)
        if (self.bag_dir / 'metadata.yaml').exists() or list(self.bag_dir.glob('*.mcap')):
            raise BagExistsError(f'{self.bag_dir}: already holds a bag')
        self.bag_dir.mkdir(parents=True, exist_ok=True)
        self.mcap_path = self.bag_dir / f'{self.bag_dir.name}_0.mcap'
        self._stream = open(self.mcap_path, 'wb')
        self._writer = McapWriter(
            self._stream, chunk_size=chunk_size,
            compression=CompressionType.ZSTD if compression else CompressionType.NONE)
        self._writer.start(profile='ros2', library='drift_tools.bag_writer')
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _Topic] = {}
        self._t_min = self._t_max = None
        self._closed = False
        self._write_metadata()

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type of every topic added so far."""
        return {t.name: t.msgtype for t in self._topics.values()}

    @property
    def bytes_written(self) -> int:
        """Size of the MCAP file so far [bytes] (what is still in the open chunk not counted)."""
        return self.mcap_path.stat().st_size if self._closed else self._stream.tell()

    def counts(self) -> dict[str, int]:
        """Topic name -> messages written so far."""
        return {t.name: t.count for t in self._topics.values()}

    def add_topic(self, topic: str, msgtype: str, msgdef: str | None = None,
                  type_hash: str = '', reliable: bool = True, latched: bool = False) -> None:
        """Register a topic; its schema is the full ROS 2 definition of ``msgtype``.

        Parameters
        ----------
        topic : str
            Absolute topic name (``/vehicle/state``).
        msgtype : str
            ``pkg/msg/Name``.
        msgdef : str, optional
            Concatenated definition; looked up from the ``.msg`` files when not given.
        type_hash : str
            RIHS01 type hash, stored in the metadata when known.
        reliable, latched : bool
            The QoS it was recorded with, kept (as rosbag2 does) so a replay offers the same.
        """
        if topic in self._topics:
            if self._topics[topic].msgtype != normalize(msgtype):
                raise ValueError(f'{topic}: already recorded as {self._topics[topic].msgtype}')
            return
        msgtype = normalize(msgtype)
        if msgtype not in self._schemas:
            text = msgdef if msgdef is not None else message_definition(msgtype)
            self._schemas[msgtype] = self._writer.register_schema(
                msgtype, SchemaEncoding.ROS2, text.encode())
        qos = qos_yaml(reliable, latched)
        channel_id = self._writer.register_channel(
            topic, MessageEncoding.CDR, self._schemas[msgtype],
            metadata={'offered_qos_profiles': qos})
        self._topics[topic] = _Topic(topic, msgtype, channel_id, type_hash, qos)

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None,
              publish_time_ns: int | None = None) -> None:
        """Append one serialized (CDR) message of an added topic; times in ns since the epoch."""
        t = self._topics[topic]
        log_time_ns = time.time_ns() if log_time_ns is None else int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        self._writer.add_message(t.channel_id, log_time_ns, bytes(data), publish_time_ns,
                                 sequence=t.count)
        t.count += 1
        self._t_min = log_time_ns if self._t_min is None else min(self._t_min, log_time_ns)
        self._t_max = log_time_ns if self._t_max is None else max(self._t_max, log_time_ns)

    def add_metadata(self, name: str, values: dict) -> None:
        """An MCAP metadata record (``name``, string -> string), e.g. the run's settings."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in values.items()})

    def flush(self) -> None:
        """Close the open chunk, push it to the file and refresh ``metadata.yaml``."""
        if self._closed:
            return
        self._writer.flush()
        os.fsync(self._stream.fileno())
        self._write_metadata()

    def close(self) -> None:
        """Write the MCAP summary and the final ``metadata.yaml``; idempotent."""
        if self._closed:
            return
        self._writer.finish()
        self._stream.close()
        self._closed = True
        self._write_metadata()
        logger.info('bag %s: %d messages', self.bag_dir, sum(self.counts().values()))

    def abandon(self) -> None:
        """Close the file as it is, without a summary (after a failed write: a full disk).

        What earlier flushes wrote stays readable (``drift_tools.bag_salvage``).
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._stream.close()
        except OSError:
            pass
        try:
            self._write_metadata()
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _write_metadata(self) -> None:
        write_metadata(self.bag_dir, self.mcap_path.name,
                       [(t.name, t.msgtype, t.count, t.type_hash, t.qos)
                        for t in self._topics.values()],
                       self._t_min, self._t_max)


_INFINITE = {'sec': 2147483647, 'nsec': 4294967295}


def qos_yaml(reliable: bool, latched: bool) -> str:
    """rosbag2's ``offered_qos_profiles`` text for one publisher (rmw enum values)."""
    profile = {'history': 3, 'depth': 0,                   # system default / unknown
               'reliability': 1 if reliable else 2,         # RELIABLE / BEST_EFFORT
               'durability': 1 if latched else 2,           # TRANSIENT_LOCAL / VOLATILE
               'deadline': _INFINITE, 'lifespan': _INFINITE, 'liveliness': 1,
               'liveliness_lease_duration': _INFINITE,
               'avoid_ros_namespace_conventions': False}
    return yaml.safe_dump([profile], sort_keys=False)


def parse_qos_yaml(text: str) -> tuple[bool, bool] | None:
    """(reliable, latched) from ``offered_qos_profiles``: all publishers must offer it."""
    try:
        profiles = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        return None
    if not isinstance(profiles, list) or not profiles or \
            not all(isinstance(p, dict) for p in profiles):
        return None
    return (all(p.get('reliability') == 1 for p in profiles),
            all(p.get('durability') == 1 for p in profiles))


def _profiles(qos_text: str) -> list:
    try:
        profiles = yaml.safe_load(qos_text) if qos_text else []
    except yaml.YAMLError:
        return []
    return profiles if isinstance(profiles, list) else []


def write_metadata(bag_dir, file_name: str, topics, t_min_ns, t_max_ns) -> None:
    """Write rosbag2 ``metadata.yaml`` (version 9) atomically.

    Parameters
    ----------
    topics : iterable of (name, msgtype, count, type_hash[, qos])
        ``qos``: the channel's ``offered_qos_profiles`` text; readers (rosbags) match a topic's
        channel by it, so both must say the same.
    t_min_ns, t_max_ns : int or None
        First and last receive time [ns since the epoch]; None for an empty bag.
    """
    count = sum(t[2] for t in topics)
    start = t_min_ns or 0
    duration = (t_max_ns - t_min_ns) if count and t_min_ns is not None else 0
    info = {
        'version': ROSBAG2_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {'topic_metadata': {'name': t[0], 'type': t[1], 'serialization_format': 'cdr',
                                'offered_qos_profiles': _profiles(t[4] if len(t) > 4 else ''),
                                'type_description_hash': t[3]},
             'message_count': t[2]}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [file_name],
        'files': [{'path': file_name, 'starting_time': {'nanoseconds_since_epoch': start},
                   'duration': {'nanoseconds': duration}, 'message_count': count}],
        'custom_data': {'writer': 'drift_tools.bag_writer'},
        'ros_distro': 'jazzy',
    }
    path = Path(bag_dir) / 'metadata.yaml'
    tmp = path.with_suffix('.yaml.tmp')
    with open(tmp, 'w', encoding='utf-8') as fh:
        yaml.safe_dump({'rosbag2_bagfile_information': info}, fh, sort_keys=False)
    os.replace(tmp, path)
