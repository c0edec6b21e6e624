"""Supervisor: trips on lost steering authority or a sideslip excursion, latches, never early."""
import math

import pytest

from drift_control.params import ParamError, config_dir
from drift_control.signals import Command, Direction, Equilibrium, Mode, Reference, VehicleState
from drift_control.supervisor import Supervisor, SupervisorParams, load_supervisor_params

EQ = Equilibrium(V=10.7, beta=math.radians(-30), r=0.71, omega_F=31.2, omega_R=41.8,
                 delta=math.radians(-22), T_R=1434.0)


def ref(t):
    return Reference(stamp=t, target=EQ, direction=Direction.LEFT)


def state(t, beta_deg=-30.0, delta_deg=-22.0):
    return VehicleState(stamp=t, V=10.7, beta=math.radians(beta_deg), r=0.71,
                        delta=math.radians(delta_deg))


def cmd(t, delta_deg=-22.0, mode=Mode.FULL):
    return Command(t, math.radians(delta_deg), 0.0, 1434.0, mode)


def run(sup, seconds, t0=0.0, **kw):
    """Feed 20 ms cycles; return the time of the trip (None if none)."""
    steps = int(round(seconds / 0.02))
    for k in range(steps + 1):
        t = t0 + k * 0.02
        reason = sup.check(state(t, **{k2: v for k2, v in kw.items() if k2 != 'cmd_deg'}),
                           ref(t), cmd(t, kw.get('cmd_deg', -22.0)), t)
        if reason:
            return t, reason
    return None, None


def test_a_held_drift_never_trips():
    """Small corrections around -20 deg that a 10 Hz actuator follows, sideslip within 3 deg."""
    sup = Supervisor(SupervisorParams())
    delta = math.radians(-20.0)
    for k in range(1500):
        t = k * 0.02
        command = delta + math.radians(0.5) * math.sin(2.0 * t) + math.radians(0.2) * (-1) ** k
        st = state(t, beta_deg=-30.0 + 3.0 * math.sin(0.5 * t), delta_deg=math.degrees(delta))
        assert sup.check(st, ref(t), cmd(t, math.degrees(command)), t) is None
        delta += 0.7 * (command - delta)


def test_a_dithering_command_that_the_wheels_follow_late_does_not_trip():
    """The NMPC's steering dithers +-1 deg at ~4 Hz around a held angle; a slow actuator follows
    it 40 ms late, so cycle by cycle the wheels move against the last demand half the time."""
    sup = Supervisor(SupervisorParams())
    held = math.radians(-21.5)
    sent = [held] * 3
    for k in range(2500):
        t = k * 0.02
        command = held + math.radians(1.0) * math.sin(2.0 * math.pi * 4.0 * t)
        st = state(t, delta_deg=math.degrees(sent[-3]))
        assert sup.check(st, ref(t), cmd(t, math.degrees(command)), t) is None
        sent.append(command)


def steer(sup, seconds, share, t0=0.0, rate=1.0, delta0_deg=0.0):
    """The controller asks for a rate-limited step toward -22 deg each cycle (re-planning from
    the measured angle, as the NMPC does); the wheels deliver ``share`` of each step."""
    delta = math.radians(delta0_deg)
    for k in range(int(round(seconds / 0.02)) + 1):
        t = t0 + k * 0.02
        command = max(delta - rate * 0.02, math.radians(-22.0))
        st = state(t, delta_deg=math.degrees(delta))
        reason = sup.check(st, ref(t), cmd(t, math.degrees(command)), t)
        if reason:
            return t, reason
        delta += share * (command - delta)
    return None, None


def test_steering_that_does_not_move_trips_and_latches():
    sup = Supervisor(SupervisorParams(steer_demand_min=0.1, steer_ratio_min=0.3, steer_window=0.5))
    t, reason = steer(sup, 2.0, share=0.0)       # the EPS holds the wheels: nothing moves
    assert t == pytest.approx(0.12, abs=0.03) and 'steering authority' in reason
    assert sup.tripped
    assert sup.check(state(3.0), ref(3.0), cmd(3.0), 3.0) == reason      # latched
    sup.reset()
    assert not sup.tripped and sup.check(state(4.0), ref(4.0), cmd(4.0), 4.0) is None


