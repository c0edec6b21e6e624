"""Faults and bad input, in process: the controller never acts on garbage and is never wedged.

Each case asserts what the stack must do: no exception, a finite command within the limits,
the safe state in the same 20 ms cycle where one applies, and the reason named.
"""
import dataclasses
import math

import numpy as np
import pytest

from drift_control.equilibrium import solve_equilibrium
from drift_control.nmpc import LockstepTrigger, Nmpc, NmpcStatus
from drift_control.ocp import load_nmpc_params
from drift_control.pacing import PeriodGate
from drift_control.params import load_vehicle
from drift_control.plausibility import InputChecker, InputLimits
from drift_control.signals import Command, Direction, Mode, Reference, VehicleState
from drift_control.supervisor import SupervisorParams
from drift_control.vehicle import front_axle_course
from drift_sim.lockstep import LockstepGate

TS = 0.02


def _state(eq, now, k=0, **kw):
    """The equilibrium as measured, with a little movement so it never looks frozen."""
    wiggle = 1e-4 * math.sin(k)
    base = VehicleState(stamp=now, V=eq.V + wiggle, beta=eq.beta, r=eq.r,
                        wheel_speeds=(eq.omega_F, eq.omega_F, eq.omega_R, eq.omega_R),
                        delta=eq.delta, drive_torque=eq.T_R)
    return dataclasses.replace(base, **kw)


def _engaged(nmpc, eq, cycles=10):
    """An NMPC that has been solving on a steady drift; returns the time of the next cycle."""
    nmpc.reset()
    for k in range(cycles):
        res = nmpc.step(_state(eq, k * TS, k), Reference(k * TS, eq, Direction.LEFT), k * TS)
        assert res.status == NmpcStatus.OK, res.message
    return cycles * TS


def _assert_safe(res, vp, why):
    c = res.command
    assert all(math.isfinite(v) for v in (c.delta, c.delta_rate, c.drive_torque))
    assert abs(c.delta) <= vp.limits.delta_max + 1e-9
    assert vp.limits.T_R_min - 1e-6 <= c.drive_torque <= vp.limits.T_R_max + 1e-6
    assert res.status == NmpcStatus.FALLBACK and c.mode == Mode.FALLBACK, res.message
    assert why in res.message, res.message


@pytest.mark.parametrize('fault, why', [
    (dict(wheel_speeds=(-100.0, -100.0, -100.0, -100.0)), 'wheel speed FL'),
    (dict(V=1000.0), 'speed 1000.0 m/s'),
    (dict(r=50.0), 'yaw rate 50.00'),
    (dict(delta=1.2), 'steering angle 1.200'),
    (dict(wheel_speeds=(30.0, 30.0, 400.0, 400.0)), 'wheel speed RL'),
])
def test_an_impossible_but_finite_state_gives_the_fallback_in_the_same_cycle(nmpc, vp, eq30,
                                                                             fault, why):
    now = _engaged(nmpc, eq30)
    last = nmpc._last
    res = nmpc.step(_state(eq30, now, 99, **fault), Reference(now, eq30, Direction.LEFT), now)
    _assert_safe(res, vp, f'implausible vehicle state: {why}')
    # the fallback ramps the torque down from the last command, it does not jump to a limit
    assert abs(res.command.drive_torque - last.drive_torque) <= 3000.0 * TS + 1e-6
    # and the first plausible state after it is solved again
    now += TS
    res = nmpc.step(_state(eq30, now, 100), Reference(now, eq30, Direction.LEFT), now)
    assert res.status == NmpcStatus.OK, res.message


def test_a_fallback_in_a_torque_burst_ramps_from_what_the_wheels_have(nmpc, vp, eq30):
    """A trip while the last request is a 6000 Nm burst the lagging powertrain has delivered
    1000 Nm of: the ramp to zero starts at 1000 Nm, never delivering the rest."""
    now = _engaged(nmpc, eq30)
    nmpc._last = dataclasses.replace(nmpc._last, drive_torque=6000.0)
    nmpc._T_act = 1000.0
    res = nmpc.step(_state(eq30, now, 99, V=1000.0), Reference(now, eq30, Direction.LEFT), now)
    _assert_safe(res, vp, 'implausible vehicle state')
    assert 1000.0 - 3000.0 * TS - 1e-6 <= res.command.drive_torque < 1000.0


