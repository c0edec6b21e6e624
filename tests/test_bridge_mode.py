"""Vehicle bridge: arming, takeover and release, back to back on python-can virtual buses."""
import itertools
from dataclasses import replace

import can
import pytest

from drift_control.signals import Command, Mode, Validity, VehicleState
from drift_vehicle_bridge.codec import CMD_STATUS, CMD_STEER, CMD_TORQUE, Codec
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.mode import BridgeMode, DropReason
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.transport import CanTransport, pdu_of
from drift_vehicle_bridge.vehicle_side import CarSide, default_dbc

DT = 0.01
_channels = itertools.count()
# A calm left-hand corner: inside the arm envelope.
CALM = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                    wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)
DRIFT = Command(0.0, delta=-0.2, delta_rate=-0.5, drive_torque=2500.0, mode=Mode.FULL)


@pytest.fixture(scope='module')
def codec():
    return Codec.load(default_dbc())


class Rig:
    """Car side, bridge and a sniffer on one virtual channel; one ``cycle`` = 10 ms."""

    def __init__(self, codec, **overrides):
        channel = f'bridge-test-{next(_channels)}'
        self.buses = [can.Bus(channel, interface='virtual') for _ in range(3)]
        car_bus, our_bus, sniff_bus = self.buses
        self.codec = codec
        self.params = load_bridge_params(None, overrides)
        self.gw = Gateway(our_bus, codec, self.params)
        self.car = CarSide(car_bus, codec)
        self.sniffer = sniff_bus
        self.t = 0.0

    def cycle(self, state=CALM, command=DRIFT, skip=()):
        """Car sends state, controller sends command, bridge steps, car polls; bridge output."""
        self.t += DT
        if state is not None:
            self.car.send_state(replace(state, stamp=self.t), skip=skip)
        if command is not None:
            self.gw.set_command(replace(command, stamp=self.t), self.t)
        self.gw.step(self.t)
        applied = self.car.poll_command(self.t)
        written = []
        while (msg := self.sniffer.recv(timeout=0.0)) is not None:
            spec = self.codec.spec_of(pdu_of(msg).id)
            if spec is not None and spec.name in (CMD_STATUS, CMD_STEER, CMD_TORQUE):
                written.append((spec.name, self.codec.decode(pdu_of(msg)).values))
                if spec.name == CMD_STATUS:
                    self.last_status = pdu_of(msg).data
        return self.gw.mode, applied, written

    def arm_and_activate(self, command=DRIFT):
        for _ in range(3):
            self.cycle(command=None)
        ok, why = self.gw.request_arm(self.t)
        assert ok, why
        mode, applied, _ = self.cycle(command=command)
        assert mode.active and applied is not None
        return applied

    def close(self):
        for bus in self.buses:
            bus.shutdown()


@pytest.fixture
def rig(codec):
    r = Rig(codec)
    yield r
    r.close()


def _requests(written):
    """The request PDUs that ask for something (both go out every cycle, flagged or not)."""
    return [name for name, values in written
            if values.get('steer_request') or values.get('torque_request')]


def test_unarmed_bridge_requests_nothing(rig):
    counters = []
    for _ in range(50):
        mode, applied, written = rig.cycle()
        assert mode == BridgeMode.OFF and applied is None
        assert [n for n, _ in written] == [CMD_STEER, CMD_TORQUE, CMD_STATUS]
        assert not _requests(written) and written[-1][1]['bridge_mode'] == BridgeMode.OFF
        counters.append(rig.codec.protection(CMD_STATUS).counter(rig.last_status))
    modulo = rig.codec.protection(CMD_STATUS).counter_modulo
    assert all((b - a) % modulo == 1 for a, b in zip(counters, counters[1:])), 'E2E counter'
    assert rig.car.checker.faults == {} and rig.car.bridge_mode == BridgeMode.OFF


