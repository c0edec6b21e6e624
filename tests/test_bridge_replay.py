"""Vehicle bridge log replay: a recorded drive (ASC, BLF, candump) paced by its own timestamps."""
import can
import pytest

from drift_control.signals import Validity, VehicleState
from drift_vehicle_bridge.codec import Codec
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.replay import LogReplay
from drift_vehicle_bridge.vehicle_side import CarSide, default_dbc

T0 = 1_700_000_000.0


@pytest.fixture(scope='module')
def codec():
    return Codec.load(default_dbc())


def _record(path, codec, seconds=1.0):
    """A drive at 10 ms: speed ramps 5 -> 6 m/s; the DS_YAW frames stop after 0.5 s."""
    class LogLink:   # CarSide's transport: each PDU a frame of the log at the drive's time
        t = 0.0

        def send(self, pdu):
            writer.on_message_received(can.Message(timestamp=T0 + self.t, arbitration_id=pdu.id,
                                                   data=pdu.data, is_extended_id=False))

        def flush(self):
            pass

    with can.Logger(str(path)) as writer:
        bus = LogLink()
        car = CarSide(bus, codec)
        for k in range(int(seconds / 0.01)):
            bus.t = 0.01 * k
            state = VehicleState(bus.t, V=5.0 + bus.t, beta=-0.1, r=0.3)
            car.send_state(state, skip=('DS_YAW',) if bus.t > 0.5 else ())


@pytest.mark.parametrize('suffix', ['.asc', '.blf', '.log'])
def test_replay_paces_frames_and_the_gateway_never_writes_or_arms(tmp_path, codec, suffix):
    path = tmp_path / f'drive{suffix}'
    _record(path, codec)
    replay = LogReplay(path)
    gateway = Gateway(None, codec, load_bridge_params())
    seen = []
    for k in range(120):
        now = 100.0 + 0.01 * k            # the replaying process's own clock
        frames = replay.due(now)
        assert all(m.timestamp <= T0 + 0.01 * k + 1e-6 for m in frames), 'nothing early'
        for msg in frames:
            gateway.receive(msg, now)
        seen.append(gateway.step(now))
        if k == 30:
            assert gateway.request_arm(now) == (False, 'arm refused: replay (no link)')
    assert replay.finished
    assert sum(gateway.stats()['rx'].values()) == 100 * 9 - 49, 'every recorded frame once'
    assert gateway.stats()['faults'] == {} and gateway.stats()['tx'] == {}
    assert seen[30].validity & Validity.R and seen[30].V == pytest.approx(5.3, abs=0.011)
    assert not seen[60].validity & Validity.R, 'DS_YAW stopped at 0.5 s: yaw rate goes stale'
    assert seen[60].validity & Validity.V
    assert seen[-1].validity == 0, 'the log ended: everything stale'
