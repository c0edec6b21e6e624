"""The bridge's E2E receive side on every description: each fault gets its named status and
state, and the signals of that PDU are invalid in the same cycle; a good stream recovers."""
import dataclasses

import pytest

from drift_control.params import config_dir
from drift_control.signals import Validity, VehicleState
from drift_vehicle_bridge.codec import Codec, VALIDITY_SIGNALS
from drift_vehicle_bridge.monitor import StateMonitor
from drift_vehicle_bridge.params import MonitorParams
from drift_vehicle_bridge.pdu import Pdu
from test_bridge_codec import DESCRIPTIONS

STATE = VehicleState(stamp=0.0, V=9.0, beta=-0.5, r=0.8, vx=8.0, vy=-4.3,
                     wheel_speeds=(27.0, 27.5, 41.0, 43.0), delta=-0.12, drive_torque=2300.0)
VICTIM = 'beta'                    # the PDU carrying it gets the fault
FAULTS = ('crc', 'data_id', 'length', 'counter_repeat', 'counter_jump', 'timeout')
STATUS = {'crc': 'ERROR (crc)', 'data_id': 'ERROR (data_id)', 'length': 'ERROR (length)',
          'counter_repeat': 'REPEATED', 'counter_jump': 'WRONG_SEQUENCE',
          'timeout': 'NO_NEW_DATA'}


class Link:
    """The car's state PDUs, one cycle of 10 ms at a time, into a StateMonitor."""

    def __init__(self, codec):
        self.codec, self.k = codec, 0
        self.monitor = StateMonitor(codec, MonitorParams())
        self.victim = next(n for n, sigs in codec.state_frames.items() if VICTIM in sigs)

    def cycle(self, fault=None):
        self.k += 1
        now = 0.01 * self.k
        for name, values in self.codec.state_signals(STATE).items():
            counter = self.k
            if name == self.victim and fault == 'counter_repeat':
                counter = self.k - 1
            if name == self.victim and fault == 'counter_jump':
                counter = self.k + 5
            pdu = self.codec.encode(name, values, counter)
            if name == self.victim:
                pdu = self._spoil(pdu, fault)
            if pdu is not None:
                self.monitor.receive(pdu, now)
        self.monitor.tick(now)
        return self.monitor.validity(now), now

    def _spoil(self, pdu, fault):
        if fault == 'crc':
            data = bytearray(pdu.data)
            data[-1] ^= 0x10
            return dataclasses.replace(pdu, data=bytes(data))
        if fault == 'data_id':       # another PDU's protection, sent with our id
            twin = next(n for n in self.codec.names if n != self.victim
                        and self.codec.spec(n).length == self.codec.spec(self.victim).length
                        and self.codec.spec(n).e2e.profile
                        == self.codec.spec(self.victim).e2e.profile)
            values = {s.name: 0 for s in self.codec.payload_signals(twin)}
            return Pdu(pdu.id, self.codec.encode(twin, values, self.k).data, fd=pdu.fd)
        if fault == 'length':
            return dataclasses.replace(pdu, data=pdu.data[:-1])
        if fault == 'timeout':
            return None
        return pdu


def _bits_of(codec, name):
    return [bit for bit, frames in codec.validity_frames.items() if name in frames]


@pytest.mark.parametrize('fault', FAULTS)
@pytest.mark.parametrize('source', DESCRIPTIONS)
def test_each_fault_is_named_and_invalidates_its_signals_in_the_cycle(source, fault):
    codec = Codec.load(config_dir() / source)
    link = Link(codec)
    for _ in range(5):
        validity, _ = link.cycle()
    assert validity == int(Validity.ALL)
    affected = _bits_of(codec, link.victim)
    assert Validity.BETA in affected
    cycles = 4 if fault == 'timeout' else 1     # missing: invalid once 30 ms have passed
    for _ in range(cycles):
        validity, now = link.cycle(fault)
    rx = link.monitor.checker.receivers[link.victim]
    assert rx.reason().startswith(STATUS[fault]), rx.reason()
    assert all(not validity & bit for bit in affected), \
        f'{fault}: {link.victim} signals still valid: 0x{validity:03x}'
    others = int(Validity.ALL) & ~sum(int(b) for b in affected)
    assert validity & others == others, 'only the faulty PDU\'s signals are invalid'
    if fault != 'timeout':
        assert link.monitor.checker.faults[fault] == 1
    recovered = [link.cycle()[0] for _ in range(4)]
    assert recovered[-1] == int(Validity.ALL), f'{fault}: no recovery {recovered}'


def test_validity_bits_name_only_state_signals():
    from drift_vehicle_bridge.codec import STATE_SIGNALS
    assert {s for sigs in VALIDITY_SIGNALS.values() for s in sigs} == set(STATE_SIGNALS)