@pytest.mark.parametrize('state, skip, reason', [
    (CALM, ('DS_YAW',), 'STATE_INVALID'),                          # no sideslip / yaw rate
    (CALM, ('DS_POWERTRAIN',), 'STATE_INVALID'),                   # cannot see the brake
    (replace(CALM, validity=int(Validity.ALL & ~Validity.DELTA)), (), 'STATE_INVALID'),
    (replace(CALM, brake_pedal=True), (), 'BRAKE_PEDAL'),
    (replace(CALM, steering_torque=6.0), (), 'DRIVER_TORQUE'),
    (replace(CALM, V=1.0), (), 'ENVELOPE'),                        # too slow to arm
    (replace(CALM, beta=-0.5), (), 'ENVELOPE'),                    # already sliding
    (replace(CALM, r=-1.8), (), 'ENVELOPE'),
])
def test_arming_needs_fresh_valid_state_inside_the_envelope(rig, state, skip, reason):
    for _ in range(5):
        rig.cycle(state=state, skip=skip, command=None)
    ok, why = rig.gw.request_arm(rig.t)
    assert not ok and reason in why
    for _ in range(5):
        mode, applied, written = rig.cycle(state=state, skip=skip)
        assert mode == BridgeMode.OFF and applied is None and not _requests(written)


def test_arming_without_any_state_is_refused(rig):
    ok, why = rig.gw.request_arm(0.0)
    assert not ok and 'STATE_INVALID' in why
    rig.cycle(state=CALM, command=None)
    rig.t += 0.05   # the one state frame set is now stale
    assert not rig.gw.request_arm(rig.t)[0]


def test_arm_then_active_full_then_torque_only_then_command_off(rig):
    applied = rig.arm_and_activate()
    assert applied.mode == Mode.FULL
    mode, applied, written = rig.cycle()
    assert mode == BridgeMode.ACTIVE_FULL and sorted(_requests(written)) == [CMD_STEER, CMD_TORQUE]
    torque_only = replace(DRIFT, mode=Mode.TORQUE_ONLY)
    mode, applied, written = rig.cycle(command=torque_only)
    assert mode == BridgeMode.ACTIVE_TORQUE_ONLY and _requests(written) == [CMD_TORQUE]
    assert applied.mode == Mode.TORQUE_ONLY
    mode, applied, written = rig.cycle(command=replace(DRIFT, mode=Mode.OFF))
    assert mode == BridgeMode.ARMED and applied is None and not _requests(written)
    assert rig.gw.modes.reason == DropReason.COMMAND_OFF


def test_allow_full_false_keeps_steering_with_the_driver(codec):
    rig = Rig(codec, mode={'allow_full': False})
    try:
        rig.arm_and_activate()
        for _ in range(10):
            mode, applied, written = rig.cycle()
            assert mode == BridgeMode.ACTIVE_TORQUE_ONLY and _requests(written) == [CMD_TORQUE]
            assert applied.mode == Mode.TORQUE_ONLY
    finally:
        rig.close()


def _stop_state(rig):
    rig.cycle(state=None)


TAKEOVERS = {
    'driver_torque': dict(state=replace(CALM, steering_torque=-5.5)),
    'brake_pedal': dict(state=replace(CALM, brake_pedal=True)),
    'steering_frame_lost': dict(skip=('DS_STEERING',)),
    'spin_out': dict(state=replace(CALM, beta=-1.0, r=2.0)),
    'state_stops': dict(state=None),
    'heartbeat_lost': dict(command=None),
}


