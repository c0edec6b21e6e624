"""Plant parameters: ``config/sim/plants/<vehicle>.yaml`` loaded into frozen, validated dataclasses.

The plant has its own parameter set (per-wheel tyres, track widths, powertrain, steering system,
road, sensors), deliberately different from the controller's ``config/vehicle`` so that the
closed loop meets model mismatch. ``set_key`` applies ``--set a.b.c=value`` overrides to a raw
mapping before it is validated, so every parameter can be changed from the command line.
"""
from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from pathlib import Path


from drift_control.params import (CombinedTyreParams, ParamError, config_dir, from_dict,
                                  load_yaml, require, set_key, split_override,
                                  vehicle_file)

SIGNALS = ('V', 'beta', 'r', 'vx', 'vy', 'ax', 'ay', 'wheel_speeds', 'delta', 'steering_torque',
           'drive_torque', 'pose', 'yaw')


@dataclass(frozen=True)
class BodyParams:
    """Rigid body and quasi-static load transfer."""

    m: float             # total mass [kg]
    I_z: float           # yaw inertia [kg m^2]
    a: float             # CoG to front axle [m]
    L: float             # wheelbase [m]
    h: float             # CoG height [m]
    track_F: float       # front track [m]
    track_R: float       # rear track [m]
    roll_share_F: float  # front share of the lateral load transfer [-]
    load_tau: float      # lag of the load transfer [s]
    c_drag: float        # 0.5 rho c_d A [kg/m]
    c_roll: float        # rolling resistance coefficient [-]
    g: float = 9.81      # gravity [m/s^2]

    def __post_init__(self):
        for name in ('m', 'I_z', 'L', 'h', 'track_F', 'track_R', 'load_tau', 'g'):
            require(getattr(self, name) > 0, f'plant.body.{name}', 'must be positive')
        require(0 < self.a < self.L, 'plant.body.a', 'must lie between 0 and L')
        require(0 <= self.roll_share_F <= 1, 'plant.body.roll_share_F', 'must be in [0, 1]')
        require(self.c_drag >= 0 and self.c_roll >= 0, 'plant.body', 'c_drag, c_roll must be >= 0')

    @property
    def b(self) -> float:
        """CoG to rear axle [m]."""
        return self.L - self.a


@dataclass(frozen=True)
class WheelParams:
    """Wheel spin, tyre relaxation and slip regularisation."""

    R_F: float        # front rolling radius [m]
    R_R: float        # rear rolling radius [m]
    I_wF: float       # one front wheel [kg m^2]
    I_wR: float       # one rear wheel [kg m^2]
    I_drive: float    # engine and driveline reflected to the rear axle [kg m^2]
    sigma_x: float    # longitudinal relaxation length [m]
    sigma_y: float    # lateral relaxation length [m]
    v_eps: float      # slip regularisation speed [m/s]
    omega_eps: float  # brake / rolling resistance sign smoothing [rad/s]

    def __post_init__(self):
        for name in ('R_F', 'R_R', 'I_wF', 'I_wR', 'sigma_x', 'sigma_y', 'v_eps', 'omega_eps'):
            require(getattr(self, name) > 0, f'plant.wheels.{name}', 'must be positive')
        require(self.I_drive >= 0, 'plant.wheels.I_drive', 'must be >= 0')


@dataclass(frozen=True)
class LsdParams:
    """Rear limited-slip differential: locking torque ``min(cap, viscous * d_omega)``, smooth."""

    locking: float    # capacity as a fraction of the input torque [-]; 0 is an open differential
    preload: float    # capacity at zero input torque [Nm]
    viscous: float    # slope in the left-right wheel speed difference [Nm s/rad]

    def __post_init__(self):
        require(0.0 <= self.locking <= 1.0, 'plant.lsd.locking', 'must be in [0, 1]')
        require(self.preload >= 0 and self.viscous > 0, 'plant.lsd',
                'preload must be >= 0 and viscous > 0')


@dataclass(frozen=True)
class PowertrainParams:
    """Drive torque lag and delay, torque range, brakes."""

    tau: float            # first-order lag [s]
    delay: float          # transport delay [s]
    T_min: float          # rear axle torque range [Nm]
    T_max: float
    brake_balance: float  # front share of the brake torque [-]

    def __post_init__(self):
        require(self.tau > 0 and self.delay >= 0, 'plant.powertrain', 'tau > 0, delay >= 0')
        require(self.T_min < self.T_max, 'plant.powertrain', 'T_min must be below T_max')
        require(0 <= self.brake_balance <= 1, 'plant.powertrain.brake_balance', 'in [0, 1]')