def test_a_frozen_sensor_is_noticed(nmpc, vp, eq30):
    now = _engaged(nmpc, eq30)
    frozen = _state(eq30, now, 7)
    limit = load_nmpc_params().inputs.freeze_cycles
    statuses = []
    for k in range(limit + 2):
        t = now + k * TS
        res = nmpc.step(dataclasses.replace(frozen, stamp=t), Reference(t, eq30, Direction.LEFT), t)
        statuses.append(res.status)
    assert NmpcStatus.FALLBACK not in statuses[:limit - 1]
    assert statuses[limit - 1] == NmpcStatus.FALLBACK
    _assert_safe(res, vp, 'measurements frozen')


def test_the_frozen_detector_ignores_a_sample_seen_again(vp):
    checker = InputChecker(vp, InputLimits(freeze_cycles=3))
    s = VehicleState(stamp=1.0, V=10.0, beta=-0.5, r=0.6, wheel_speeds=(30.0,) * 4)
    assert all(checker.check(s) is None for _ in range(10)), 'same stamp: one sample'
    assert checker.check(dataclasses.replace(s, stamp=1.02)) is None
    assert 'frozen' in checker.check(dataclasses.replace(s, stamp=1.04))
    assert checker.check(dataclasses.replace(s, stamp=1.06, V=10.01)) is None, 'moves again'


def test_a_reference_with_a_short_horizon_or_nan_is_refused(nmpc, eq30):
    now = _engaged(nmpc, eq30)
    short = Reference(now, eq30, Direction.LEFT, horizon=(eq30,) * 3)
    res = nmpc.step(_state(eq30, now, 50), short, now)
    assert res.status != NmpcStatus.OK and 'horizon of 3 stages' in res.message
    nan = Reference(now + TS, dataclasses.replace(eq30, V=math.nan), Direction.LEFT)
    res = nmpc.step(_state(eq30, now + TS, 51), nan, now + TS)
    assert res.status != NmpcStatus.OK and 'reference not finite' in res.message
    assert all(math.isfinite(v) for v in (res.command.delta, res.command.drive_torque))


def test_one_future_stamp_does_not_wedge_the_period_gate():
    gate = PeriodGate(TS)
    fired = []
    for k in range(100):
        t = k * 0.01
        stamp = 1e6 if k == 30 else t            # one state stamped 1e6 s
        if gate.due(stamp, clock=t):
            gate.fired(stamp)
            fired.append(k)
    assert 30 not in fired and gate.refused_future == 1
    assert fired == list(range(0, 30, 2)) + list(range(31, 100, 2)), 'the next state serves'


def test_a_backward_clock_step_restarts_the_period_gate():
    gate = PeriodGate(TS)
    fired = []
    for k in range(200):
        t = k * 0.01 - (5.0 if k >= 100 else 0.0)    # the clock steps back 5 s at k = 100
        if gate.due(t, clock=t):
            gate.fired(t)
            fired.append(k)
    assert fired == list(range(0, 200, 2)), 'no 5 s gap after the step'
    assert gate.restarts == 1


def test_the_nmpc_trigger_survives_a_future_state():
    trig = LockstepTrigger(TS, reference_wait=0.005)
    solves = 0
    for k in range(50):
        t = k * 0.01
        stamp = 1e6 if k == 10 else t
        if trig.on_state(stamp, wall=t, clock=t) or trig.on_reference(t):
            trig.fired()
            solves += 1
    assert solves == 25


