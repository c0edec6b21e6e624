"""Reads what is left of a damaged or unfinished MCAP bag, and writes a repaired copy.

A recorder killed by SIGKILL or a full disk leaves an MCAP without its summary, possibly with a
half-written last chunk; a bad sector or a faulty copy can damage a chunk in the middle. The
scanner walks the records itself: each chunk is checked (its lengths, and the CRC of its
content) and a damaged one is skipped by searching for the next valid chunk, so one bad chunk
loses only its own messages. Nothing here writes to the bag it reads: the input file is mapped
read-only. :func:`recover_bag` writes a new bag directory and says what it kept and dropped.
"""
from __future__ import annotations

import io
import mmap
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Metadata, Schema

MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEAD = 9                      # opcode (1) + length (8)
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4      # start, end, uncompressed size, crc, compression length
_MAX_COMPRESSION_NAME = 16
_KNOWN_OPCODES = {int(op) for op in Opcode}


class BagDamagedError(ValueError):
    """A bag that cannot be read at all (not an MCAP, no bag directory)."""


@dataclass(frozen=True)
class Damage:
    """A byte range of the file that could not be read."""

    start: int                  # byte offset
    end: int                    # byte offset (exclusive)
    what: str                   # 'damaged chunk', 'unreadable bytes', 'unfinished record'
    time_range: tuple | None = None   # (first, last) message log time [ns] the chunk claimed

    def describe(self) -> str:
        text = f'{self.what} at bytes {self.start}..{self.end} ({self.end - self.start} bytes)'
        if self.time_range:
            t0, t1 = self.time_range
            text += f', messages logged {t0 * 1e-9:.3f}..{t1 * 1e-9:.3f} s'
        return text


@dataclass
class Scan:
    """Everything readable in one MCAP file."""

    path: Path
    schemas: dict = field(default_factory=dict)     # id -> Schema
    channels: dict = field(default_factory=dict)    # id -> Channel
    messages: list = field(default_factory=list)    # Message records, file order
    metadata: list = field(default_factory=list)    # Metadata records
    damage: list = field(default_factory=list)      # Damage
    chunks: int = 0                                 # chunks read whole
    finished: bool = False                          # the footer was found
    channels_from_metadata: tuple = ()              # channel ids rebuilt from metadata.yaml
    orphans: int = 0                                # messages of a channel no one defined

    @property
    def complete(self) -> bool:
        """The file was finished and nothing in it is damaged."""
        return self.finished and not self.damage

    def problems(self) -> list[str]:
        """One line per thing that is not as a finished, undamaged bag has it."""
        lines = [d.describe() for d in self.damage]
        if not self.finished:
            lines.append('no footer: the recorder did not finish the file')
        if self.channels_from_metadata:
            lines.append(f'channel definitions {list(self.channels_from_metadata)} rebuilt '
                         'from metadata.yaml (their chunk was lost)')
        if self.orphans:
            lines.append(f'{self.orphans} messages of undefined channels dropped')
        return lines


def scan_mcap(path) -> Scan:
    """Read every intact record of an MCAP file, skipping damaged chunks."""
    path = Path(path)
    scan = Scan(path)
    with open(path, 'rb') as fh:
        size = fh.seek(0, io.SEEK_END)
        if size < len(MAGIC):
            raise BagDamagedError(f'{path}: not an MCAP file ({size} bytes)')
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            if buf[:len(MAGIC)] != MAGIC:
                raise BagDamagedError(f'{path}: not an MCAP file (bad magic)')
            _walk(buf, len(MAGIC), scan)
    return scan