def test_a_lagging_but_moving_actuator_does_not_trip():
    sup = Supervisor(SupervisorParams())
    assert steer(sup, 3.0, share=0.7) == (None, None)    # a 10 Hz actuator on 20 ms steps
    sup = Supervisor(SupervisorParams())
    assert steer(sup, 3.0, share=0.35) == (None, None)   # sluggish, still above 0.3


def test_steering_pushed_back_by_the_aligning_moment_trips():
    sup = Supervisor(SupervisorParams())
    t, reason = steer(sup, 2.0, share=-0.2, delta0_deg=-5.0)
    assert t is not None and t < 0.2 and 'steering authority' in reason


def test_torque_only_mode_does_not_judge_the_drivers_steering():
    sup = Supervisor(SupervisorParams())
    for k in range(200):
        t = k * 0.02
        assert sup.check(state(t, delta_deg=-5.0), ref(t), cmd(t, -22.0, Mode.TORQUE_ONLY),
                         t) is None


def test_sideslip_beyond_the_reference_or_a_spin_trips():
    sup = Supervisor(SupervisorParams(beta_excess_max=0.35, beta_excess_time=0.3))
    t, reason = run(sup, 2.0, beta_deg=-55.0)
    assert t == pytest.approx(0.32, abs=0.021) and 'beyond its reference' in reason
    sup = Supervisor(SupervisorParams(beta_abs_max=1.05))
    assert sup.check(state(0.0, beta_deg=-65.0), None, None, 0.0).endswith('spinning')


def test_params_file_loads_and_a_bad_key_is_named(tmp_path):
    assert load_supervisor_params(config_dir() / 'supervisor.yaml').enabled
    (tmp_path / 's.yaml').write_text('supervisor: {steer_eror_max: 0.1}\n')
    with pytest.raises(ParamError, match='steer_eror_max'):
        load_supervisor_params(tmp_path / 's.yaml')


def test_nmpc_with_a_supervisor_latches_its_fallback_when_the_steering_does_not_follow():
    """The paper's weak EPS: the wheels stay put while the NMPC asks for counter-steer."""
    import dataclasses

    import numpy as np

    from drift_control.model_plant import ModelPlant
    from drift_control.nmpc import Nmpc, NmpcStatus
    from drift_control.ocp import load_nmpc_params
    from drift_control.params import load_vehicle
    from drift_control.vehicle import NX, X

    vp = load_vehicle()
    nmpc = Nmpc(vp, load_nmpc_params(), supervisor=SupervisorParams())
    plant = ModelPlant(vp)
    x0 = np.zeros(NX)
    x0[[X.V, X.BETA, X.R, X.OMEGA_F, X.OMEGA_R, X.DELTA]] = (10.7, EQ.beta, EQ.r, 31.2, 41.8, 0.0)
    st = plant.reset(x0)
    statuses, torques = [], []
    for k in range(60):
        t = k * 0.02
        st = dataclasses.replace(st, stamp=t, delta=0.0)        # the wheels do not turn
        result = nmpc.step(st, ref(t), t)
        statuses.append(result.status)
        torques.append(result.command.drive_torque)
        st = plant.step(dataclasses.replace(result.command, delta=0.0), 0.02)
    first = statuses.index(NmpcStatus.FALLBACK)
    assert 0.05 <= first * 0.02 <= 0.5, 'trips once enough motion was asked for, not at once'
    assert all(s == NmpcStatus.FALLBACK for s in statuses[first:]), 'latched'
    assert 'steering authority' in nmpc.supervisor.reason
    # the torque off at once, engine braking only while the rear wheels spin over the ground
    assert set(torques[first:]) <= {0.0, nmpc.bounds.T_R_min} and torques[-1] == 0.0