def test_the_lockstep_gate_does_not_take_a_future_command_for_every_step():
    gate = LockstepGate(dt=0.01, command_period=TS, timeout=1.0, startup_timeout=10.0)
    gate.offer(Command(1e6, 0.0, 0.0, 0.0, Mode.FULL))
    assert not gate.ready(0.0, wall=0.0), 'a command from the future is no command for t = 0'
    gate.offer(Command(0.0, 0.0, 0.0, 0.0, Mode.FULL))
    assert gate.ready(0.0, wall=0.1)


def test_malformed_messages_are_rejected_not_raised():
    msgs = pytest.importorskip('drift_msgs.msg')
    from drift_control.nodes import convert
    bad = msgs.DriftReference(direction=7)
    assert convert.decode(convert.reference_from_msg, bad) is None
    bad = msgs.DriftCommand(mode=9)
    assert convert.decode(convert.command_from_msg, bad) is None
    good = convert.reference_to_msg(Reference(1.0, solve_equilibrium(
        math.radians(-30.0), 15.0, load_vehicle()).eq, Direction.LEFT))
    assert convert.decode(convert.reference_from_msg, good).direction == Direction.LEFT


def test_input_limits_are_validated():
    from drift_control.params import ParamError
    with pytest.raises(ParamError, match='nmpc.inputs.freeze_cycles'):
        InputLimits(freeze_cycles=1)
    assert np.isclose(load_nmpc_params().inputs.V_max, InputLimits().V_max)