@dataclass(frozen=True)
class SteeringParams:
    """Steering system: rate-limited reference, torque-limited position loop, aligning moment."""

    ratio: float             # steering-wheel / road-wheel angle [-]
    delta_max: float         # road-wheel angle end stop [rad]
    rate_max: float          # rate limit of the actuator's angle reference [rad/s]
    J: float                 # inertia at the road wheels [kg m^2]
    c: float                 # damping at the road wheels [Nm s/rad]
    bandwidth: float         # position-loop bandwidth [Hz]
    torque_max: float        # actuator torque at the steering wheel [Nm]
    driver_torque_max: float  # human (with assist) torque at the steering wheel [Nm]
    driver_share: float      # share of the steering torque the human feels, rest is assist [-]
    trail_mech: float        # mechanical trail [m]
    trail_pneu: float        # pneumatic trail at zero slip [m]
    trail_B: float           # pneumatic trail decay [1/rad]

    def __post_init__(self):
        for name in ('ratio', 'delta_max', 'rate_max', 'J', 'bandwidth', 'torque_max',
                     'driver_torque_max'):
            require(getattr(self, name) > 0, f'plant.steering.{name}', 'must be positive')
        require(0 <= self.driver_share <= 1, 'plant.steering.driver_share', 'must be in [0, 1]')
        require(self.c >= 0 and self.trail_mech >= 0 and self.trail_pneu >= 0,
                'plant.steering', 'c and trails must be >= 0')


@dataclass(frozen=True)
class RoadParams:
    """Spatial friction field: ``mu(x, y) = mu_surface + variation * g(x, y)``, ``|g| <= 1``."""

    variation: float       # amplitude [-]
    wavelength_min: float  # [m]
    wavelength_max: float  # [m]
    modes: int             # number of plane waves

    def __post_init__(self):
        require(0 <= self.variation < 0.5, 'plant.road.variation', 'must be in [0, 0.5)')
        require(0 < self.wavelength_min <= self.wavelength_max, 'plant.road',
                'need 0 < wavelength_min <= wavelength_max')
        require(self.modes >= 1, 'plant.road.modes', 'must be >= 1')


@dataclass(frozen=True)
class SignalNoise:
    """One measured signal: white Gaussian noise and a pure delay."""

    std: float     # standard deviation [signal unit]
    delay: float   # [s]

    def __post_init__(self):
        require(self.std >= 0 and self.delay >= 0, 'plant.measurement', 'std, delay >= 0')


@dataclass(frozen=True)
class PlantParams:
    """Everything the plant needs, from ``config/sim/plants/<vehicle>.yaml``."""

    dt: float
    substeps: int
    body: BodyParams
    wheels: WheelParams
    lsd: LsdParams
    powertrain: PowertrainParams
    steering: SteeringParams
    road: RoadParams
    front_tyre: CombinedTyreParams
    rear_tyre: CombinedTyreParams
    measurement: dict[str, SignalNoise] = field(default_factory=dict)

    def __post_init__(self):
        require(0 < self.dt <= 0.005, 'plant.dt', 'must be in (0, 5 ms]')
        require(self.substeps >= 1, 'plant.substeps', 'must be >= 1')
        unknown = sorted(set(self.measurement) - set(SIGNALS))
        require(not unknown, 'plant.measurement', f'unknown signal(s) {unknown}; known {SIGNALS}')

    @property
    def step(self) -> float:
        """Length of one plant call [s]."""
        return self.dt * self.substeps


def plant_file(vehicle: str | None = None, config: str | os.PathLike | None = None) -> Path:
    """``config/sim/plants/<vehicle>.yaml``: the simulator's car of a ``config/vehicle`` car."""
    vehicle = vehicle_file(vehicle, config).stem    # an unknown car: the known ones are named
    path = Path(config or config_dir()) / 'sim' / 'plants' / f'{vehicle}.yaml'
    if not path.is_file():
        raise ParamError(f'vehicle {vehicle!r}: no simulator plant {path} (the double-track '
                         'model of the car; see docs/bring_your_own_car.md)')
    return path


def plant_yaml(config: str | os.PathLike | None = None, vehicle: str | None = None) -> dict:
    """The raw mapping of a vehicle's plant file (default: the default vehicle's)."""
    return load_yaml(plant_file(vehicle, config))


def load_plant_params(raw: dict | None = None, overrides=(), config=None,
                      vehicle: str | None = None) -> PlantParams:
    """Validate a plant mapping (default: the vehicle's plant file) after ``--set`` overrides."""
    raw = copy.deepcopy(raw if raw is not None else plant_yaml(config, vehicle))
    for item in overrides:
        set_key(raw, *split_override(item), where='plant')
    return from_dict(PlantParams, raw, 'plant')