@pytest.mark.parametrize('event', sorted(TAKEOVERS))
def test_takeover_or_loss_drops_to_off_within_one_cycle_and_stays_off(rig, event):
    rig.arm_and_activate()
    for _ in range(20):
        assert rig.cycle()[0] == BridgeMode.ACTIVE_FULL
    t_event = rig.t
    kwargs = TAKEOVERS[event]
    # When the bridge can first know: at once for a value, after the timeout for a silence.
    timeout = {'state_stops': rig.params.monitor.frame_timeout,
               'steering_frame_lost': rig.params.monitor.frame_timeout,
               'heartbeat_lost': rig.params.mode.heartbeat_timeout}.get(event, 0.0)
    cycles = []
    for _ in range(int(round(timeout / DT)) + 4):
        cycles.append(rig.cycle(**kwargs))
    first_off = next(i for i, (mode, _, _) in enumerate(cycles) if mode == BridgeMode.OFF)
    if timeout == 0.0:
        assert first_off == 0, f'{event}: the very cycle that sees it goes OFF'
    t_off = t_event + (first_off + 1) * DT
    assert t_off - t_event <= timeout + DT + 1e-9, f'{event}: OFF after {t_off - t_event:.3f} s'
    for mode, applied, written in cycles[first_off:]:
        assert mode == BridgeMode.OFF, 'latched'
        assert not _requests(written), 'no request frame once OFF'
        assert applied is None, 'the car releases in the same cycle'
        assert written[-1][1]['bridge_mode'] == BridgeMode.OFF
    assert rig.gw.modes.reason.name in {
        'driver_torque': 'DRIVER_TORQUE', 'brake_pedal': 'BRAKE_PEDAL',
        'steering_frame_lost': 'STATE_INVALID', 'spin_out': 'ENVELOPE',
        'state_stops': 'STATE_INVALID', 'heartbeat_lost': 'HEARTBEAT'}[event]
    assert rig.gw.stats()['dropped_at'] == pytest.approx(t_off), 'when, for the diagnostics'
    for _ in range(10):   # the cause is gone: still OFF until someone arms again
        mode, applied, written = rig.cycle()
        assert mode == BridgeMode.OFF and applied is None and not _requests(written)
    assert rig.gw.request_arm(rig.t)[0]
    assert rig.cycle()[0] == BridgeMode.ACTIVE_FULL


def test_driver_torque_at_the_threshold_is_not_a_takeover(rig):
    rig.arm_and_activate()
    thr = rig.params.mode.steering_torque_takeover
    for _ in range(10):
        assert rig.cycle(state=replace(CALM, steering_torque=thr - 0.01))[0].active


def test_torque_only_driver_steering_is_not_a_takeover_but_full_mode_is(rig):
    """Semi-automated mode: the driver steers hard by design; only the brake takes over."""
    torque_only = replace(DRIFT, mode=Mode.TORQUE_ONLY)
    rig.arm_and_activate(command=torque_only)
    steering = replace(CALM, steering_torque=4 * rig.params.mode.steering_torque_takeover)
    for _ in range(10):
        mode, applied, written = rig.cycle(state=steering, command=torque_only)
        assert mode == BridgeMode.ACTIVE_TORQUE_ONLY and _requests(written) == [CMD_TORQUE]
    mode, applied, written = rig.cycle(state=steering, command=DRIFT)   # asks to steer: no
    assert mode == BridgeMode.OFF and applied is None and not _requests(written)
    assert rig.gw.modes.reason == DropReason.DRIVER_TORQUE


def test_disarm_and_arm_timeout(rig):
    rig.arm_and_activate()
    rig.gw.disarm()
    mode, applied, written = rig.cycle()
    assert mode == BridgeMode.OFF and applied is None and not _requests(written)
    assert rig.gw.modes.reason == DropReason.DISARM
    for _ in range(10):   # let the command stream go stale, then arm without a controller
        assert rig.cycle(command=None)[0] == BridgeMode.OFF
    assert rig.gw.request_arm(rig.t)[0]
    n = int(rig.params.mode.arm_timeout / DT)
    modes = [rig.cycle(command=None)[0] for _ in range(n + 2)]
    assert modes[0] == BridgeMode.ARMED and modes[-1] == BridgeMode.OFF
    assert rig.gw.modes.reason == DropReason.ARM_TIMEOUT


def test_requests_are_clamped_and_rate_limited_from_the_measured_values(rig):
    lim = rig.params.limits
    wild = Command(0.0, delta=-3.0, delta_rate=-50.0, drive_torque=50000.0, mode=Mode.FULL)
    wild = replace(wild, delta=-0.99, drive_torque=7999.0)   # inside the DBC, outside the limits
    prev_delta, prev_torque = CALM.delta, CALM.drive_torque
    rig.arm_and_activate(command=wild)
    prev_delta = CALM.delta - lim.delta_rate_max * DT
    prev_torque = CALM.drive_torque + lim.torque_rate_max * DT
    for _ in range(200):
        mode, applied, written = rig.cycle(command=wild)
        steer = dict(written)[CMD_STEER]
        torque = dict(written)[CMD_TORQUE]
        assert abs(steer['delta_req'] - prev_delta) <= lim.delta_rate_max * DT + 1e-4
        assert abs(torque['torque_req'] - prev_torque) <= lim.torque_rate_max * DT + 1.0
        assert abs(steer['delta_req']) <= lim.delta_max + 1e-4
        assert abs(steer['delta_rate_req']) <= lim.delta_rate_max + 1e-3
        assert lim.torque_min <= torque['torque_req'] <= lim.torque_max
        prev_delta, prev_torque = steer['delta_req'], torque['torque_req']
    assert prev_delta == pytest.approx(-lim.delta_max, abs=1e-4)
    assert prev_torque == pytest.approx(lim.torque_max, abs=1.0)


