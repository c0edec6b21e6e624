"""FlexRay frames out of ASAM CMP captures (EtherType 0x99FE) in pcap or pcapng files; read only.

A capture module (ASAM Capture Module Protocol) timestamps each bus frame it sees and sends it in
Ethernet frames of EtherType 0x99FE; a logger stores those as pcap or pcapng. Layouts as
Wireshark's dissector reads them, ``epan/dissectors/packet-asam-cmp.c`` (wireshark/wireshark at
18a1eb82b483; the channel flag from a later revision of it; all fields big-endian): CMP header of 8
bytes (version, reserved, device ID u16, message type (0x01 data), stream ID, stream sequence
counter u16), then data messages while 16 bytes remain, each a 16-byte header (timestamp u64 [ns],
interface ID u32, common flags u8 (segmentation 0x0C), payload type u8 (0x04 FlexRay), payload
length u16) and its payload. FlexRay payload: flags u16 (0x0001 frame CRC error, 0x0002 header CRC
error, 0x0004 null frame, 0x0200 channel B), reserved u16, header CRC u16, frame ID u16, cycle u8,
frame CRC u24, reserved u8, data length u8, data. Captures whose modules predate the channel flag
read as channel A.

Frames with a CRC error, null frames and segmented messages are skipped and counted; so is
everything that does not parse. A file that is neither pcap nor pcapng is a ParamError.
"""
from __future__ import annotations

import mmap
import os
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

from drift_control.params import ParamError

ETHERTYPE_CMP = 0x99FE
VLAN_TAGS = (0x8100, 0x88A8)
LINKTYPE_ETHERNET = 1
CMP_DATA_MSG, CMP_FLEXRAY = 0x01, 0x04
CMP_HEADER = struct.Struct('>BBHBBH')        # version, res, device ID, msg type, stream, seq
MSG_HEADER = struct.Struct('>QIBBH')         # timestamp [ns], interface, flags, type, length
FLEXRAY = struct.Struct('>HHHHB3sBB')        # flags, res, header CRC, frame ID, cycle, CRC...
SEGMENTED = 0x0C
FR_CRC_ERRORS, FR_NULL_FRAME, FR_CHANNEL_B = 0x0003, 0x0004, 0x0200
PCAPNG_MAGIC = b'\x0a\x0d\x0d\x0a'         # section header block type
PCAP_MAGIC = {b'\xd4\xc3\xb2\xa1': '<', b'\x4d\x3c\xb2\xa1': '<',     # us, ns timestamps
              b'\xa1\xb2\xc3\xd4': '>', b'\xa1\xb2\x3c\x4d': '>'}


@dataclass(frozen=True, slots=True)
class FlexrayFrame:
    """One FlexRay frame as the capture module saw it.

    Attributes
    ----------
    timestamp : float
        The capture module's timestamp [s] (its clock, usually gPTP-synchronised).
    interface_id : int
        The capture module's interface the frame came in on.
    channel : str
        'A' or 'B'.
    slot : int
        Frame ID (static segment: the slot).
    cycle : int
        Cycle counter 0..63.
    data : bytes
        The frame's payload.
    """

    timestamp: float
    interface_id: int
    channel: str
    slot: int
    cycle: int
    data: bytes


def read_flexray(path: str | os.PathLike, counts: Counter | None = None
                 ) -> Iterator[FlexrayFrame]:
    """The FlexRay frames of a pcap/pcapng capture, in file order (read lazily).

    ``counts``, if given, gets what was skipped: 'not_cmp', 'not_ethernet', 'crc_error',
    'null_frame', 'segmented', 'malformed', 'truncated_capture', and 'flexray' for each frame.
    Raises ParamError (one line) at once for a file that is not a capture.
    """
    counts = Counter() if counts is None else counts
    try:
        with open(path, 'rb') as f:
            magic = f.read(4)
    except OSError as err:
        raise ParamError(f'{path}: cannot read the capture: {err.strerror}') from None
    if magic not in PCAP_MAGIC and magic != PCAPNG_MAGIC:
        raise ParamError(f'{path}: not a pcap or pcapng file (magic {magic.hex() or "empty"})')
    return _frames(path, magic, counts)


def _frames(path, magic: bytes, counts: Counter) -> Iterator[FlexrayFrame]:
    with open(path, 'rb') as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        packets = _pcapng(data, counts) if magic == PCAPNG_MAGIC \
            else _pcap(data, PCAP_MAGIC[magic], counts)
        for linktype, packet in packets:
            if linktype != LINKTYPE_ETHERNET:
                counts['not_ethernet'] += 1
                continue
            cmp = _cmp_payload(packet)
            if cmp is None:
                counts['not_cmp'] += 1
                continue
            yield from _flexray_frames(cmp, counts)