def test_the_bridge_drops_to_off_on_a_frozen_state(vp):
    """Alive counters advance, the values do not: OFF once the window (200 ms) has passed."""
    import can
    from drift_vehicle_bridge.gateway import Gateway
    from drift_vehicle_bridge.params import load_bridge_params
    from drift_vehicle_bridge.transport import CanTransport
    from drift_vehicle_bridge.vehicle_side import CarSide
    params = load_bridge_params(None, {'auto_arm': True})
    limits = load_nmpc_params().inputs.for_period(params.cycle_time, TS)
    assert limits.freeze_cycles == 20
    calm = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                        wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)
    with can.Bus('faults_frozen', interface='virtual') as car_bus, \
            can.Bus('faults_frozen', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gw = Gateway(our_bus, car.codec, params, InputChecker(vp, limits))
        modes = []
        for k in range(100):
            now = 0.01 * k
            V = calm.V if k >= 40 else _noisy(calm.V, k)     # frozen from cycle 40 on
            car.send_state(dataclasses.replace(calm, stamp=now, V=V))
            if k >= 10:
                gw.set_command(Command(now, -0.1, 0.0, 800.0, Mode.FULL), now)
            gw.step(now)
            car.poll_command(now)
            modes.append(gw.mode.name)
    first_off = modes.index('OFF', 20)
    assert modes[20:58] == ['ACTIVE_FULL'] * 38 and 58 <= first_off <= 60, modes[50:62]
    assert gw.modes.reason.name == 'STATE_INVALID' and 'frozen' in gw.modes.implausible


def test_a_parked_car_is_not_a_frozen_sensor(vp):
    checker = InputChecker(vp, InputLimits(freeze_cycles=3))
    parked = VehicleState(stamp=0.0, V=0.0, beta=0.0, r=0.0, wheel_speeds=(0.0,) * 4)
    assert all(checker.check(dataclasses.replace(parked, stamp=0.02 * k)) is None
               for k in range(50))


def test_the_bridge_drops_to_off_on_an_impossible_wheel_speed(vp):
    """The car side gets the same physical bounds: ACTIVE -> OFF in the cycle it arrives."""
    import can
    from drift_vehicle_bridge.gateway import Gateway
    from drift_vehicle_bridge.params import load_bridge_params
    from drift_vehicle_bridge.transport import CanTransport
    from drift_vehicle_bridge.vehicle_side import CarSide
    params = load_bridge_params(None, {'auto_arm': True})
    calm = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                        wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)
    with can.Bus('faults_t', interface='virtual') as car_bus, \
            can.Bus('faults_t', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gw = Gateway(our_bus, car.codec, params, InputChecker(vp))
        modes = []
        for k in range(60):
            now = 0.01 * k
            bad = k >= 40
            car.send_state(dataclasses.replace(calm, stamp=now, V=_noisy(calm.V, k), wheel_speeds=(
                (24.0, 24.0, -90.0, -90.0) if bad else calm.wheel_speeds)))
            if k >= 10:
                gw.set_command(Command(now, -0.1, 0.0, 800.0, Mode.FULL), now)
            gw.step(now)
            car.poll_command(now)
            modes.append(gw.mode.name)
    assert modes[39] == 'ACTIVE_FULL' and modes[40] == 'OFF', modes[35:45]
    assert gw.modes.reason.name == 'STATE_INVALID' and 'wheel speed RL' in gw.modes.implausible


def test_a_state_offered_again_does_not_restart_the_nmpc_s_wait_for_its_reference():
    """The lock-step sim offers state 0 again every 0.2 s until the first command; a late NMPC
    whose reference never comes must still answer after its wait, not wait anew each time."""
    trig = LockstepTrigger(TS, reference_wait=1.0)
    assert not trig.on_state(0.0, wall=0.0, clock=0.0)
    for wall in (0.2, 0.4, 0.6, 0.8, 1.0):
        trig.on_state(0.0, wall=wall, clock=0.0)
    assert trig.poll(1.05), 'answered 1 s after the state first came'


@pytest.mark.parametrize('script, argv', [
    ('run_stack', ['--duration', '-5']), ('run_stack', ['--sim-duration', 'inf']),
    ('simulate', ['--scenario', 'steady_dry', '--seed', '-1'])])
def test_negative_durations_and_seeds_are_one_line_and_exit_2(capsys, script, argv):
    from conftest import load_script
    with pytest.raises(SystemExit) as ended:
        load_script(script).main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert ended.value.code == 2 and 'error: argument' in err[-1]


def test_a_negative_surface_friction_is_refused_not_read_as_the_named_surface():
    from drift_control.params import ParamError
    from drift_control.scenario import load_scenario_spec
    with pytest.raises(ParamError, match='surface.mu: must be in'):
        load_scenario_spec('steady_dry', ['surface.mu=-1'])
    assert load_scenario_spec('steady_dry', ['surface.mu=0.9']).surface.mu == 0.9


@pytest.mark.parametrize('stamp_offset, why', [(-0.06, 'vehicle state stale (0.060 s old)'),
                                              (0.06, 'vehicle state from the future (0.060 s')])
def test_a_stale_or_future_state_gives_the_fallback_in_the_same_cycle(nmpc, vp, eq30,
                                                                     stamp_offset, why):
    """A state more than 50 ms off the node's clock: no plan is served without a measurement."""
    now = _engaged(nmpc, eq30)
    res = nmpc.step(_state(eq30, now + stamp_offset, 99), Reference(now, eq30, Direction.LEFT),
                    now)
    _assert_safe(res, vp, why)
    now += TS
    res = nmpc.step(_state(eq30, now, 100), Reference(now, eq30, Direction.LEFT), now)
    assert res.status == NmpcStatus.OK, 'a fresh state is solved again (cold start)'


def test_a_failing_solver_serves_the_plan_then_falls_back_within_limits(nmpc, vp, eq30,
                                                                        monkeypatch):
    now = _engaged(nmpc, eq30)
    limit = load_nmpc_params().max_failures
    monkeypatch.setattr(nmpc._solver, 'solve',
                        lambda *a, **k: (_ for _ in ()).throw(RuntimeError('injected')))
    statuses = []
    for k in range(limit + 2):
        t = now + k * TS
        res = nmpc.step(_state(eq30, t, 200 + k), Reference(t, eq30, Direction.LEFT), t)
        statuses.append(res.status)
        c = res.command
        assert all(math.isfinite(v) for v in (c.delta, c.delta_rate, c.drive_torque))
        assert abs(c.delta) <= vp.limits.delta_max + 1e-9
    assert statuses == [NmpcStatus.SHIFTED] * limit + [NmpcStatus.FALLBACK] * 2
    _assert_safe(res, vp, 'solver raised RuntimeError: injected')
    monkeypatch.undo()
    t = now + (limit + 2) * TS
    res = nmpc.step(_state(eq30, t, 300), Reference(t, eq30, Direction.LEFT), t)
    assert res.status == NmpcStatus.OK, 'the repaired solver is used again'


@pytest.mark.parametrize('field, value, why', [
    ('delta', 0.9, 'steering 0.900 rad beyond'),
    ('T_R', 1e5, 'torque 100000 Nm outside'),
    ('V', -3.0, 'speed -3.00 m/s')])
def test_an_infeasible_reference_is_named_and_never_solved_for(nmpc, vp, eq30, field, value,
                                                               why):
    now = _engaged(nmpc, eq30)
    bad = dataclasses.replace(eq30, **{field: value})
    statuses = []
    for k in range(load_nmpc_params().max_failures + 1):
        t = now + k * TS
        res = nmpc.step(_state(eq30, t, 400 + k), Reference(t, bad, Direction.LEFT), t)
        statuses.append(res.status)
        assert f'reference infeasible: target {why}' in res.message, res.message
    assert statuses[-1] == NmpcStatus.FALLBACK and NmpcStatus.OK not in statuses
    _assert_safe(res, vp, 'reference infeasible')


def _noisy(value, k):
    """A measured value as a sensor gives it: moving in its last digits (0.01 per DBC bit)."""
    return value + 0.02 * math.sin(1.7 * k)


class _LossyLink:
    """A transport that loses a share of the PDUs it sends (seeded)."""

    def __init__(self, link, loss, seed):
        self._link, self.loss, self.lost = link, loss, 0
        self._rng = np.random.default_rng(seed)

    def send(self, pdu):
        if self._rng.random() < self.loss:
            self.lost += 1
            return
        self._link.send(pdu)

    def __getattr__(self, name):
        return getattr(self._link, name)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_twenty_percent_frame_loss_on_the_bus(vp, seed):
    """20 % of the frames lost both ways: a state that goes stale drops the bridge to OFF in the
    same 10 ms cycle (STATE_INVALID), nothing the car applies is ever out of its limits, and
    after the drop the bridge requests nothing."""
    import can
    from drift_vehicle_bridge.gateway import Gateway
    from drift_vehicle_bridge.mode import REQUIRED
    from drift_vehicle_bridge.params import load_bridge_params
    from drift_vehicle_bridge.transport import CanTransport
    from drift_vehicle_bridge.vehicle_side import CarSide
    params = load_bridge_params(None, {'auto_arm': True})
    calm = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                        wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)
    channel = f'faults_loss_{seed}'
    with can.Bus(channel, interface='virtual') as car_bus, \
            can.Bus(channel, interface='virtual') as our_bus:
        car = CarSide(_LossyLink(CanTransport(car_bus), 0.2, seed))
        gw = Gateway(_LossyLink(CanTransport(our_bus), 0.2, seed + 100), car.codec, params,
                     InputChecker(vp))
        active, dropped_at, applied_after_drop = 0, None, []
        for k in range(400):
            now = 0.01 * k
            car.send_state(dataclasses.replace(calm, stamp=now, V=_noisy(calm.V, k)))
            if k % 2 == 0:
                gw.set_command(Command(now, -0.1, -0.2, 800.0, Mode.FULL), now)
            state = gw.step(now)
            applied = car.poll_command(now)
            if applied is not None:
                assert all(math.isfinite(v) for v in (applied.delta, applied.drive_torque))
                assert abs(applied.delta) <= vp.limits.delta_max + 1e-9
                assert vp.limits.T_R_min - 1.0 <= applied.drive_torque <= vp.limits.T_R_max + 1.0
            if state is None or not state.has(REQUIRED):
                assert not gw.mode.active, f'cycle {k}: stale state but still {gw.mode.name}'
            if gw.mode.active:
                active += 1
            elif gw.been_active and dropped_at is None:
                dropped_at = k
                assert gw.modes.reason.name in ('STATE_INVALID', 'HEARTBEAT'), gw.modes.reason
            if dropped_at is not None and k > dropped_at + 5:
                applied_after_drop.append(applied)
    assert gw.been_active, 'the bridge never became active through the loss'
    assert car.transport.lost > 0.15 * car.frames_sent
    assert all(a is None for a in applied_after_drop), 'the car applied requests after the drop'