def test_non_finite_commands_are_dropped_and_count_as_lost_heartbeat(rig):
    rig.arm_and_activate()
    bad = replace(DRIFT, delta=float('nan'))
    modes = [rig.cycle(command=bad)[0] for _ in range(10)]
    assert modes[-1] == BridgeMode.OFF and rig.gw.modes.reason == DropReason.HEARTBEAT
    assert rig.gw.errors['command_rejected'] == 10


def test_only_allow_listed_frames_are_ever_written(codec):
    rig = Rig(codec, tx_allow=['DS_CMD_TORQUE', 'DS_CMD_STATUS'])
    try:
        for _ in range(3):   # the state PDUs E2E state machines: NODATA, INIT, INIT, VALID
            rig.cycle(command=None)
        assert rig.gw.request_arm(rig.t)[0]
        for _ in range(10):
            mode, applied, written = rig.cycle()
            assert mode == BridgeMode.ACTIVE_FULL and CMD_STEER not in dict(written)
            assert applied is None, 'the car applies no FULL request without its steering frame'
        assert rig.gw.errors['tx_blocked'] == 10
        assert CMD_STEER not in rig.gw.sent
    finally:
        rig.close()


def test_car_side_rejects_corrupted_command_frames(rig):
    rig.arm_and_activate()
    # A forged steering frame with a bad CRC, injected on the bus beside the bridge.
    forged = rig.codec.encode(CMD_STEER, {'steer_request': 1, 'delta_req': 0.9,
                                          'delta_rate_req': 0.0}, counter=3)
    data = bytearray(forged.data)
    data[0] ^= 0x55
    CanTransport(rig.sniffer).send(replace(forged, data=bytes(data)))
    mode, applied, _ = rig.cycle()
    assert applied is None, 'an E2E error invalidates the steering request in that cycle'
    assert rig.car.checker.faults['crc'] == 1
    assert rig.car.checker.receivers[CMD_STEER].reason() == 'OK, INVALID'
    recovered = [rig.cycle()[1] for _ in range(3)]
    assert recovered[-1] is not None and recovered[-1].delta != pytest.approx(0.9), \
        'the E2E state machine is VALID again once the error has left its window'
    assert mode == BridgeMode.ACTIVE_FULL


def test_the_backlog_before_the_first_cycle_is_dropped_and_a_failing_link_does_not_hang_it(codec):
    from drift_vehicle_bridge.pdu import Pdu

    class Queue:
        def __init__(self, items):
            self.items = list(items)

        def recv(self, timeout=0.0):
            item = self.items.pop(0) if self.items else None
            if isinstance(item, Exception):
                raise item
            return item

    params = load_bridge_params()
    backlog = [Pdu(0x110, bytes(8))] * 5 + [OSError('bad datagram')] + [Pdu(0x111, bytes(8))]
    gw = Gateway(Queue(backlog), codec, params)
    assert gw.discard_backlog() == 7 and gw.stats()['discarded_at_start'] == 7

    class Broken:
        def recv(self, timeout=0.0):
            raise OSError('socket closed')

    assert Gateway(Broken(), codec, params).discard_backlog() > 0     # bounded, returns


def test_the_car_drops_the_requests_it_queued_before_it_started(codec):
    # a simulated car that waited (for the recorder) before its first step: the bridge's
    # requests meanwhile are history, not counter jumps
    with can.Bus('backlog_car', interface='virtual') as car_bus, \
            can.Bus('backlog_car', interface='virtual') as our_bus:
        car = CarSide(car_bus, codec)
        gw = Gateway(our_bus, codec, load_bridge_params())
        for k in range(30):
            gw.step(0.01 * k)             # requests every cycle, no one reading
        assert car.discard_backlog() == 90
        assert car.discard_backlog() == 0 and car.checker.rejected == 0
