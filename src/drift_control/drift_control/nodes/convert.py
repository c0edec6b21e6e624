"""drift_msgs <-> drift_control.signals: the one place where messages, stamps and frame ids live.

Stamps: a core ``stamp`` is float seconds of the publisher's clock; a message header carries the
same time as ``builtin_interfaces/Time``. Every ``*_to_msg(obj, stamp)`` takes ``stamp`` as an
``rclpy.time.Time``, a ``builtin_interfaces.msg.Time``, float seconds, or None (use ``obj.stamp``).
"""
from __future__ import annotations

import math

from builtin_interfaces.msg import Time
from drift_msgs import msg
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg

from drift_control.estimator import FIELDS, SensorSample
from drift_control.signals import (Command, Direction, Equilibrium, Mode, Reference,
                                   VehicleState)

MAP_FRAME = 'map'
BODY_FRAME = 'base_link'


def time_to_msg(stamp) -> Time:
    """``rclpy.time.Time``, ``builtin_interfaces/Time`` or float seconds -> ``Time``."""
    if isinstance(stamp, Time):
        return stamp
    if hasattr(stamp, 'to_msg'):
        return stamp.to_msg()
    ns = int(round(float(stamp) * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def time_from_msg(stamp: Time) -> float:
    """``builtin_interfaces/Time`` -> float seconds."""
    return stamp.sec + 1e-9 * stamp.nanosec


def _header(header, stamp, fallback: float, frame_id: str):
    header.stamp = time_to_msg(fallback if stamp is None else stamp)
    header.frame_id = frame_id


def state_from_msg(m: msg.VehicleState) -> VehicleState:
    """VehicleState message -> ``signals.VehicleState``."""
    return VehicleState(
        stamp=time_from_msg(m.header.stamp), V=m.v, beta=m.beta, r=m.r, vx=m.vx, vy=m.vy,
        ax=m.ax, ay=m.ay, wheel_speeds=tuple(float(w) for w in m.wheel_speeds), delta=m.delta,
        steering_torque=m.steering_torque, drive_torque=m.drive_torque,
        brake_pedal=bool(m.brake_pedal), x=m.x, y=m.y, yaw=m.yaw, validity=int(m.validity))


def state_to_msg(state: VehicleState, stamp=None, frame_id: str = BODY_FRAME) -> msg.VehicleState:
    """``signals.VehicleState`` -> VehicleState message."""
    m = msg.VehicleState(
        v=state.V, beta=state.beta, r=state.r, vx=state.vx, vy=state.vy, ax=state.ax,
        ay=state.ay, wheel_speeds=[float(w) for w in state.wheel_speeds], delta=state.delta,
        steering_torque=state.steering_torque, drive_torque=state.drive_torque,
        brake_pedal=bool(state.brake_pedal), x=state.x, y=state.y, yaw=state.yaw,
        validity=int(state.validity))
    _header(m.header, stamp, state.stamp, frame_id)
    return m


def equilibrium_to_msg(eq: Equilibrium) -> msg.Equilibrium:
    """``signals.Equilibrium`` -> Equilibrium message."""
    return msg.Equilibrium(v=eq.V, beta=eq.beta, r=eq.r, omega_f=eq.omega_F, omega_r=eq.omega_R,
                           delta=eq.delta, drive_torque=eq.T_R)


def equilibrium_from_msg(m: msg.Equilibrium) -> Equilibrium:
    """Equilibrium message -> ``signals.Equilibrium``."""
    return Equilibrium(V=m.v, beta=m.beta, r=m.r, omega_F=m.omega_f, omega_R=m.omega_r,
                       delta=m.delta, T_R=m.drive_torque)


def reference_to_msg(ref: Reference, stamp=None, frame_id: str = MAP_FRAME) -> msg.DriftReference:
    """``signals.Reference`` -> DriftReference message."""
    m = msg.DriftReference(
        direction=int(ref.direction), target=equilibrium_to_msg(ref.target),
        horizon=[equilibrium_to_msg(e) for e in ref.horizon], curvature=ref.curvature,
        curvature_cmd=ref.curvature_cmd, s=ref.s, e_y=ref.e_y, heading_error=ref.heading_error,
        clamped=bool(ref.clamped), horizon_curvature=list(ref.horizon_curvature))
    _header(m.header, stamp, ref.stamp, frame_id)
    return m


def reference_from_msg(m: msg.DriftReference) -> Reference:
    """DriftReference message -> ``signals.Reference``."""
    return Reference(
        stamp=time_from_msg(m.header.stamp), target=equilibrium_from_msg(m.target),
        direction=Direction(int(m.direction)),
        horizon=tuple(equilibrium_from_msg(e) for e in m.horizon), curvature=m.curvature,
        curvature_cmd=m.curvature_cmd, s=m.s, e_y=m.e_y, heading_error=m.heading_error,
        clamped=bool(m.clamped), horizon_curvature=tuple(float(K) for K in m.horizon_curvature))


def command_to_msg(cmd: Command, stamp=None, frame_id: str = BODY_FRAME) -> msg.DriftCommand:
    """``signals.Command`` -> DriftCommand message."""
    m = msg.DriftCommand(mode=int(cmd.mode), delta=cmd.delta, delta_rate=cmd.delta_rate,
                         drive_torque=cmd.drive_torque)
    _header(m.header, stamp, cmd.stamp, frame_id)
    return m


def command_from_msg(m: msg.DriftCommand) -> Command:
    """DriftCommand message -> ``signals.Command``."""
    return Command(stamp=time_from_msg(m.header.stamp), delta=m.delta, delta_rate=m.delta_rate,
                   drive_torque=m.drive_torque, mode=Mode(int(m.mode)))


def path_to_msg(path, stamp, frame_id: str = MAP_FRAME, step: float = 0.5):
    """``drift_control.path.Path`` -> ``nav_msgs/Path``, one pose every ``step`` [m]."""
    m = PathMsg()
    _header(m.header, stamp, 0.0, frame_id)
    every = max(int(round(step / path.ds)), 1)
    idx = list(range(0, path.n, every)) + ([] if path.closed else [path.n - 1])
    for i in idx + ([0] if path.closed else []):
        pose = PoseStamped()
        pose.header = m.header
        pose.pose.position.x, pose.pose.position.y = float(path.x[i]), float(path.y[i])
        pose.pose.orientation.z = math.sin(0.5 * float(path.psi[i]))
        pose.pose.orientation.w = math.cos(0.5 * float(path.psi[i]))
        m.poses.append(pose)
    return m


def status_to_msg(result, stamp=None, frame_id: str = BODY_FRAME) -> msg.NmpcStatus:
    """``nmpc.NmpcResult`` -> NmpcStatus message (predicted trajectory flattened row-major)."""
    from drift_control.nmpc import INPUT_NAMES, STATE_NAMES   # casadi only for the NMPC node
    m = msg.NmpcStatus(
        status=int(result.status), message=str(result.message)[:500],
        iterations=int(result.iterations), solve_time=float(result.solve_time_s),
        cost=float(result.cost), consecutive_failures=int(result.consecutive_failures),
        stage_dt=float(result.stage_dt), state_names=list(STATE_NAMES),
        predicted_states=[float(v) for v in result.predicted_states.ravel()],
        input_names=list(INPUT_NAMES),
        predicted_inputs=[float(v) for v in result.predicted_inputs.ravel()])
    _header(m.header, stamp, result.command.stamp, frame_id)
    return m


SENSOR_UNITS = tuple(FIELDS)   # SensorSample.UNIT_* in this order


def sensor_samples_to_msg(samples, stamp, t: float | None = None) -> msg.SensorSamples:
    """``estimator.SensorSample``s that arrived together at ``stamp`` -> SensorSamples message.

    ``t``: the samples' own clock at ``stamp`` (a simulator's time in a real-time run): each
    sample is then stamped ``stamp`` minus its age ``t - sample.stamp``; None: as it is.
    """
    m = msg.SensorSamples()
    m.header.stamp = time_to_msg(stamp)
    m.header.frame_id = BODY_FRAME
    arrival = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
    for s in samples:
        ns = (arrival - int(round((t - s.stamp) * 1e9)) if t is not None
              else int(round(s.stamp * 1e9)))
        m.samples.append(msg.SensorSample(
            stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
            unit=SENSOR_UNITS.index(s.unit), values=[float(v) for v in s.values]))
    return m


def sensor_samples_from_msg(m: msg.SensorSamples, epoch: int = 0):
    """SensorSamples message -> (arrival [s], list of ``estimator.SensorSample``), times minus
    ``epoch`` whole seconds (wall-clock stamps keep their nanoseconds in a float that way),
    rounded to the nanosecond as the simulator's own stamps are: the estimator then steps on
    the very floats of the one-process loop (``drift_sim.closed_loop``).

    ValueError for a unit out of range, a wrong number of values or a non-finite one.
    """
    def seconds(t):
        return round((t.sec - epoch) + 1e-9 * t.nanosec, 9)

    samples = []
    for s in m.samples:
        if s.unit >= len(SENSOR_UNITS):
            raise ValueError(f'sensor unit {s.unit} out of range 0..{len(SENSOR_UNITS) - 1}')
        unit = SENSOR_UNITS[s.unit]
        values = tuple(float(v) for v in s.values)
        if len(values) != len(FIELDS[unit]) or not all(math.isfinite(v) for v in values):
            raise ValueError(f'{unit} sample needs {len(FIELDS[unit])} finite values '
                             f'{FIELDS[unit]}, got {list(values)}')
        samples.append(SensorSample(unit, seconds(s.stamp), values))
    return seconds(m.header.stamp), samples


def decode(convert, msg, logger=None):
    """``convert(msg)``, or None for a malformed message (an enum out of range, a wrong-length
    array): a message is rejected with its reason, it never ends a node."""
    try:
        return convert(msg)
    except (ValueError, TypeError, IndexError, OverflowError) as err:
        if logger is not None:
            logger.warning(f'rejected a malformed {type(msg).__name__}: {err}',
                           throttle_duration_sec=2.0)
        return None


__all__ = ['SENSOR_UNITS', 'command_from_msg', 'command_to_msg', 'decode', 'equilibrium_from_msg',
           'equilibrium_to_msg', 'path_to_msg', 'reference_from_msg', 'reference_to_msg',
           'sensor_samples_from_msg', 'sensor_samples_to_msg', 'state_from_msg', 'state_to_msg',
           'status_to_msg', 'time_from_msg', 'time_to_msg']