def test_an_unwritable_bag_or_an_empty_metadata_file_is_one_line(capsys, tmp_path):
    from conftest import load_script
    assert load_script('run_stack').main(['--bag', '/proc/no_such/bag', '--duration', '1']) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('run_stack: --bag /proc/no_such/bag: cannot create it'), err
    assert len(err.splitlines()) == 1
    from drift_tools.bag import bag_info
    (tmp_path / 'metadata.yaml').write_text('')
    with pytest.raises(ValueError, match='not a rosbag2 metadata file'):
        bag_info(tmp_path)


def test_the_period_gate_takes_every_second_jittered_state():
    # real-time states at 100 Hz, stamps +-2 ms: a state a little early still opens its
    # period (with a 1 ms tolerance, 4 % of the solves waited for the next state: 30 ms gaps)
    rng = np.random.default_rng(3)
    stamps = np.arange(2000) * 0.01 + rng.uniform(-0.002, 0.002, 2000)
    gate, fired = PeriodGate(TS), []
    for stamp in stamps:
        if gate.due(stamp, clock=stamp):
            gate.fired(stamp)
            fired.append(stamp)
    gaps = np.diff(fired)
    assert len(fired) == 1000 and gaps.max() < 0.027 and gaps.min() > 0.013


def test_the_nmpc_trigger_takes_the_phase_of_the_reference_node():
    # the reference node serves the odd states; the NMPC starts on an even one (no reference
    # yet), waits out one reference_wait on the next even one, then solves on the odd states
    trig = LockstepTrigger(TS, reference_wait=0.005)
    solves, waited = [], 0
    for k in range(40):
        t = k * 0.01
        ready = trig.on_state(t, wall=t)
        if k % 2:
            ready = trig.on_reference(t) or ready
        if not ready and trig.poll(t + 0.006):
            ready, waited = True, waited + 1
        if ready:
            solves.append(round(trig.fired() / 0.01))
    assert waited == 2 and solves[:2] == [0, 2]
    assert solves[2:] == list(range(3, 40, 2)), 'every odd state, with its reference'


