"""The DBC codec: CAN frames <-> VehicleState / Command signals, with E2E CRC8 and alive counter.

No bus and no ROS here. The frame layout lives in ``config/can/drift_vehicle.dbc`` (cantools does
all bit packing); this module adds the AUTOSAR E2E profile-1 style protection the DBC documents:
byte 0 is a CRC8 SAE J1850 over the message's 16-bit ``E2E_DataID`` (low, high byte) and the
remaining payload bytes, and a 4-bit ``AliveCounter`` counts transmissions.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from enum import Enum

import can
import cantools
from crccheck.crc import Crc8SaeJ1850

from drift_control.params import ParamError
from drift_control.signals import Command, Mode, Validity, VehicleState
from drift_vehicle_bridge.mode import BridgeMode

CRC_SIGNAL = 'CRC'
COUNTER_SIGNAL = 'AliveCounter'
COUNTER_MODULO = 16

# State frames: message -> {DBC signal: VehicleState field}. Wheel speeds go to wheel_speeds[i].
STATE_FRAMES: dict[str, dict[str, str]] = {
    'DS_VELOCITY': {'vx': 'vx', 'vy': 'vy', 'V': 'V'},
    'DS_YAW': {'r': 'r', 'beta': 'beta'},
    'DS_ACCEL': {'ax': 'ax', 'ay': 'ay'},
    'DS_WHEELS_FRONT': {'omega_FL': 'omega_FL', 'omega_FR': 'omega_FR'},
    'DS_WHEELS_REAR': {'omega_RL': 'omega_RL', 'omega_RR': 'omega_RR'},
    'DS_STEERING': {'delta': 'delta', 'steering_torque': 'steering_torque'},
    'DS_POWERTRAIN': {'drive_torque': 'drive_torque', 'brake_pedal': 'brake_pedal'},
    'DS_POSE_XY': {'x': 'x', 'y': 'y'},
    'DS_POSE_YAW': {'yaw': 'yaw'},
}
WHEELS = ('omega_FL', 'omega_FR', 'omega_RL', 'omega_RR')   # order of VehicleState.wheel_speeds

# Which fresh frames each validity bit needs.
VALIDITY_FRAMES: dict[Validity, tuple[str, ...]] = {
    Validity.V: ('DS_VELOCITY',),
    Validity.VX_VY: ('DS_VELOCITY',),
    Validity.BETA: ('DS_YAW',),
    Validity.R: ('DS_YAW',),
    Validity.AX_AY: ('DS_ACCEL',),
    Validity.WHEEL_SPEEDS: ('DS_WHEELS_FRONT', 'DS_WHEELS_REAR'),
    Validity.DELTA: ('DS_STEERING',),
    Validity.STEERING_TORQUE: ('DS_STEERING',),
    Validity.DRIVE_TORQUE: ('DS_POWERTRAIN',),
    Validity.BRAKE_PEDAL: ('DS_POWERTRAIN',),
    Validity.POSE: ('DS_POSE_XY', 'DS_POSE_YAW'),
}

CMD_STEER = 'DS_CMD_STEER'
CMD_TORQUE = 'DS_CMD_TORQUE'
CMD_STATUS = 'DS_CMD_STATUS'
COMMAND_FRAMES = (CMD_STEER, CMD_TORQUE, CMD_STATUS)


class Fault(str, Enum):
    """Why a received frame was rejected (the keys of the fault counters)."""

    UNKNOWN_ID = 'unknown_id'           # not in the DBC, or extended / FD / remote / error frame
    DLC = 'dlc'                         # payload length differs from the DBC
    CRC = 'crc'                         # E2E CRC mismatch
    COUNTER_REPEAT = 'counter_repeat'   # same alive counter as the last accepted frame
    COUNTER_JUMP = 'counter_jump'       # counter advanced by more than max_counter_delta
    RANGE = 'range'                     # a signal outside its DBC [min|max]


class FrameError(Exception):
    """A received frame failed a check; ``fault`` says which."""

    def __init__(self, fault: Fault, detail: str):
        super().__init__(f'{fault.value}: {detail}')
        self.fault = fault


@dataclass(frozen=True)
class Frame:
    """A decoded frame that passed the ID, DLC and CRC checks."""

    name: str
    counter: int
    values: dict


class Codec:
    """Encode and decode the DBC's frames with their E2E protection.

    Parameters
    ----------
    db : cantools.database.can.Database
        The drift vehicle DBC; checked once here for the E2E layout every frame must have.
    """

    def __init__(self, db):
        self.db = db
        self._by_name = {m.name: m for m in db.messages}
        self._by_id = {m.frame_id: m for m in db.messages}
        self._data_id: dict[int, bytes] = {}
        self._limits: dict[str, list[tuple[str, float, float]]] = {}
        seen_ids = set()
        for m in db.messages:
            crc, counter = _signal(m, CRC_SIGNAL), _signal(m, COUNTER_SIGNAL)
            if crc is None or crc.start != 0 or crc.length != 8 or counter is None \
                    or counter.length != 4:
                raise ParamError(f'dbc {m.name}: needs CRC at bits 0..7 and a 4-bit AliveCounter')
            attr = m.dbc.attributes.get('E2E_DataID') if m.dbc else None
            data_id = attr.value if attr else 0
            if not 0 < data_id < 65536 or data_id in seen_ids:
                raise ParamError(f'dbc {m.name}: E2E_DataID {data_id} missing or not unique')
            seen_ids.add(data_id)
            self._data_id[m.frame_id] = data_id.to_bytes(2, 'little')
            # Half a step of slack: decoded values are raw * scale, exact to float rounding.
            self._limits[m.name] = [
                (s.name, s.minimum - 0.5 * s.scale, s.maximum + 0.5 * s.scale)
                for s in m.signals if s.minimum is not None and s.maximum is not None]
        for name, sigs in STATE_FRAMES.items():
            missing = set(sigs) - {s.name for s in self.message(name).signals}
            if missing:
                raise ParamError(f'dbc {name}: lacks signal(s) {sorted(missing)}')
        for name in COMMAND_FRAMES:
            self.message(name)

    @classmethod
    def load(cls, path: str | os.PathLike) -> 'Codec':
        """Read a DBC file (cantools, strict: overlapping signals are an error)."""
        try:
            db = cantools.database.load_file(str(path), database_format='dbc', strict=True)
        except (OSError, cantools.database.UnsupportedDatabaseFormatError) as err:
            raise ParamError(f'{path}: cannot read the DBC: {err}') from None
        return cls(db)

    def message(self, name: str):
        """The cantools message called ``name``."""
        try:
            return self._by_name[name]
        except KeyError:
            raise ParamError(f'dbc: no message {name!r}') from None

    def frame_id(self, name: str) -> int:
        return self.message(name).frame_id

    def name_of(self, frame_id: int) -> str | None:
        m = self._by_id.get(frame_id)
        return m.name if m else None

    def crc(self, frame_id: int, data: bytes) -> int:
        """E2E CRC8 (SAE J1850) over the data ID and every payload byte after the CRC byte."""
        return Crc8SaeJ1850.calc(self._data_id[frame_id] + bytes(data[1:]))

    def encode(self, name: str, values: dict, counter: int, strict: bool = True) -> can.Message:
        """One protected frame; ``strict=False`` lets out-of-range values through (tests only)."""
        m = self.message(name)
        raw = {**values, CRC_SIGNAL: 0, COUNTER_SIGNAL: counter % COUNTER_MODULO}
        data = bytearray(m.encode(raw, scaling=True, strict=strict))
        data[0] = self.crc(m.frame_id, data)
        return can.Message(arbitration_id=m.frame_id, data=data, is_extended_id=False,
                           is_fd=False)

    def decode(self, msg: can.Message) -> Frame:
        """Check ID, DLC and CRC and decode; raises FrameError (range: see ``check_range``)."""
        m = self._by_id.get(msg.arbitration_id)
        if m is None or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame \
                or msg.is_fd:
            raise FrameError(Fault.UNKNOWN_ID, f'id 0x{msg.arbitration_id:x}')
        data = bytes(msg.data or b'')
        if len(data) != m.length or msg.dlc != m.length:
            raise FrameError(Fault.DLC, f'{m.name}: {len(data)} bytes, dlc {msg.dlc}')
        if data[0] != self.crc(m.frame_id, data):
            raise FrameError(Fault.CRC, m.name)
        values = m.decode(data, decode_choices=False, scaling=True)
        return Frame(m.name, int(values[COUNTER_SIGNAL]), values)

    def check_range(self, frame: Frame) -> None:
        """Raise FrameError(RANGE) if a signal lies outside its DBC [min|max]."""
        for sig, lo, hi in self._limits[frame.name]:
            if not lo <= frame.values[sig] <= hi:
                raise FrameError(Fault.RANGE, f'{frame.name}.{sig} = {frame.values[sig]}')

    def saturate(self, name: str, values: dict) -> dict:
        """Clip values to the DBC range of their signals (a gateway saturates, it cannot fail)."""
        sigs = {s.name: s for s in self.message(name).signals}
        return {k: min(max(v, sigs[k].minimum), sigs[k].maximum) for k, v in values.items()}


def state_signals(state: VehicleState) -> dict[str, dict]:
    """Signal values of every state frame for ``state`` (message name -> {signal: value})."""
    fields = {'vx': state.vx, 'vy': state.vy, 'V': state.V, 'r': state.r, 'beta': state.beta,
              'ax': state.ax, 'ay': state.ay, 'delta': state.delta,
              'steering_torque': state.steering_torque, 'drive_torque': state.drive_torque,
              'brake_pedal': int(bool(state.brake_pedal)), 'x': state.x, 'y': state.y,
              'yaw': math.atan2(math.sin(state.yaw), math.cos(state.yaw))}
    fields.update(zip(WHEELS, state.wheel_speeds))
    return {name: {sig: fields[f] for sig, f in sigs.items()}
            for name, sigs in STATE_FRAMES.items()}


def state_from_fields(fields: dict, stamp: float, validity: int) -> VehicleState:
    """A VehicleState from the latest decoded field values (missing fields read 0)."""
    get = fields.get
    return VehicleState(
        stamp=stamp, V=get('V', 0.0), beta=get('beta', 0.0), r=get('r', 0.0),
        vx=get('vx', 0.0), vy=get('vy', 0.0), ax=get('ax', 0.0), ay=get('ay', 0.0),
        wheel_speeds=tuple(get(w, 0.0) for w in WHEELS), delta=get('delta', 0.0),
        steering_torque=get('steering_torque', 0.0), drive_torque=get('drive_torque', 0.0),
        brake_pedal=bool(get('brake_pedal', 0)), x=get('x', 0.0), y=get('y', 0.0),
        yaw=get('yaw', 0.0), validity=int(validity))


def frame_fields(frame: Frame) -> dict:
    """The VehicleState field values a decoded state frame carries."""
    return {field: float(frame.values[sig]) for sig, field in STATE_FRAMES[frame.name].items()}


def steer_signals(cmd: Command) -> dict:
    return {'steer_request': 1, 'delta_req': cmd.delta, 'delta_rate_req': cmd.delta_rate}


def torque_signals(cmd: Command) -> dict:
    return {'torque_request': 1, 'torque_req': cmd.drive_torque}


def command_from_signals(status: dict, steer: dict | None, torque: dict | None,
                         stamp: float) -> Command | None:
    """What the car must apply: None unless the bridge is ACTIVE and its request frames are fresh.

    In ACTIVE_TORQUE_ONLY the steering stays with the driver: ``delta`` and ``delta_rate`` are 0
    and ``mode`` is ``Mode.TORQUE_ONLY``.
    """
    mode = int(status['bridge_mode'])
    if mode == BridgeMode.ACTIVE_FULL and steer and torque and steer['steer_request'] \
            and torque['torque_request']:
        return Command(stamp, float(steer['delta_req']), float(steer['delta_rate_req']),
                       float(torque['torque_req']), Mode.FULL)
    if mode == BridgeMode.ACTIVE_TORQUE_ONLY and torque and torque['torque_request']:
        return Command(stamp, 0.0, 0.0, float(torque['torque_req']), Mode.TORQUE_ONLY)
    return None


def _signal(message, name):
    return next((s for s in message.signals if s.name == name), None)
