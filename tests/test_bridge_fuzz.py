"""Vehicle bridge fuzz, every bus description: labelled mutations each rejected with their named
fault; 100,000 random and corrupted PDUs judged like an independent receiver; a babbling bus."""
import random
import struct
from collections import Counter

import can
import e2e.p01
import e2e.p02
import e2e.p04
import e2e.p05
import pytest

from drift_control.params import config_dir
from drift_control.signals import VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import Codec
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.pdu import Pdu
from test_bridge_codec import DESCRIPTIONS

MAX_DELTA = 2
N_LABELLED = 12000
N_RANDOM = 100_000
KINDS = ('good', 'good', 'good', 'length', 'bitflip', 'data_id', 'counter_repeat',
         'counter_jump', 'range', 'unknown_id')


@pytest.fixture(scope='module', params=DESCRIPTIONS)
def codec(request):
    return Codec.load(config_dir() / request.param)


def _raw_span(s):
    """Smallest and largest physical value the signal's bits can carry."""
    lo, hi = (-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed \
        else (0, (1 << s.length) - 1)
    return lo * s.scale + s.offset, hi * s.scale + s.offset


def _out_of_range_value(rng, s):
    lo, hi = _raw_span(s)
    sides = [(s.maximum + s.scale, hi)] if hi >= s.maximum + s.scale else []
    sides += [(lo, s.minimum - s.scale)] if lo <= s.minimum - s.scale else []
    a, b = rng.choice(sides)
    return round(rng.uniform(a, b) / s.scale) * s.scale


def _values(rng, codec, name):
    return {s.name: rng.uniform(s.minimum, s.maximum) for s in codec.payload_signals(name)}


def _twin(codec, name):
    """Another PDU of the same length and profile: its protection on our id is a wrong data ID."""
    spec = codec.spec(name)
    return next((n for n in codec.names if n != name and codec.spec(n).length == spec.length
                 and codec.spec(n).e2e.profile == spec.e2e.profile), None)


def test_labelled_mutations_are_each_rejected_and_counted(codec):
    rng = random.Random(20261123)
    names = list(codec.state_frames)
    checker = FrameChecker(codec, names, MAX_DELTA)
    next_counter = Counter()          # per PDU: counter of the next in-sequence PDU
    last_ok: dict[str, int] = {}      # per PDU: counter the checker last took
    expected, accepted = Counter(), 0
    for i in range(N_LABELLED):
        name = rng.choice(names)
        spec, prot = codec.spec(name), codec.protection(name)
        kind = rng.choice(KINDS)
        if kind in ('counter_repeat', 'counter_jump') and name not in last_ok \
                or kind == 'data_id' and _twin(codec, name) is None:
            kind = 'good'
        values = _values(rng, codec, name)
        counter = next_counter[name]
        if kind == 'counter_repeat':
            counter = last_ok[name]
        elif kind == 'counter_jump':
            counter = last_ok.get(name, next_counter[name] - 1) \
                + rng.randint(MAX_DELTA + 1, prot.counter_modulo - 1)
        elif kind == 'range':
            sig = rng.choice([s for s in codec.payload_signals(name) if s.length > 1])
            values[sig.name] = _out_of_range_value(rng, sig)
        pdu = codec.encode(name, values, counter, strict=kind != 'range')
        data = bytearray(pdu.data)
        if kind == 'length':
            pdu = Pdu(pdu.id, bytes(data[:rng.randrange(spec.length)]), fd=pdu.fd)
        elif kind == 'bitflip':   # any single-bit error outside the header: the CRC catches it
            bit = rng.choice([b for b in range(8 * spec.length) if b not in prot.header_bits])
            data[bit // 8] ^= 1 << (bit % 8)
            pdu = Pdu(pdu.id, bytes(data), fd=pdu.fd)
            kind = 'crc'
        elif kind == 'data_id':
            forged = codec.encode(_twin(codec, name), _values(rng, codec, _twin(codec, name)),
                                  counter)
            pdu = Pdu(pdu.id, forged.data, fd=pdu.fd)
        elif kind == 'unknown_id':
            pdu = Pdu(rng.choice([0x7FF, 0x123, 0x9000_0110, 0x4000_0110]), bytes(data),
                      fd=pdu.fd)
        if kind in ('good', 'counter_jump', 'range'):   # the checker takes these counters
            last_ok[name] = counter % prot.counter_modulo
            next_counter[name] = counter + 1
        before = Counter(checker.faults)
        frame = checker.check(pdu, i * 1e-4)
        if kind == 'good':
            assert frame is not None, f'PDU {i}: a good {name} was rejected ({checker.faults})'
            accepted += 1
        else:
            assert frame is None, f'PDU {i}: a {kind} {name} was accepted'
            counted = checker.faults - before
            # an 8-bit CRC: a corrupted PDU passes one of the other data IDs' CRCs now and then
            named = {kind, 'data_id'} if kind == 'crc' and prot.profile in ('P01', 'P02') \
                else {kind}
            assert len(counted) == 1 and set(counted) <= named, f'PDU {i}: {kind} as {counted}'
            expected.update(counted)
    assert dict(checker.faults) == dict(expected)
    assert sum(checker.accepted.values()) == accepted
    assert accepted + sum(expected.values()) == N_LABELLED
    assert min(expected.values()) > 400, f'each fault kind exercised: {expected}'


class ReferenceReceiver:
    """An independent receiver, written from the profiles (autosar-e2e's CRC checks, the
    counter rules of AUTOSAR's E2E_PXXCheck), to judge the checker PDU by PDU."""

    def __init__(self, codec, names):
        self.codec, self.names = codec, set(names)
        self.last: dict[str, int] = {}

    def crc_ok(self, spec, data: bytes) -> bool:
        e, n = spec.e2e, len(data)
        if e.profile == 'P01':
            return e2e.p01.e2e_p01_check(bytearray(data), e.data_id, length=n, offset=e.offset)
        if e.profile == 'P02':
            return e2e.p02.e2e_p02_check(bytearray(data), bytes(e.data_id_list), length=n)
        if e.profile == 'P05':
            return e2e.p05.e2e_p05_check(bytearray(data), e.data_id, length=n, offset=e.offset)
        if e.profile == 'P04':
            length, _, data_id = struct.unpack_from('>HHI', data, e.offset)
            return length == n and data_id == e.data_id and \
                e2e.p04.e2e_p04_check(bytearray(data), e.data_id, length=n, offset=e.offset)
        raise AssertionError(e.profile)

    def counter(self, spec, data: bytes) -> int:
        o = spec.e2e.offset
        return {'P01': lambda: data[o + 1] & 0x0F, 'P02': lambda: data[o + 1] & 0x0F,
                'P05': lambda: data[o + 2],
                'P04': lambda: struct.unpack_from('>H', data, o + 2)[0]}[spec.e2e.profile]()

    def accepts(self, pdu: Pdu) -> bool:
        spec = self.codec.spec_of(pdu.id)
        if spec is None or spec.name not in self.names or pdu.fd != spec.fd \
                or len(pdu.data) != spec.length or not self.crc_ok(spec, pdu.data):
            return False
        modulo = self.codec.protection(spec.name).counter_modulo
        counter = self.counter(spec, pdu.data)
        if counter >= modulo:      # P01/P02: 15 is not a counter value
            return False
        step = (counter - self.last[spec.name]) % modulo if spec.name in self.last else 1
        if step == 0:
            return False
        self.last[spec.name] = counter           # authentic and new: the sequence moves on
        values = spec.message.decode(bytes(pdu.data), decode_choices=False)
        return step <= MAX_DELTA and all(s.minimum - 1e-9 <= values[s.name] <= s.maximum + 1e-9
                                         for s in self.codec.payload_signals(spec.name))


def test_random_pdus_never_escape_and_every_rejection_is_counted(codec):
    """100,000 random ids, lengths and bytes, and random corruptions of real PDUs, in one stream.

    No exception; each PDU's verdict equals that of an independent reference receiver, so
    nothing out of range or unprotected is ever accepted.
    """
    rng = random.Random(7)
    names = list(codec.state_frames)
    checker = FrameChecker(codec, names, MAX_DELTA)
    reference = ReferenceReceiver(codec, names)
    ids = [p.id for p in codec.description.pdus] + [0, 0x7FF, 0x10F, 0x119, 0x17F, 0x183]
    fd = codec.description.pdus[0].fd
    good = [codec.encode(n, v, i) for i in range(16)
            for n, v in codec.state_signals(VehicleState(0.0, 5.0, -0.2, 0.5)).items()]
    longest = max(p.length for p in codec.description.pdus)
    accepted = 0
    for i in range(N_RANDOM):
        if rng.random() < 0.5:
            base = rng.choice(good)
            data = bytearray(base.data)
            for _ in range(rng.randint(0, 3)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            cut = rng.choice((len(data),) * 3 + (rng.randint(0, len(data)),))
            pdu = Pdu(base.id, bytes(data[:cut]), fd=base.fd)
        else:
            pdu = Pdu(rng.choice(ids), bytes(rng.randrange(256)
                                            for _ in range(rng.randint(0, longest))),
                      fd=fd if rng.random() < 0.95 else not fd)
        verdict = checker.check(pdu, i * 1e-4) is not None
        assert verdict == reference.accepts(pdu), f'PDU {i}: {pdu}'
        accepted += verdict
    rejected = sum(checker.faults.values())
    assert sum(checker.accepted.values()) == accepted > 1000
    assert accepted + rejected + checker.foreign == N_RANDOM
    assert checker.faults['crc'] > 10_000 and checker.faults['unknown_id'] > 5000


def test_gateway_survives_a_babbling_bus():
    """10,000 random frames through a (virtual) bus into the gateway: no exception, counted."""
    codec = Codec.load(config_dir() / DESCRIPTIONS[0])
    rng = random.Random(11)
    params = load_bridge_params()
    with can.Bus('fuzz', interface='virtual') as noise, \
            can.Bus('fuzz', interface='virtual') as ours:
        gateway = Gateway(ours, codec, params)
        ids = [p.id for p in codec.description.pdus] + [0x123, 0x7FF]
        sent = 0
        for cycle in range(100):
            for _ in range(100):
                noise.send(can.Message(arbitration_id=rng.choice(ids), is_extended_id=False,
                                       data=bytes(rng.randrange(256)
                                                  for _ in range(rng.randint(0, 8)))))
                sent += 1
            gateway.step(cycle * 0.01)
            assert gateway.mode.name == 'OFF'
        stats = gateway.stats()
        assert sum(stats['rx'].values()) + sum(stats['faults'].values()) + stats['foreign'] == sent
        assert stats['tx'] == dict.fromkeys(('DS_CMD_STEER', 'DS_CMD_TORQUE', 'DS_CMD_STATUS'),
                                            100), 'OFF: the three PDUs, requesting nothing'
