"""Vehicle bridge fuzz: >= 10,000 mutated and random frames; nothing escapes, each bad one counts."""
import random
from collections import Counter

import can
import pytest
from crccheck.crc import Crc8SaeJ1850

from drift_control.signals import VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import STATE_FRAMES, Codec, state_signals
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.vehicle_side import default_dbc

E2E = ('CRC', 'AliveCounter')
MAX_DELTA = 2
N_LABELLED = 12000
N_RANDOM = 10000
KINDS = ('good', 'good', 'good', 'dlc', 'crc', 'bitflip', 'counter_repeat', 'counter_jump',
         'range', 'unknown_id')


@pytest.fixture(scope='module')
def codec():
    return Codec.load(default_dbc())


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
    return {s.name: rng.uniform(s.minimum, s.maximum)
            for s in codec.message(name).signals if s.name not in E2E}


def test_labelled_mutations_are_each_rejected_and_counted(codec):
    rng = random.Random(20261123)
    checker = FrameChecker(codec, STATE_FRAMES, MAX_DELTA, resync_after=10.0)
    known_ids = {m.frame_id for m in codec.db.messages}
    next_counter = Counter()          # per frame: counter of the next in-sequence frame
    last_ok: dict[str, int] = {}      # per frame: counter the checker last took
    expected = Counter()
    accepted = 0
    for i in range(N_LABELLED):
        now = i * 1e-4
        name = rng.choice(list(STATE_FRAMES))
        kind = rng.choice(KINDS)
        if kind == 'counter_repeat' and name not in last_ok:
            kind = 'good'
        values = _values(rng, codec, name)
        counter = next_counter[name]
        if kind == 'counter_repeat':
            counter = last_ok[name]
        elif kind == 'counter_jump':
            counter = last_ok.get(name, next_counter[name] - 1) + rng.randint(MAX_DELTA + 1, 15)
        elif kind == 'range':
            sig = rng.choice([s for s in codec.message(name).signals
                              if s.name not in E2E and s.length > 1])
            values[sig.name] = _out_of_range_value(rng, sig)
        msg = codec.encode(name, values, counter, strict=kind != 'range')
        data = bytearray(msg.data)
        if kind == 'dlc':
            msg = can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False,
                              data=data[:rng.randint(0, 7)])
        elif kind == 'crc':
            data[0] ^= rng.randint(1, 255)
            msg.data = data
        elif kind == 'bitflip':   # any single-bit error in the payload: CRC8 must catch it
            bit = rng.randrange(8, 64)
            data[bit // 8] ^= 1 << (bit % 8)
            msg.data = data
            kind = 'crc'
        elif kind == 'unknown_id':
            extended = rng.random() < 0.3
            arb = rng.randrange(1 << 29) if extended else rng.randrange(1 << 11)
            if not extended and arb in known_ids:
                arb = 0x7FF
            msg = can.Message(arbitration_id=arb, is_extended_id=extended,
                              data=bytes(rng.randrange(256) for _ in range(rng.randint(0, 8))))
        if kind in ('good', 'counter_jump', 'range'):   # the checker takes these counters
            last_ok[name] = counter % 16
            next_counter[name] = counter + 1
        frame = checker.check(msg, now)
        if kind == 'good':
            assert frame is not None, f'frame {i}: a good {name} was rejected ({checker.faults})'
            accepted += 1
        else:
            assert frame is None, f'frame {i}: a {kind} {name} was accepted'
            expected[kind] += 1
            assert checker.faults[kind] == expected[kind], f'frame {i}: {kind} not counted'
    assert dict(checker.faults) == dict(expected)
    assert sum(checker.accepted.values()) == accepted
    assert accepted + sum(expected.values()) == N_LABELLED
    assert min(expected.values()) > 500, f'each fault kind exercised: {expected}'


class ReferenceReceiver:
    """An independent E2E receiver, written from the DBC's comment, to judge the checker."""

    def __init__(self, codec):
        self.db = codec.db
        self.last = {}

    def accepts(self, msg) -> bool:
        try:
            m = self.db.get_message_by_frame_id(msg.arbitration_id)
        except KeyError:
            return False
        if msg.is_extended_id or msg.is_remote_frame or len(msg.data) != 8 \
                or m.name not in STATE_FRAMES:
            return False
        data_id = m.dbc.attributes['E2E_DataID'].value
        if msg.data[0] != Crc8SaeJ1850.calc(data_id.to_bytes(2, 'little') + bytes(msg.data[1:])):
            return False
        values = m.decode(bytes(msg.data), decode_choices=False)
        counter = values['AliveCounter']
        step = (counter - self.last[m.name]) % 16 if m.name in self.last else 1
        if step == 0:
            return False
        self.last[m.name] = counter           # authentic and new: the sequence moves on
        return step <= MAX_DELTA and all(s.minimum - 1e-9 <= values[s.name] <= s.maximum + 1e-9
                                         for s in m.signals)


def test_random_frames_never_escape_and_every_rejection_is_counted(codec):
    """Random IDs, lengths and bytes, and random corruptions of real frames, in one stream.

    Each frame's verdict must equal that of an independent reference receiver.
    """
    rng = random.Random(7)
    checker = FrameChecker(codec, STATE_FRAMES, MAX_DELTA, resync_after=10.0)
    reference = ReferenceReceiver(codec)
    ids = [m.frame_id for m in codec.db.messages] + [0, 0x7FF, 0x10F, 0x119, 0x17F, 0x183]
    good = [codec.encode(n, v, i) for i in range(16)
            for n, v in state_signals(VehicleState(0.0, 5.0, -0.2, 0.5)).items()]
    accepted = 0
    for i in range(N_RANDOM):
        if rng.random() < 0.5:
            base = rng.choice(good)
            data = bytearray(base.data)
            for _ in range(rng.randint(0, 3)):
                data[rng.randrange(8)] = rng.randrange(256)
            msg = can.Message(arbitration_id=base.arbitration_id, is_extended_id=False,
                              data=data[:rng.choice((8, 8, 8, rng.randint(0, 8)))])
        else:
            msg = can.Message(arbitration_id=rng.choice(ids), is_extended_id=rng.random() < 0.1,
                              is_remote_frame=rng.random() < 0.02,
                              data=bytes(rng.randrange(256) for _ in range(rng.randint(0, 8))))
        verdict = checker.check(msg, i * 1e-4) is not None
        assert verdict == reference.accepts(msg), f'frame {i}: {msg}'
        accepted += verdict
    rejected = sum(checker.faults.values())
    assert sum(checker.accepted.values()) == accepted > 100
    assert accepted + rejected + checker.foreign == N_RANDOM
    assert checker.faults['crc'] > 1000 and checker.faults['unknown_id'] > 500


def test_gateway_survives_a_babbling_bus(codec):
    """10,000 random frames through a (virtual) bus into the gateway: no exception, counted."""
    rng = random.Random(11)
    params = load_bridge_params()
    with can.Bus('fuzz', interface='virtual') as noise, \
            can.Bus('fuzz', interface='virtual') as ours:
        gateway = Gateway(ours, codec, params)
        ids = [m.frame_id for m in codec.db.messages] + [0x123, 0x7FF]
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
        assert stats['tx'] == {'DS_CMD_STATUS': 100}, 'OFF: only the heartbeat is written'
