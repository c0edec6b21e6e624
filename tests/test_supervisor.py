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
    sup = Supervisor(SupervisorParams())
    assert run(sup, 30.0, beta_deg=-33.0, delta_deg=-20.0) == (None, None)


def test_steering_that_cannot_follow_trips_after_the_set_time_and_latches():
    p = SupervisorParams(steer_error_max=0.1, steer_error_time=0.5)
    sup = Supervisor(p)
    # the EPS holds the wheels at -10 deg while the NMPC asks for -22 deg of counter-steer
    t, reason = run(sup, 2.0, delta_deg=-10.0)
    assert t == pytest.approx(0.52, abs=0.021) and 'steering authority' in reason
    assert sup.tripped
    assert sup.check(state(3.0), ref(3.0), cmd(3.0), 3.0) == reason      # latched
    sup.reset()
    assert not sup.tripped and sup.check(state(4.0), ref(4.0), cmd(4.0), 4.0) is None


def test_a_short_steering_lag_does_not_trip():
    sup = Supervisor(SupervisorParams(steer_error_time=0.5))
    assert run(sup, 0.4, delta_deg=-10.0) == (None, None)
    assert run(sup, 2.0, t0=0.42) == (None, None)        # caught up: the timer restarts


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