def _walk(buf, pos: int, scan: Scan) -> None:
    size = len(buf)
    while pos < size:
        if size - pos < _RECORD_HEAD:
            if buf[pos:size] != MAGIC[:size - pos]:
                scan.damage.append(Damage(pos, size, 'unfinished record'))
            return
        opcode = buf[pos]
        (length,) = struct.unpack_from('<Q', buf, pos + 1)
        end = pos + _RECORD_HEAD + length
        ok = opcode in _KNOWN_OPCODES and end <= size
        if ok and opcode == Opcode.CHUNK:
            ok = _read_chunk(buf, pos, end, scan)
        elif ok:
            ok = _read_record(opcode, bytes(buf[pos + _RECORD_HEAD:end]), scan)
        if ok:
            if opcode == Opcode.FOOTER:
                scan.finished = True
                return
            pos = end
            continue
        nxt = _next_chunk(buf, pos + 1)
        if nxt is None:
            what = 'unfinished record' if opcode in _KNOWN_OPCODES and end > size \
                else 'unreadable bytes'
            if opcode == Opcode.CHUNK and end > size:
                kept = _read_unfinished_chunk(buf, pos, scan)
                what = f'unfinished chunk ({kept} messages of it kept)' if kept else what
            scan.damage.append(Damage(pos, size, what, _claimed_times(buf, pos, opcode)))
            return
        what = 'damaged chunk' if opcode == Opcode.CHUNK else 'unreadable bytes'
        scan.damage.append(Damage(pos, nxt, what, _claimed_times(buf, pos, opcode)))
        pos = nxt


def _chunk_body(buf, pos: int, end: int):
    """The parsed chunk at ``pos`` if its lengths agree and its CRC matches, else None."""
    body = pos + _RECORD_HEAD
    if end - body < _CHUNK_FIXED + 8:
        return None
    t0, t1, usize, crc, clen = struct.unpack_from('<QQQII', buf, body)
    if clen > _MAX_COMPRESSION_NAME or t1 < t0:
        return None
    at = body + _CHUNK_FIXED
    compression = bytes(buf[at:at + clen])
    (dlen,) = struct.unpack_from('<Q', buf, at + clen)
    data_start = at + clen + 8
    if data_start + dlen != end:
        return None
    data = bytes(buf[data_start:end])
    try:
        if compression == b'':
            raw = data
        elif compression == b'zstd':
            import zstandard
            raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=usize)
        elif compression == b'lz4':
            import lz4.frame
            raw = lz4.frame.decompress(data)
        else:
            return None
    except Exception:   # noqa: BLE001 - a corrupt stream raises the codec's own error types
        return None
    if len(raw) != usize or (crc and zlib.crc32(raw) != crc):
        return None
    return (t0, t1), raw


def _read_chunk(buf, pos: int, end: int, scan: Scan) -> bool:
    parsed = _chunk_body(buf, pos, end)
    if parsed is None:
        return False
    staged, whole = _stage_records(parsed[1], scan.path)
    if not whole:
        return False
    _merge(staged, scan)
    scan.chunks += 1
    return True


def _read_unfinished_chunk(buf, pos: int, scan: Scan) -> int:
    """The whole records of an uncompressed chunk the file ends inside (a copy cut short, a
    full disk), kept in ``scan``; how many messages. A compressed one keeps nothing."""
    body = pos + _RECORD_HEAD
    if len(buf) - body < _CHUNK_FIXED + 8:
        return 0
    clen = struct.unpack_from('<QQQII', buf, body)[4]
    if clen != 0:
        return 0
    (dlen,) = struct.unpack_from('<Q', buf, body + _CHUNK_FIXED)
    start = body + _CHUNK_FIXED + 8
    staged, _ = _stage_records(bytes(buf[start:min(len(buf), start + dlen)]), scan.path)
    _merge(staged, scan)
    return len(staged.messages)


def _stage_records(raw: bytes, path) -> tuple[Scan, bool]:
    """The records of a chunk's data, in order up to the first that is cut short or does not
    parse, and whether that was all of them."""
    staged, at = Scan(path), 0
    while at < len(raw):
        if len(raw) - at < _RECORD_HEAD:
            return staged, False
        opcode = raw[at]
        (length,) = struct.unpack_from('<Q', raw, at + 1)
        stop = at + _RECORD_HEAD + length
        if stop > len(raw) or not _read_record(opcode, raw[at + _RECORD_HEAD:stop], staged):
            return staged, False
        at = stop
    return staged, True


