"""nodes/convert.py: every message <-> signal conversion is a lossless round trip."""
import math

import pytest

pytestmark = pytest.mark.ros

convert = pytest.importorskip('drift_control.nodes.convert')

from drift_control import path as P  # noqa: E402
from drift_control.signals import (Command, Direction, Equilibrium, Mode, Reference,  # noqa: E402
                                   Validity, VehicleState)

EQ = Equilibrium(V=10.2, beta=-0.52, r=0.68, omega_F=31.9, omega_R=44.1, delta=-0.11, T_R=1234.5)


def test_state_round_trip():
    st = VehicleState(stamp=12.345678901, V=10.0, beta=-0.5, r=0.7, vx=8.8, vy=-4.8, ax=0.1,
                      ay=6.9, wheel_speeds=(31.0, 32.0, 40.0, 41.0), delta=-0.1,
                      steering_torque=1.5, drive_torque=900.0, brake_pedal=True, x=3.0, y=-4.0,
                      yaw=2.9, validity=int(Validity.ALL & ~Validity.AX_AY))
    back = convert.state_from_msg(convert.state_to_msg(st))
    assert back == VehicleState(**{**vars(st), 'stamp': pytest.approx(st.stamp, abs=1e-9)})


def test_reference_round_trip_keeps_horizon_and_signs():
    ref = Reference(stamp=3.5, target=EQ, direction=Direction.RIGHT,
                    horizon=(EQ, EQ.mirrored()), curvature=-1 / 15, curvature_cmd=-0.07,
                    s=1234.5, e_y=-0.3, heading_error=0.4, clamped=True,
                    horizon_curvature=(-1 / 15, 0.0))
    m = convert.reference_to_msg(ref, None)
    assert m.header.stamp.sec == 3 and m.header.stamp.nanosec == 500_000_000
    assert m.direction == m.DIRECTION_RIGHT
    assert convert.reference_from_msg(m) == ref


def test_reference_stamp_argument_overrides():
    ref = Reference(stamp=3.5, target=EQ)
    assert convert.reference_from_msg(convert.reference_to_msg(ref, 7.25)).stamp == 7.25


def test_command_round_trip():
    for mode in Mode:
        cmd = Command(stamp=1.0, delta=-0.2, delta_rate=0.5, drive_torque=1500.0, mode=mode)
        m = convert.command_to_msg(cmd, None)
        assert m.mode == int(mode)
        assert convert.command_from_msg(m) == cmd


def test_path_message_follows_the_path():
    path = P.circle(15.0)
    m = convert.path_to_msg(path, 0.0, step=1.0)
    assert len(m.poses) == pytest.approx(path.length, abs=2)
    for pose in m.poses:
        p = pose.pose
        assert math.hypot(p.position.x, p.position.y - 15.0) == pytest.approx(15.0)
        yaw = 2 * math.atan2(p.orientation.z, p.orientation.w)
        assert math.cos(yaw) * p.position.x + math.sin(yaw) * (p.position.y - 15) == (
            pytest.approx(0.0, abs=1e-9)), 'tangent to the circle'
