"""Plain data passed between the stack's blocks: the ROS-free twins of the drift_msgs types.

Every block (simulator, bridge, reference selector, NMPC) speaks these; only ``nodes/convert.py``
of each package turns them into messages. SI units and radians throughout. Sign convention of the
whole stack: x forward, y left, yaw rate positive counter-clockwise; a left-hand (counter-clockwise)
drift has ``r > 0``, ``beta < 0`` and, once it is a full drift, counter-steer ``delta < 0``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields, replace
from enum import IntEnum, IntFlag


class Validity(IntFlag):
    """Per-signal validity bits; same values as the ``VALID_*`` constants of VehicleState.msg."""

    V = 1
    BETA = 2
    R = 4
    VX_VY = 8
    AX_AY = 16
    WHEEL_SPEEDS = 32
    DELTA = 64
    STEERING_TORQUE = 128
    DRIVE_TORQUE = 256
    BRAKE_PEDAL = 512
    POSE = 1024
    ALL = 2047

    # What the controller cannot do without: speed, sideslip, yaw rate, wheel speeds, steering.
    CONTROL = V | BETA | R | WHEEL_SPEEDS | DELTA


class Direction(IntEnum):
    """Drift direction; the value is the sign of the yaw rate."""

    RIGHT = -1
    NONE = 0
    LEFT = 1


class Mode(IntEnum):
    """Actuation mode of a command; same values as DriftCommand.msg ``MODE_*``."""

    OFF = 0
    FULL = 1
    TORQUE_ONLY = 2
    FALLBACK = 3


@dataclass(frozen=True)
class VehicleState:
    """Vehicle state as measured or estimated on the car (or by the simulator).

    Attributes
    ----------
    stamp : float
        Time of the measurement [s] (sim or wall time, the clock of the publisher).
    V : float
        Speed over ground [m/s].
    beta : float
        Sideslip angle ``atan2(vy, vx)`` [rad].
    r : float
        Yaw rate [rad/s].
    wheel_speeds : tuple of 4 float
        Wheel angular speeds FL, FR, RL, RR [rad/s].
    delta : float
        Road-wheel steering angle [rad].
    """

    stamp: float
    V: float
    beta: float
    r: float
    vx: float = 0.0
    vy: float = 0.0
    ax: float = 0.0
    ay: float = 0.0
    wheel_speeds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    delta: float = 0.0
    steering_torque: float = 0.0   # driver torque at the steering wheel [Nm]
    drive_torque: float = 0.0      # rear axle drive torque at the wheels, as applied [Nm]
    brake_pedal: bool = False
    x: float = 0.0                 # pose in the map frame [m, m, rad]
    y: float = 0.0
    yaw: float = 0.0
    validity: int = int(Validity.ALL)

    @property
    def omega_F(self) -> float:
        """Front axle wheel speed, mean of left and right [rad/s]."""
        return 0.5 * (self.wheel_speeds[0] + self.wheel_speeds[1])

    @property
    def omega_R(self) -> float:
        """Rear axle wheel speed, mean of left and right [rad/s]."""
        return 0.5 * (self.wheel_speeds[2] + self.wheel_speeds[3])

    def is_finite(self) -> bool:
        """True when every numeric field is finite (NaN/inf never reach a solver)."""
        # asked by the selector, the NMPC, its supervisor and checks each cycle: worked out once
        known = self.__dict__.get('_finite')
        if known is None:
            known = _all_finite(self)
            object.__setattr__(self, '_finite', known)
        return known

    def has(self, bits: Validity) -> bool:
        """True when all the given validity bits are set."""
        return (self.validity & int(bits)) == int(bits)


@dataclass(frozen=True)
class Equilibrium:
    """One steady-state drift equilibrium of the single-track model (paper Eq. 3).

    Attributes
    ----------
    V : float
        Speed [m/s].
    beta : float
        Sideslip angle [rad].
    r : float
        Yaw rate [rad/s]; path radius is ``V / r``.
    omega_F, omega_R : float
        Front and rear wheel speeds [rad/s].
    delta : float
        Road-wheel steering angle [rad].
    T_R : float
        Rear axle drive torque at the wheels [Nm].
    """

    V: float
    beta: float
    r: float
    omega_F: float
    omega_R: float
    delta: float
    T_R: float

    def mirrored(self) -> 'Equilibrium':
        """The same equilibrium driven the other way round (left <-> right)."""
        return Equilibrium(self.V, -self.beta, -self.r, self.omega_F, self.omega_R,
                           -self.delta, self.T_R)

    def is_finite(self) -> bool:
        isfinite = math.isfinite   # 26 per reference: field by field, not the generic walk
        try:
            return (isfinite(self.V) and isfinite(self.beta) and isfinite(self.r)
                    and isfinite(self.omega_F) and isfinite(self.omega_R)
                    and isfinite(self.delta) and isfinite(self.T_R))
        except TypeError:   # a field that is no number: judged as the other signals are
            return _all_finite(self)


@dataclass(frozen=True)
class Reference:
    """What the reference selector hands the NMPC each cycle.

    ``horizon`` optionally holds one equilibrium per NMPC stage (from the predicted arc length);
    empty means "hold ``target`` over the horizon". ``horizon_curvature`` is the path's own
    curvature at those stages (empty: ``curvature`` over the horizon).
    """

    stamp: float
    target: Equilibrium
    direction: Direction = Direction.NONE
    horizon: tuple[Equilibrium, ...] = ()
    curvature: float = 0.0       # path curvature K(s) [1/m], positive turning left
    curvature_cmd: float = 0.0   # curvature after the path-following correction [1/m]
    s: float = 0.0               # arc length along the path [m]
    e_y: float = 0.0             # lateral error, positive left of the path [m]
    heading_error: float = 0.0   # vehicle yaw minus path tangent angle [rad]
    clamped: bool = False        # the map lookup left the grid and was clamped
    horizon_curvature: tuple[float, ...] = ()   # path curvature at each horizon stage [1/m]

    def at(self, now: float, stage_dt: float) -> 'Reference':
        """This reference as seen ``now - stamp`` seconds after the state it was selected for:
        the horizon moved on by that many stages of ``stage_dt`` (linear between stages, the
        last one held), its first stage the target. Itself when not older or without a horizon.
        """
        shift = (now - self.stamp) / stage_dt
        if not shift > 0.0 or not self.horizon:
            return self
        stages, last = self.horizon, len(self.horizon) - 1
        K = self.horizon_curvature
        moved, moved_K = [], []
        for k in range(len(stages)):
            x = min(k + shift, float(last))
            i = min(int(x), last - 1) if last > 0 else 0
            f = x - i
            a, b = stages[i], stages[min(i + 1, last)]
            moved.append(a if f == 0.0 else Equilibrium(
                a.V + f * (b.V - a.V), a.beta + f * (b.beta - a.beta), a.r + f * (b.r - a.r),
                a.omega_F + f * (b.omega_F - a.omega_F), a.omega_R + f * (b.omega_R - a.omega_R),
                a.delta + f * (b.delta - a.delta), a.T_R + f * (b.T_R - a.T_R)))
            if len(K) == len(stages):
                moved_K.append(K[i] + f * (K[min(i + 1, last)] - K[i]))
        return replace(self, target=moved[0], horizon=tuple(moved),
                       horizon_curvature=tuple(moved_K) if moved_K else K)

    def is_finite(self) -> bool:
        # asked by the selector, the NMPC and the supervisor each cycle: worked out once (frozen)
        known = self.__dict__.get('_finite')
        if known is None:
            known = (self.target.is_finite() and all(e.is_finite() for e in self.horizon)
                     and _all_finite(self))
            object.__setattr__(self, '_finite', known)
        return known


@dataclass(frozen=True)
class Command:
    """Actuator command: road-wheel steering angle and rate, rear axle drive torque."""

    stamp: float
    delta: float
    delta_rate: float
    drive_torque: float
    mode: Mode = Mode.FULL


def _field_numbers(value) -> tuple[float, ...]:
    """A field's numbers: a float or int, or a tuple of them flattened; none for other values
    (nested dataclasses, None, strings)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (float(value),)
    if isinstance(value, tuple) and all(isinstance(v, (int, float)) for v in value):
        return tuple(float(v) for v in value)
    return ()


def _all_finite(obj) -> bool:
    """Every number of a dataclass's fields is finite (a short path for plain floats)."""
    for name in _field_names(type(obj)):
        value = getattr(obj, name)
        if type(value) is float:
            if not math.isfinite(value):
                return False
        elif not all(math.isfinite(v) for v in _field_numbers(value)):
            return False
    return True


@functools.lru_cache(maxsize=None)
def _field_names(cls) -> tuple[str, ...]:
    """A dataclass's field names, looked up once per class (checked on every cycle)."""
    return tuple(f.name for f in fields(cls))


__all__ = ['Command', 'Direction', 'Equilibrium', 'Mode', 'Reference', 'Validity',
           'VehicleState']