def _merge(staged: Scan, scan: Scan) -> None:
    for sid, schema in staged.schemas.items():
        scan.schemas.setdefault(sid, schema)
    for cid, channel in staged.channels.items():
        scan.channels.setdefault(cid, channel)
    scan.messages.extend(staged.messages)


def _read_record(opcode: int, body: bytes, scan: Scan) -> bool:
    """Parse one record into ``scan``; False when its body does not parse."""
    stream = ReadDataStream(io.BytesIO(body))
    try:
        if opcode == Opcode.SCHEMA:
            schema = Schema.read(stream)
            scan.schemas.setdefault(schema.id, schema)
        elif opcode == Opcode.CHANNEL:
            channel = Channel.read(stream)
            scan.channels.setdefault(channel.id, channel)
        elif opcode == Opcode.MESSAGE:
            scan.messages.append(Message.read(stream, len(body)))
        elif opcode == Opcode.METADATA:
            scan.metadata.append(Metadata.read(stream))
        elif opcode not in _KNOWN_OPCODES:
            return False
    except (struct.error, UnicodeDecodeError, ValueError, EOFError, IndexError):
        return False
    return stream.count <= len(body)


def _next_chunk(buf, start: int) -> int | None:
    """Offset of the next valid chunk record at or after ``start``."""
    size = len(buf)
    pos = buf.find(b'\x06', start)
    while pos != -1 and pos + _RECORD_HEAD <= size:
        (length,) = struct.unpack_from('<Q', buf, pos + 1)
        end = pos + _RECORD_HEAD + length
        if end <= size and _chunk_body(buf, pos, end) is not None:
            return pos
        pos = buf.find(b'\x06', pos + 1)
    return None


def _claimed_times(buf, pos: int, opcode: int):
    """The message time range a damaged chunk's header claims, if it looks sane."""
    if opcode != Opcode.CHUNK or len(buf) - pos < _RECORD_HEAD + 16:
        return None
    t0, t1 = struct.unpack_from('<QQ', buf, pos + _RECORD_HEAD)
    return (t0, t1) if 0 < t0 <= t1 < 2**63 else None


# --- bags (directories) --------------------------------------------------------------------

def bag_file(bag_dir) -> Path:
    """The one ``.mcap`` file of a rosbag2 directory."""
    bag_dir = Path(bag_dir)
    if not bag_dir.is_dir():
        raise BagDamagedError(f'{bag_dir}: no such bag directory')
    mcaps = sorted(bag_dir.glob('*.mcap'))
    if len(mcaps) != 1:
        raise BagDamagedError(f'{bag_dir}: expected one .mcap file, found {len(mcaps)}')
    return mcaps[0]


def scan_bag(bag_dir) -> Scan:
    """:func:`scan_mcap` of a bag, with channels lost with their chunk rebuilt if possible.

    Our recorder (``drift_tools.bag_writer``) numbers channels and schemas in the order its
    ``metadata.yaml`` lists the topics, so a channel whose definition was in a damaged chunk can
    be rebuilt from there; messages of a channel still unknown are dropped and counted.
    """
    from drift_tools.msgdef import MsgDefError, message_definition

    scan = scan_mcap(bag_file(bag_dir))
    used = {m.channel_id for m in scan.messages}
    missing = sorted(used - set(scan.channels))
    if missing:
        topics = _metadata_topics(bag_dir)
        schema_ids = {}
        for msgtype in (t for _, t in topics):
            schema_ids.setdefault(msgtype, len(schema_ids) + 1)
        rebuilt = []
        for cid in missing:
            if not 1 <= cid <= len(topics):
                continue
            topic, msgtype = topics[cid - 1]
            sid = schema_ids[msgtype]
            if sid not in scan.schemas:
                try:
                    text = message_definition(msgtype)
                except (MsgDefError, OSError):
                    continue
                scan.schemas[sid] = Schema(id=sid, name=msgtype, encoding='ros2msg',
                                           data=text.encode())
            elif scan.schemas[sid].name != msgtype:
                continue                 # numbering does not match: do not guess
            scan.channels[cid] = Channel(id=cid, topic=topic, message_encoding='cdr',
                                         schema_id=sid, metadata={})
            rebuilt.append(cid)
        scan.channels_from_metadata = tuple(rebuilt)
    kept = [m for m in scan.messages if m.channel_id in scan.channels]
    scan.orphans = len(scan.messages) - len(kept)
    scan.messages = kept
    return scan


