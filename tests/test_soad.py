"""Socket Adaptor PDU header framing and the UDP transport, on 127.0.0.1 with ephemeral ports."""
import random
import select
import socket
import struct
import time
from collections import Counter

import pytest

from drift_control.params import ParamError
from drift_vehicle_bridge.pdu import Pdu
from drift_vehicle_bridge.soad import (MAX_DATAGRAM, DatagramError, UdpTransport, pack,
                                       parse_endpoint, unpack)

LO = '127.0.0.1'
N_FUZZ = 100_000
SEED = 25


@pytest.fixture
def car():
    """The gateway's side: a plain UDP socket, independent of the transport under test."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((LO, 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


@pytest.fixture
def ours(car):
    with UdpTransport(local=(LO, 0), remote=car.getsockname()) as transport:
        yield transport


# --- framing ---------------------------------------------------------------------------------

def test_header_is_big_endian_id_then_length_then_payload():
    # packet-pdu-transport.c: ID at offset 0, length at 4, both ENC_BIG_ENDIAN; payload from 8.
    datagram = pack([Pdu(0x12345678, b'\xaa\xbb'), Pdu(0x00000102, b'')])
    assert datagram == bytes.fromhex('12345678 00000002 aabb' '00000102 00000000')


def test_pack_unpack_round_trip_keeps_order_ids_and_payloads():
    pdus = [Pdu(0, b''), Pdu(0xFFFFFFFF, bytes(range(8))), Pdu(0x10, b'\x00' * 64),
            Pdu(0x10, b'x')]
    got = unpack(pack(pdus), timestamp=12.5)
    assert [(p.id, p.data) for p in got] == [(p.id, p.data) for p in pdus]
    assert all(p.timestamp == 12.5 and p.fd is None for p in got)


@pytest.mark.parametrize('pdu_id', [-1, 1 << 32])
def test_pack_refuses_an_id_wider_than_32_bits(pdu_id):
    with pytest.raises(ValueError, match='32 bits'):
        pack([Pdu(pdu_id, b'')])


def test_empty_datagram_holds_no_pdus():
    assert unpack(b'') == []


def test_zero_length_pdu_is_well_formed():
    assert unpack(struct.pack('>II', 7, 0)) == [Pdu(7, b'')]


@pytest.mark.parametrize('tail', [b'\x00', b'\x00' * 7])
def test_truncated_header_names_itself_and_keeps_the_whole_pdus_before_it(tail):
    good = pack([Pdu(1, b'ab'), Pdu(2, b'cd')])
    with pytest.raises(DatagramError) as info:
        unpack(good + tail)
    err = info.value
    assert (err.reason, err.offset) == ('truncated_header', len(good))
    assert [p.id for p in err.pdus] == [1, 2]
    assert isinstance(err, ValueError) and 'truncated header' in str(err)


def test_length_past_the_end_names_itself_and_keeps_the_whole_pdus_before_it():
    good = pack([Pdu(1, b'ab')])
    with pytest.raises(DatagramError) as info:
        unpack(good + struct.pack('>II', 9, 5) + b'abcd')     # one byte short
    assert (info.value.reason, info.value.offset) == ('length_past_end', len(good))
    assert info.value.pdus == [Pdu(1, b'ab')]
    with pytest.raises(DatagramError, match='length past end'):
        unpack(struct.pack('>II', 9, 0xFFFFFFFF))          # no 8 + length overflow here


# --- endpoints -------------------------------------------------------------------------------

@pytest.mark.parametrize('text, expected', [('127.0.0.1:30501', ('127.0.0.1', 30501)),
                                            ('gateway.local:0', ('gateway.local', 0)),
                                            (' [::1]:30501 ', ('::1', 30501))])
def test_parse_endpoint(text, expected):
    assert parse_endpoint(text) == expected


@pytest.mark.parametrize('text', ['127.0.0.1', '127.0.0.1:', ':30501', '127.0.0.1:65536',
                                  '127.0.0.1:-1', '127.0.0.1:3e4', '::1:30501', '[nope]:1',
                                  '127.0.0.1:\u00b2', 30501, None])
def test_parse_endpoint_refuses_in_one_line_naming_the_key(text):
    with pytest.raises(ParamError) as info:
        parse_endpoint(text, key='bridge.soad.remote')
    assert str(info.value).startswith('bridge.soad.remote: ') and '\n' not in str(info.value)


def test_unresolvable_or_unusable_endpoints_are_param_errors():
    with pytest.raises(ParamError, match='remote'):
        UdpTransport(local=(LO, 0), remote=('no-such-host.invalid', 30501))
    with pytest.raises(ParamError, match='port 0'):
        UdpTransport(local=(LO, 0), remote=(LO, 0))


# --- the transport ---------------------------------------------------------------------------

def test_flush_sends_the_queue_as_one_datagram_to_the_remote(car, ours):
    ours.send(Pdu(0x101, b'\x01' * 8))
    ours.send(Pdu(0x102, b'\x02' * 8))
    ours.flush()
    datagram, sender = car.recvfrom(65536)
    assert sender == ours.local_address
    assert unpack(datagram) == [Pdu(0x101, b'\x01' * 8), Pdu(0x102, b'\x02' * 8)]
    ours.flush()                                            # nothing queued: nothing sent
    car.setblocking(False)
    with pytest.raises(BlockingIOError):
        car.recvfrom(65536)
    assert ours.sent == Counter(datagrams=1, pdus=2)


def test_flush_splits_at_the_safe_datagram_size_and_keeps_order(car, ours):
    pdus = [Pdu(i, bytes([i % 256]) * 8) for i in range(300)]        # 300 x 16 bytes
    big = Pdu(0xB16, b'\xff' * 2000)                                  # alone, IP fragments it
    for pdu in pdus[:150] + [big] + pdus[150:]:
        ours.send(pdu)
    ours.flush()
    got, sizes = [], []
    while len(got) < 301:
        datagram, _ = car.recvfrom(65536)
        sizes.append(len(datagram))
        got += unpack(datagram)
    assert got == pdus[:150] + [big] + pdus[150:]
    assert max(s for s in sizes if s != 2008) <= MAX_DATAGRAM[socket.AF_INET] and 2008 in sizes
    assert len(sizes) == ours.sent['datagrams'] == 5    # 92 + 58 | big | 92 + 58 PDUs


def test_a_pdu_that_cannot_fit_a_datagram_is_refused_at_send(ours):
    with pytest.raises(ValueError, match='do not fit'):
        ours.send(Pdu(1, bytes(65500)))
    with pytest.raises(ValueError, match='32 bits'):
        ours.send(Pdu(1 << 32, b''))


def test_recv_hands_over_a_datagram_in_order_stamped_with_its_arrival(car):
    ticks = iter([100.0, 200.0])
    with UdpTransport(local=(LO, 0), remote=car.getsockname(), clock=lambda: next(ticks)) as ours:
        car.sendto(pack([Pdu(1, b'a'), Pdu(2, b'b')]), ours.local_address)
        car.sendto(pack([Pdu(3, b'c')]), ours.local_address)
        got = [ours.recv(timeout=2.0) for _ in range(3)]
        assert [(p.id, p.data, p.timestamp) for p in got] == \
            [(1, b'a', 100.0), (2, b'b', 100.0), (3, b'c', 200.0)]
        assert ours.recv() is None
        assert ours.received == Counter(datagrams=2, pdus=3)


def test_recv_times_out_with_none(ours):
    start = time.monotonic()
    assert ours.recv(timeout=0.05) is None
    assert 0.05 <= time.monotonic() - start < 1.0
    assert ours.recv() is None


def test_garbage_is_counted_and_the_good_pdus_still_arrive(car, ours):
    to = ours.local_address
    car.sendto(pack([Pdu(1, b'ok')]) + b'\x00\x01\x02', to)            # truncated header
    car.sendto(pack([Pdu(2, b'ok')]) + struct.pack('>II', 3, 99), to)  # length past end
    car.sendto(b'', to)
    car.sendto(pack([Pdu(4, b'')]), to)                                # zero length: handed over
    got = [ours.recv(timeout=2.0) for _ in range(3)]
    assert [(p.id, p.data) for p in got] == [(1, b'ok'), (2, b'ok'), (4, b'')]
    assert ours.errors == Counter(truncated_header=1, length_past_end=1, empty_datagram=1)


def test_datagrams_from_anyone_but_the_remote_are_dropped(car, ours):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        stranger.bind((LO, 0))
        stranger.sendto(pack([Pdu(0x666, b'evil')]), ours.local_address)
        car.sendto(pack([Pdu(1, b'ok')]), ours.local_address)      # sent after: arrives after
        pdu = ours.recv(timeout=2.0)
    assert (pdu.id, pdu.data) == (1, b'ok')
    assert ours.errors == Counter(foreign_sender=1)


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as sock:
            sock.bind(('::1', 0))
        return True
    except OSError:
        return False


@pytest.mark.skipif(not _ipv6_loopback(), reason='no IPv6 loopback here')
def test_ipv6_endpoints_work_the_same():
    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as car:
        car.bind(('::1', 0))
        car.settimeout(2.0)
        with UdpTransport(local=('::1', 0), remote=car.getsockname()[:2]) as ours:
            assert ours.max_datagram == MAX_DATAGRAM[socket.AF_INET6]
            ours.send(Pdu(5, b'v6'))
            ours.flush()
            datagram, _ = car.recvfrom(65536)
            car.sendto(datagram, ours.local_address)
            pdu = ours.recv(timeout=2.0)
    assert (pdu.id, pdu.data) == (5, b'v6')


def test_shutdown_closes_the_socket_and_may_be_called_twice(car):
    with UdpTransport(local=(LO, 0), remote=car.getsockname()) as ours:
        ours.send(Pdu(1, b''))
    assert ours.fileno() == -1
    ours.shutdown()
    with pytest.raises(OSError):      # a closed transport says so; it does not look idle
        ours.recv()


# --- fuzz ------------------------------------------------------------------------------------

def _fuzz_datagrams(rng: random.Random, n: int):
    """Random bytes, and valid datagrams cut, bit-flipped or with a wrong length field."""
    for _ in range(n):
        kind = rng.randrange(4)
        if kind == 0:
            yield rng.randbytes(rng.randrange(0, 40))
            continue
        pdus = [Pdu(rng.getrandbits(32), rng.randbytes(rng.choice((0, 1, 8, 8, 16, 64))))
                for _ in range(rng.randrange(1, 5))]
        datagram = bytearray(pack(pdus))
        if kind == 1:
            del datagram[rng.randrange(len(datagram) + 1):]
        elif kind == 2:
            for _ in range(rng.randrange(1, 4)):
                datagram[rng.randrange(len(datagram))] ^= 1 << rng.randrange(8)
        else:
            struct.pack_into('>I', datagram, 4, rng.choice((0, 1, 9, 63, 65, 0xFFFFFFFF)))
        yield bytes(datagram)


def _outcome(datagram: bytes) -> tuple[str, int]:
    """(what unpack says, how many PDUs it gives); checks that the PDUs re-pack to the bytes."""
    try:
        pdus = unpack(datagram)
        assert pack(pdus) == datagram
        return ('empty_datagram' if not datagram else 'ok'), len(pdus)
    except DatagramError as err:
        assert pack(err.pdus) == datagram[:err.offset]
        return err.reason, len(err.pdus)


def test_fuzzed_datagrams_never_raise_out_of_recv_and_every_fault_is_counted(car, ours):
    rng = random.Random(SEED)
    expected, expected_pdus, got_pdus = Counter(), 0, 0
    batch = []
    for datagram in _fuzz_datagrams(rng, N_FUZZ):
        reason, n = _outcome(datagram)
        expected[reason] += 1
        expected_pdus += n
        batch.append(datagram)
        if len(batch) == 50:     # well inside the socket's receive buffer: nothing is dropped
            for d in batch:
                car.sendto(d, ours.local_address)
            got_pdus += _drain(ours, len(batch))
            batch = []
    for d in batch:
        car.sendto(d, ours.local_address)
    got_pdus += _drain(ours, len(batch))
    assert ours.received['datagrams'] == N_FUZZ
    assert got_pdus == expected_pdus == ours.received['pdus']
    assert ours.errors == Counter({k: v for k, v in expected.items() if k != 'ok'})
    # Every fault kind is exercised, often (seed 25: 64.6 k lengths past the end, 15.6 k
    # truncated headers, 1.4 k empty datagrams, 18.4 k whole ones).
    assert min(expected['truncated_header'], expected['length_past_end'],
               expected['empty_datagram']) > 1000, expected


def _drain(transport: UdpTransport, datagrams: int) -> int:
    """Receive until ``datagrams`` more datagrams were read; the number of PDUs handed over."""
    target = transport.received['datagrams'] + datagrams
    n = 0
    while True:
        while transport.recv() is not None:
            n += 1
        if transport.received['datagrams'] >= target:
            return n
        ready, _, _ = select.select([transport], [], [], 2.0)
        assert ready, 'datagrams lost on loopback'