def _cmp_payload(frame: bytes) -> bytes | None:
    """The EtherType 0x99FE payload of an Ethernet frame (VLAN tags skipped), else None."""
    offset = 12
    while offset + 2 <= len(frame):
        ethertype = int.from_bytes(frame[offset:offset + 2], 'big')
        if ethertype in VLAN_TAGS:
            offset += 4
            continue
        return frame[offset + 2:] if ethertype == ETHERTYPE_CMP else None
    return None


def _flexray_frames(cmp: bytes, counts: Counter) -> Iterator[FlexrayFrame]:
    if len(cmp) < CMP_HEADER.size:
        counts['malformed'] += 1
        return
    if CMP_HEADER.unpack_from(cmp)[3] != CMP_DATA_MSG:
        return                                  # control, status, vendor: no bus frames
    offset = CMP_HEADER.size
    while len(cmp) - offset >= MSG_HEADER.size:
        ns, interface, flags, kind, length = MSG_HEADER.unpack_from(cmp, offset)
        start = offset + MSG_HEADER.size
        offset = start + length
        if offset > len(cmp):
            counts['malformed'] += 1
            return
        if kind != CMP_FLEXRAY:
            continue
        if flags & SEGMENTED:
            counts['segmented'] += 1
            continue
        payload = cmp[start:offset]
        if len(payload) < FLEXRAY.size:
            counts['malformed'] += 1
            continue
        fr_flags, _, _, slot, cycle, _, _, n = FLEXRAY.unpack_from(payload)
        if FLEXRAY.size + n > len(payload):
            counts['malformed'] += 1
        elif fr_flags & FR_CRC_ERRORS:
            counts['crc_error'] += 1
        elif fr_flags & FR_NULL_FRAME:
            counts['null_frame'] += 1
        else:
            counts['flexray'] += 1
            yield FlexrayFrame(ns * 1e-9, interface, 'B' if fr_flags & FR_CHANNEL_B else 'A',
                               slot, cycle, bytes(payload[FLEXRAY.size:FLEXRAY.size + n]))


def _pcap(data, order: str, counts: Counter) -> Iterator[tuple[int, bytes]]:
    if len(data) < 24:
        counts['truncated_capture'] += 1
        return
    linktype = struct.unpack_from(order + 'I', data, 20)[0] & 0x0FFFFFFF   # upper bits: FCS
    offset = 24
    while offset < len(data):
        if offset + 16 > len(data):
            counts['truncated_capture'] += 1
            return
        captured = struct.unpack_from(order + 'I', data, offset + 8)[0]
        start = offset + 16
        offset = start + captured
        if offset > len(data):
            counts['truncated_capture'] += 1
            return
        yield linktype, data[start:offset]


def _pcapng(data, counts: Counter) -> Iterator[tuple[int, bytes]]:
    order, linktypes, offset = '<', [], 0
    while offset < len(data):
        if offset + 12 > len(data):
            counts['truncated_capture'] += 1
            return
        if data[offset:offset + 4] == PCAPNG_MAGIC:     # section header: byte order anew
            order = '<' if data[offset + 8:offset + 12] == b'\x4d\x3c\x2b\x1a' else '>'
            linktypes = []
        kind, length = struct.unpack_from(order + 'II', data, offset)
        if length < 12 or length % 4 or offset + length > len(data):
            counts['truncated_capture'] += 1
            return
        body = data[offset + 8:offset + length - 4]
        offset += length
        if kind == 1 and len(body) >= 8:                     # interface description
            linktypes.append(struct.unpack_from(order + 'H', body)[0])
        elif kind == 6 and len(body) >= 20:                  # enhanced packet
            interface, _, _, captured, _ = struct.unpack_from(order + 'IIIII', body)
            if interface < len(linktypes) and 20 + captured <= len(body):
                yield linktypes[interface], body[20:20 + captured]
            else:
                counts['malformed'] += 1
        elif kind == 3 and len(body) >= 4 and linktypes:     # simple packet (interface 0)
            original = struct.unpack_from(order + 'I', body)[0]
            yield linktypes[0], body[4:4 + original]


__all__ = ['ETHERTYPE_CMP', 'FlexrayFrame', 'read_flexray']