def _metadata_topics(bag_dir) -> list:
    """``[(topic, msgtype), ...]`` in ``metadata.yaml`` order, if it was written by our recorder."""
    try:
        with open(Path(bag_dir) / 'metadata.yaml', encoding='utf-8') as fh:
            info = yaml.safe_load(fh)['rosbag2_bagfile_information']
        if (info.get('custom_data') or {}).get('writer') != 'drift_tools.bag_writer':
            return []
        return [(e['topic_metadata']['name'], e['topic_metadata']['type'])
                for e in info.get('topics_with_message_count') or []]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return []


@dataclass(frozen=True)
class Recovery:
    """What :func:`recover_bag` kept and dropped."""

    source: Path
    target: Path
    kept: dict                  # topic -> messages written
    problems: tuple             # lines, as Scan.problems

    def lines(self) -> list[str]:
        out = [f'{self.source} -> {self.target}: kept {sum(self.kept.values())} messages']
        out += [f'  {topic}: {n}' for topic, n in sorted(self.kept.items())]
        out += [f'  dropped: {p}' for p in self.problems] or ['  nothing dropped']
        return out


def recover_bag(source, target) -> Recovery:
    """Write what :func:`scan_bag` reads of ``source`` into the new bag directory ``target``.

    Messages are written in log-time order with their original times and sequence numbers; the
    metadata records are copied. ``source`` is only read.
    """
    from mcap.well_known import MessageEncoding
    from mcap.writer import Writer

    from drift_tools.bag_writer import write_metadata

    source, target = Path(source), Path(target)
    if target.exists() and any(target.iterdir()):
        raise FileExistsError(f'{target}: exists and is not empty')
    if target.resolve() == source.resolve():
        raise FileExistsError(f'{target}: is the source bag')
    scan = scan_bag(source)
    target.mkdir(parents=True, exist_ok=True)
    out = target / f'{target.name}_0.mcap'
    counts = {cid: 0 for cid in scan.channels}
    with open(out, 'wb') as fh:
        writer = Writer(fh)
        writer.start(profile='ros2', library='drift_tools.bag_salvage')
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                      for sid, s in sorted(scan.schemas.items())}
        channel_ids = {cid: writer.register_channel(
            c.topic, c.message_encoding or MessageEncoding.CDR, schema_ids.get(c.schema_id, 0),
            c.metadata) for cid, c in sorted(scan.channels.items())}
        for m in sorted(scan.messages, key=lambda m: m.log_time):
            writer.add_message(channel_ids[m.channel_id], m.log_time, m.data, m.publish_time,
                               m.sequence)
            counts[m.channel_id] += 1
        for record in scan.metadata:
            writer.add_metadata(record.name, record.metadata)
        writer.finish()
    times = [m.log_time for m in scan.messages]
    topics = [(c.topic, scan.schemas[c.schema_id].name if c.schema_id in scan.schemas else '',
               counts[cid], '', c.metadata.get('offered_qos_profiles', ''))
              for cid, c in sorted(scan.channels.items()) if counts[cid]]
    write_metadata(target, out.name, topics, min(times, default=None), max(times, default=None))
    kept = {scan.channels[cid].topic: n for cid, n in counts.items() if n}
    return Recovery(source, target, kept, tuple(scan.problems()))