def test_a_trip_gives_the_drift_up(vp, eq30):
    """After the supervisor's trip the torque is off at once, engine braking while the rear
    wheels spin over the ground, and the steering heads for the front axle's course (here past
    the counter-steer of the drift's equilibrium, which the last command held)."""
    nmpc = Nmpc(vp, load_nmpc_params(), supervisor=SupervisorParams())
    now = _engaged(nmpc, eq30)
    last, ref = nmpc._last, Reference(now, eq30, Direction.LEFT)
    spinning = _state(eq30, now, 99, beta=-1.2, r=1.0)   # beyond 60 deg of sideslip
    res = nmpc.step(spinning, ref, now)
    _assert_safe(res, vp, 'supervisor')
    ground = spinning.V * math.cos(spinning.beta)
    assert spinning.omega_R * vp.R_R > 1.5 * ground
    assert res.command.drive_torque == nmpc.bounds.T_R_min, 'engine braking'
    step = nmpc.params.fallback_delta_rate * TS
    assert front_axle_course(spinning.V, spinning.beta, spinning.r, vp.a) < last.delta - step
    assert res.command.delta == pytest.approx(last.delta - step), 'toward the course'
    now += TS
    rolling = (eq30.omega_F,) * 2 + (ground / vp.R_R,) * 2
    res = nmpc.step(dataclasses.replace(spinning, stamp=now, wheel_speeds=rolling), ref, now)
    _assert_safe(res, vp, 'supervisor')
    assert res.command.drive_torque == 0.0, 'no torque once the rear wheels roll'
