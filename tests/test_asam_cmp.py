"""ASAM CMP FlexRay frames out of pcap / pcapng captures written here byte by byte."""
import random
import struct
from collections import Counter

import pytest

from drift_control.params import ParamError
from drift_vehicle_bridge.asam_cmp import FlexrayFrame, read_flexray

MACS = bytes.fromhex('ffffffffffff' '020000000001')


def cmp_message(kind, payload, ns=0, interface=7, flags=0):
    return struct.pack('>QIBBH', ns, interface, flags, kind, len(payload)) + payload


def flexray(slot, cycle, data, flags=0):
    return struct.pack('>HHHHB3sBB', flags, 0, 0x1234, slot, cycle, b'\x00\x00\x00', 0,
                       len(data)) + data


def cmp_frame(*messages, msg_type=0x01, vlan=False):
    """An Ethernet frame of EtherType 0x99FE carrying one CMP data message group."""
    header = struct.pack('>BBHBBH', 1, 0, 0x0042, msg_type, 0, 1)
    tag = struct.pack('>HH', 0x8100, 5) if vlan else b''
    return MACS + tag + b'\x99\xfe' + header + b''.join(messages)


def pcap(packets, order='<', linktype=1):
    out = struct.pack(order + 'IHHiIII', 0xA1B2C3D4, 2, 4, 0, 0, 65535, linktype)
    for p in packets:
        out += struct.pack(order + 'IIII', 0, 0, len(p), len(p)) + p
    return out


def block(kind, body):
    body += b'\x00' * (-len(body) % 4)
    return struct.pack('<II', kind, len(body) + 12) + body + struct.pack('<I', len(body) + 12)


def pcapng(packets):
    out = block(0x0A0D0D0A, struct.pack('<IHHq', 0x1A2B3C4D, 1, 0, -1))
    out += block(1, struct.pack('<HHI', 1, 0, 0))
    for i, p in enumerate(packets):
        out += block(6, struct.pack('<IIIII', 0, 0, 0, len(p), len(p)) + p) if i % 2 == 0 \
            else block(3, struct.pack('<I', len(p)) + p)
    return out


PACKETS = [
    cmp_frame(cmp_message(4, flexray(12, 3, b'\x01' * 8), ns=1_500_000_000),
              cmp_message(1, b'\x00' * 20),                                      # CAN: skipped
              cmp_message(4, flexray(13, 3, b'\x02' * 16, flags=0x0200), ns=1_500_000_100)),
    MACS + b'\x08\x00' + b'\x45' * 40,                                           # IPv4
    cmp_frame(cmp_message(4, flexray(14, 4, b'', flags=0x0004)),                 # null frame
              cmp_message(4, flexray(15, 4, b'\x03' * 8, flags=0x0001)),         # frame CRC
              cmp_message(4, flexray(16, 4, b'\x04' * 8), flags=0x04)),          # segmented
    cmp_frame(cmp_message(4, flexray(20, 5, b'\x05' * 8), ns=2_000_000_000), vlan=True),
    cmp_frame(cmp_message(4, flexray(21, 5, b'\x06' * 8))[:-3]),                 # cut short
]
EXPECTED = [FlexrayFrame(1.5, 7, 'A', 12, 3, b'\x01' * 8),
            FlexrayFrame(1.5000001, 7, 'B', 13, 3, b'\x02' * 16),
            FlexrayFrame(2.0, 7, 'A', 20, 5, b'\x05' * 8)]
EXPECTED_COUNTS = Counter(flexray=3, not_cmp=1, null_frame=1, crc_error=1, segmented=1,
                          malformed=1)


@pytest.mark.parametrize('write', [lambda: pcap(PACKETS), lambda: pcap(PACKETS, '>'),
                                   lambda: pcapng(PACKETS)], ids=['pcap', 'pcap-be', 'pcapng'])
def test_flexray_frames_come_out_and_the_rest_is_counted(tmp_path, write):
    path = tmp_path / 'capture'
    path.write_bytes(write())
    counts = Counter()
    frames = list(read_flexray(path, counts))
    assert [(f.channel, f.slot, f.cycle, f.data, f.interface_id) for f in frames] == \
        [(f.channel, f.slot, f.cycle, f.data, f.interface_id) for f in EXPECTED]
    assert [f.timestamp for f in frames] == pytest.approx([f.timestamp for f in EXPECTED],
                                                          abs=1e-12)
    assert counts == EXPECTED_COUNTS


def test_a_capture_cut_mid_record_keeps_what_came_before(tmp_path):
    path = tmp_path / 'cut.pcapng'
    path.write_bytes(pcapng(PACKETS)[:-10])
    counts = Counter()
    assert len(list(read_flexray(path, counts))) == 3
    assert counts['truncated_capture'] == 1


def test_other_link_types_are_counted(tmp_path):
    path = tmp_path / 'raw.pcap'
    path.write_bytes(pcap(PACKETS, linktype=101))
    counts = Counter()
    assert list(read_flexray(path, counts)) == []
    assert counts == Counter(not_ethernet=len(PACKETS))


@pytest.mark.parametrize('content', [b'', b'not a capture at all'])
def test_a_file_that_is_no_capture_is_a_one_line_param_error_at_once(tmp_path, content):
    path = tmp_path / 'x.pcap'
    path.write_bytes(content)
    with pytest.raises(ParamError, match='not a pcap or pcapng file'):
        read_flexray(path)                     # before any iteration
    with pytest.raises(ParamError, match='cannot read'):
        read_flexray(tmp_path / 'missing.pcap')


def test_mutated_captures_never_raise(tmp_path):
    rng = random.Random(25)
    good = [pcap(PACKETS), pcapng(PACKETS)]
    path = tmp_path / 'fuzz'
    for _ in range(2000):
        data = bytearray(rng.choice(good))
        for _ in range(rng.randrange(1, 6)):
            data[rng.randrange(4, len(data))] = rng.randrange(256)   # the magic stays
        if rng.random() < 0.3:
            del data[rng.randrange(4, len(data) + 1):]
        path.write_bytes(bytes(data))
        for frame in read_flexray(path):
            assert frame.channel in 'AB' and len(frame.data) <= 255
