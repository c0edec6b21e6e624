"""Bridge parameters: ``config/bridge.yaml`` loaded into frozen, validated dataclasses."""
from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass, field
from pathlib import Path

from drift_control.params import (ParamError, config_dir, from_dict, load_vehicle, load_yaml,
                                  merge, require)
from drift_vehicle_bridge.e2e import SMConfig


# python-can interfaces that cannot reach a vehicle: the only ones auto_arm is allowed on.
SIMULATED_INTERFACES = ('virtual', 'udp_multicast')
TRANSPORTS = ('can', 'udp')


@dataclass(frozen=True)
class BusParams:
    """What ``can.Bus(**kwargs)`` gets: any python-can interface (socketcan, pcan, virtual...)."""

    interface: str              # python-can backend name
    channel: str                # 'can0', 'PCAN_USBBUS1', a virtual channel name, a multicast group
    bitrate: int = 500000       # [bit/s]; ignored by virtual and udp_multicast
    fd: bool = False            # CAN FD frames (a CAN FD description needs it)

    def __post_init__(self):
        require(bool(self.interface), 'bridge.bus.interface', 'must not be empty')
        require(self.bitrate > 0, 'bridge.bus.bitrate', f'must be positive, got {self.bitrate}')

    def kwargs(self) -> dict:
        """Keyword arguments for ``can.Bus``."""
        return {'interface': self.interface, 'channel': self.channel,
                'bitrate': self.bitrate, 'fd': self.fd}


@dataclass(frozen=True)
class UdpParams:
    """PDUs over UDP with the Socket Adaptor header, the way an Ethernet gateway forwards them."""

    local: str = '127.0.0.1:30501'      # host:port the bridge receives on
    remote: str = '127.0.0.1:30502'     # the gateway's host:port

    def __post_init__(self):
        from drift_vehicle_bridge.soad import parse_endpoint
        parse_endpoint(self.local, 'bridge.udp.local')
        parse_endpoint(self.remote, 'bridge.udp.remote')

    def swapped(self) -> 'UdpParams':
        """The gateway's end of the same link (the simulated car)."""
        return UdpParams(local=self.remote, remote=self.local)


@dataclass(frozen=True)
class MonitorParams:
    """Receive checks: E2E counter tolerance, state machine and per-PDU timeouts."""

    frame_timeout: float = 0.03         # a state PDU older than this is stale [s] (3 cycles)
    max_counter_delta: int = 3          # accepted counter step: 2 lost PDUs, the frame timeout's gap
    timeouts: dict[str, float] = field(default_factory=dict)   # per-PDU overrides [s]
    e2e: SMConfig = SMConfig()          # AUTOSAR E2E state machine of every PDU

    def __post_init__(self):
        require(self.frame_timeout > 0, 'bridge.monitor.frame_timeout', 'must be positive')
        require(1 <= self.max_counter_delta <= 14, 'bridge.monitor.max_counter_delta',
                f'must be in [1, 14], got {self.max_counter_delta}')
        for name, t in self.timeouts.items():
            require(t > 0, f'bridge.monitor.timeouts.{name}', 'must be positive')


@dataclass(frozen=True)
class Envelope:
    """Operating envelope: speed window and sideslip / yaw-rate magnitudes."""

    V_min: float        # [m/s]
    V_max: float        # [m/s]
    beta_max: float     # |beta| limit [rad]
    r_max: float        # |r| limit [rad/s]

    def __post_init__(self):
        require(0 <= self.V_min < self.V_max, 'envelope', 'needs 0 <= V_min < V_max')
        require(self.beta_max > 0 and self.r_max > 0, 'envelope',
                'beta_max and r_max must be positive')

    def holds(self, V: float, beta: float, r: float) -> bool:
        """True inside the envelope."""
        return self.V_min <= V <= self.V_max and abs(beta) <= self.beta_max \
            and abs(r) <= self.r_max


@dataclass(frozen=True)
class ModeParams:
    """Arming, takeover and heartbeat rules of the mode manager."""

    arm_envelope: Envelope              # state must be inside to arm
    active_envelope: Envelope           # leaving it while ARMED/ACTIVE drops to OFF
    steering_torque_takeover: float     # driver torque above this drops to OFF [Nm]
    heartbeat_timeout: float            # DriftCommand older than this drops to OFF [s]
    arm_timeout: float                  # ARMED without a command for this long drops to OFF [s]
    allow_full: bool = True             # False: FULL commands are executed torque-only

    def __post_init__(self):
        require(self.steering_torque_takeover > 0, 'bridge.mode.steering_torque_takeover',
                'must be positive')
        require(self.heartbeat_timeout > 0, 'bridge.mode.heartbeat_timeout', 'must be positive')
        require(self.arm_timeout > 0, 'bridge.mode.arm_timeout', 'must be positive')


@dataclass(frozen=True)
class LimitParams:
    """Command clamps and rate limits, applied after the NMPC and before the bus."""

    delta_max: float            # |road-wheel angle| [rad]
    delta_rate_max: float       # |road-wheel rate| [rad/s]
    torque_min: float           # rear axle torque [Nm]
    torque_max: float           # [Nm]
    torque_rate_max: float      # |d torque / dt| [Nm/s]

    def __post_init__(self):
        require(self.delta_max > 0, 'bridge.limits.delta_max', 'must be positive')
        require(self.delta_rate_max > 0, 'bridge.limits.delta_rate_max', 'must be positive')
        require(self.torque_min <= 0 <= self.torque_max, 'bridge.limits',
                'needs torque_min <= 0 <= torque_max')
        require(self.torque_rate_max > 0, 'bridge.limits.torque_rate_max', 'must be positive')


@dataclass(frozen=True)
class SensorLinkParams:
    """Sensor mode: the sensor units' signals handed to the state estimator as samples."""

    enabled: bool = False               # publish vehicle/sensors instead of vehicle/state
    latency: dict[str, float] = field(default_factory=dict)   # unit -> sample instant to the
                                                              # bridge's reception [s]
    rate: dict[str, float] = field(default_factory=dict)      # unit -> samples per second [Hz]

    def __post_init__(self):
        from drift_vehicle_bridge.description import SENSOR_SIGNALS
        for key, table, low, high, unit_of in (('latency', self.latency, 0.0, 0.5, 's'),
                                               ('rate', self.rate, 1.0, 1000.0, 'Hz')):
            for unit, v in table.items():
                require(unit in SENSOR_SIGNALS, f'bridge.sensors.{key}.{unit}',
                        f'unknown sensor unit (one of {list(SENSOR_SIGNALS)})')
                require(low <= v <= high, f'bridge.sensors.{key}.{unit}',
                        f'must be in [{low:g}, {high:g}] {unit_of}, got {v!r}')
            missing = [u for u in SENSOR_SIGNALS if u not in table]
            require(not self.enabled or not missing, f'bridge.sensors.{key}',
                    f'sensor mode needs the {key} of every unit (missing {missing})')


@dataclass(frozen=True)
class BridgeParams:
    """Everything the bridge core needs; ``description`` is relative to the config directory."""

    description: str                    # bus description: a DBC (CAN, CAN FD) or a FlexRay ARXML
    cycle_time: float                   # [s]
    transport: str                      # 'can' (python-can ``bus``) or 'udp' (``udp``)
    bus: BusParams
    monitor: MonitorParams
    mode: ModeParams
    limits: LimitParams
    tx_allow: tuple[str, ...]           # the only PDU names ever written
    udp: UdpParams = UdpParams()
    sensors: SensorLinkParams = SensorLinkParams()
    auto_arm: bool = False              # simulation only: arm without an operator request

    def __post_init__(self):
        require(0 < self.cycle_time <= 0.1, 'bridge.cycle_time', 'must be in (0, 0.1] s')
        require(self.transport in TRANSPORTS, 'bridge.transport',
                f'must be one of {TRANSPORTS}, got {self.transport!r}')
        require(len(self.tx_allow) > 0, 'bridge.tx_allow', 'must name at least one PDU')
        # On a car, arming is the safety driver's decision; never a configuration default.
        require(not self.auto_arm or self.simulated(), 'bridge.auto_arm',
                f'only on a simulated link (CAN {SIMULATED_INTERFACES} or UDP on loopback), '
                f'not on {self.link()}')

    def simulated(self) -> bool:
        """True when the link cannot reach a vehicle: a simulated CAN bus, or UDP on loopback."""
        if self.transport == 'can':
            return self.bus.interface in SIMULATED_INTERFACES
        from drift_vehicle_bridge.soad import parse_endpoint
        return all(_loopback(parse_endpoint(e)[0]) for e in (self.udp.local, self.udp.remote))

    def link(self) -> str:
        """The link in words, for logs: ``udp_multicast:239.74.163.10``, ``udp 127.0.0.1:30502``."""
        if self.transport == 'can':
            return f'{self.bus.interface}:{self.bus.channel}'
        return f'udp {self.udp.local} -> {self.udp.remote}'


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == 'localhost'


def load_bridge_params(cfg_dir: str | os.PathLike | None = None,
                       overrides: dict | None = None,
                       vehicle: str | None = None) -> BridgeParams:
    """Load ``bridge.yaml`` from ``cfg_dir`` (default: the project's config directory).

    ``overrides`` is merged per section (``{'bus': {'channel': 'vcan0'}}``) before validation,
    so a node parameter gets the same checks as the file. The command limits come from the
    vehicle's (``config/vehicle/<vehicle>.yaml`` limits, default vehicle when None): bridge.yaml
    may set a tighter one, never a wider one.
    """
    cfg_dir = Path(cfg_dir) if cfg_dir else config_dir()
    raw = merge(load_yaml(cfg_dir / 'bridge.yaml'), overrides)
    limits = raw.get('limits') or {}
    if isinstance(limits, dict):
        raw['limits'] = {**vehicle_limits(load_vehicle(vehicle, cfg_dir).limits, limits), **limits}
    return from_dict(BridgeParams, raw, 'bridge')


def vehicle_limits(lim, tighter: dict) -> dict:
    """The bridge's command limits of a vehicle's ``ActuatorLimits``; ``tighter`` values must
    lie within them (a ParamError names the key otherwise)."""
    own = {'delta_max': lim.delta_max, 'delta_rate_max': lim.delta_dot_max,
           'torque_min': lim.T_R_min, 'torque_max': lim.T_R_max}
    for key, value in tighter.items():
        if key not in own or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue   # the validator names unknown keys and non-numbers
        wider = value < own[key] if key == 'torque_min' else value > own[key]
        if wider:
            raise ParamError(f'bridge.limits.{key}: {value} is beyond the vehicle\'s own limit '
                             f'{own[key]} (config/vehicle): the bridge may only tighten it')
    return own


def description_path(params: BridgeParams, cfg_dir: str | os.PathLike | None = None) -> Path:
    """Absolute path of the bus description named in the parameters."""
    path = Path(params.description)
    return path if path.is_absolute() else (Path(cfg_dir) if cfg_dir else config_dir()) / path


__all__ = ['BridgeParams', 'BusParams', 'Envelope', 'LimitParams', 'ModeParams',
           'MonitorParams', 'ParamError', 'SIMULATED_INTERFACES', 'SensorLinkParams', 'UdpParams',
           'description_path',
           'load_bridge_params']
