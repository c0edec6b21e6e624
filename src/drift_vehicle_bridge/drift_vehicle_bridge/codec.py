"""The codec: PDUs <-> VehicleState / Command signals, for any bus description, E2E protected.

No bus and no ROS here. The PDUs, their bit layouts and their E2E profiles come from a
``Description`` (a classic or CAN FD DBC, a FlexRay ARXML: ``load_description``);
cantools packs the signals and ``e2e`` writes and checks the profile's header. The signal names
are the contract (``STATE_SIGNALS``, ``COMMAND_SIGNALS``), whatever PDU carries them.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from drift_control.params import ParamError
from drift_control.signals import Command, Mode, VehicleState
from drift_vehicle_bridge.description import (CMD_STATUS, CMD_STEER, CMD_TORQUE, COMMAND_FRAMES,
                                              COMMAND_SENDER, COMMAND_SIGNALS, SENSOR_SIGNALS,
                                              STATE_SENDER, STATE_SIGNALS, VALIDITY_SIGNALS,
                                              WHEELS, Description, PduSpec)
from drift_vehicle_bridge.e2e import Protection, protection
from drift_vehicle_bridge.mode import BridgeMode
from drift_vehicle_bridge.pdu import Pdu

class Fault(str, Enum):
    """Why a received PDU was rejected (the keys of the fault counters)."""

    UNKNOWN_ID = 'unknown_id'           # not in the description (or an extended/remote/error frame)
    FORMAT = 'format'                   # CAN FD frame for a classic message, or the reverse
    LENGTH = 'length'                   # payload length (or the E2E length field) differs
    CRC = 'crc'                         # E2E CRC mismatch
    DATA_ID = 'data_id'                 # protected with another PDU's data ID (misrouted, masquerade)
    COUNTER_REPEAT = 'counter_repeat'   # same E2E counter as the last accepted PDU
    COUNTER_JUMP = 'counter_jump'       # counter advanced by more than max_counter_delta
    RANGE = 'range'                     # a signal outside its [min|max]


class FrameError(Exception):
    """A received PDU failed a check; ``fault`` says which."""

    def __init__(self, fault: Fault, detail: str):
        super().__init__(f'{fault.value}: {detail}')
        self.fault = fault


@dataclass(frozen=True)
class Frame:
    """A decoded PDU that passed its checks: payload signal values (no E2E header fields)."""

    name: str
    counter: int
    values: dict


class Codec:
    """Encode and decode a description's PDUs with their E2E protection.

    Parameters
    ----------
    description : Description
        The bus description; checked once here: unique ids and data IDs, E2E headers that no
        payload signal overlaps, every state signal in exactly one GATEWAY PDU, the command PDUs.
    """

    def __init__(self, description: Description):
        self.description = description
        src = description.source
        self._specs: dict[str, PduSpec] = {}
        self._by_id: dict[int, PduSpec] = {}
        self._protection: dict[str, Protection] = {}
        self._payload: dict[str, list] = {}     # name -> cantools signals outside the E2E header
        self._header: dict[str, dict] = {}      # name -> {header signal: 0} for packing
        self._limits: dict[str, list[tuple[str, float, float]]] = {}
        e2e_ids = set()
        for spec in description.pdus:
            if spec.name in self._specs or spec.id in self._by_id:
                raise ParamError(f'{src}: {spec.name}: name or id 0x{spec.id:x} not unique')
            prot = protection(spec.e2e, spec.length)
            key = (spec.e2e.profile, spec.e2e.data_id, spec.e2e.data_id_list)
            if key in e2e_ids:
                raise ParamError(f'{src}: {spec.name}: E2E data ID {spec.e2e.data_id} not unique')
            e2e_ids.add(key)
            header, payload = {}, []
            for sig in spec.message.signals:
                bits = signal_bits(sig)
                if bits <= prot.header_bits:
                    header[sig.name] = 0
                elif bits & prot.header_bits:
                    raise ParamError(f'{src}: {spec.name}.{sig.name} overlaps the '
                                     f'{spec.e2e.profile} E2E header')
                else:
                    payload.append(sig)
            self._specs[spec.name], self._by_id[spec.id] = spec, spec
            self._protection[spec.name] = prot
            self._payload[spec.name], self._header[spec.name] = payload, header
            # Half a step of slack: decoded values are raw * scale, exact to float rounding.
            self._limits[spec.name] = [
                (s.name, s.minimum - 0.5 * s.scale, s.maximum + 0.5 * s.scale)
                for s in payload if s.minimum is not None and s.maximum is not None]
        self.state_frames = self._state_frames()
        self.sensor_frames, self.sensor_missing = self._sensor_frames()
        # every GATEWAY PDU with a state or sensor signal, and the sensor units each carries
        self.gateway_pdus = tuple(n for n in self._specs if n in self.state_frames or any(
            n in pdus for pdus in self.sensor_frames.values()))
        self.pdu_units = {n: tuple(u for u, pdus in self.sensor_frames.items() if n in pdus)
                          for n in self.gateway_pdus}
        self.validity_frames = {
            bit: tuple(sorted({n for n, sigs in self.state_frames.items() if set(sigs) & set(need)}))
            for bit, need in VALIDITY_SIGNALS.items()}
        for name, sigs in COMMAND_SIGNALS.items():
            missing = set(sigs) - {s.name for s in self.payload_signals(name)}
            if missing:
                raise ParamError(f'{src}: {name} lacks signal(s) {sorted(missing)}')
            if COMMAND_SENDER not in self.spec(name).senders:
                raise ParamError(f'{src}: {name} must be sent by {COMMAND_SENDER}')

    def _state_frames(self) -> dict[str, dict[str, str]]:
        """PDU name -> {signal: VehicleState field}: each state signal in one GATEWAY PDU."""
        carriers: dict[str, str] = {}
        for spec in self._specs.values():
            if STATE_SENDER not in spec.senders:
                continue
            for sig in self._payload[spec.name]:
                if sig.name in STATE_SIGNALS:
                    if sig.name in carriers:
                        raise ParamError(f'{self.description.source}: state signal {sig.name} in '
                                         f'both {carriers[sig.name]} and {spec.name}')
                    carriers[sig.name] = spec.name
        missing = sorted(set(STATE_SIGNALS) - set(carriers))
        if missing:
            raise ParamError(f'{self.description.source}: no {STATE_SENDER} PDU carries the '
                             f'state signal(s) {missing}')
        frames: dict[str, dict[str, str]] = {}
        for sig, name in carriers.items():
            frames.setdefault(name, {})[sig] = STATE_SIGNALS[sig]
        return frames

    def _sensor_frames(self) -> tuple[dict[str, tuple[str, ...]], dict[str, tuple[str, ...]]]:
        """Sensor unit -> the GATEWAY PDUs carrying its signals, for the units whose every
        signal a PDU carries; and unit -> its signals no PDU carries, for the others."""
        wanted = {s for sigs in SENSOR_SIGNALS.values() for s in sigs}
        carriers: dict[str, str] = {}
        for spec in self._specs.values():
            if STATE_SENDER not in spec.senders:
                continue
            for sig in self._payload[spec.name]:
                if sig.name in wanted and carriers.setdefault(sig.name, spec.name) != spec.name:
                    raise ParamError(f'{self.description.source}: sensor signal {sig.name} in '
                                     f'both {carriers[sig.name]} and {spec.name}')
        frames, missing = {}, {}
        for unit, sigs in SENSOR_SIGNALS.items():
            absent = tuple(s for s in sigs if s not in carriers)
            if absent:
                missing[unit] = absent
            else:
                frames[unit] = tuple(dict.fromkeys(carriers[s] for s in sigs))
        return frames, missing

    @classmethod
    def load(cls, path: str | os.PathLike) -> 'Codec':
        """Read a ``.dbc`` or ``.arxml`` bus description."""
        return cls(load_description(path))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._specs)

    def spec(self, name: str) -> PduSpec:
        """The PDU called ``name``."""
        try:
            return self._specs[name]
        except KeyError:
            raise ParamError(f'{self.description.source}: no PDU {name!r}') from None

    def message(self, name: str):
        """The cantools message (bit layout) of the PDU called ``name``."""
        return self.spec(name).message

    def protection(self, name: str) -> Protection:
        return self._protection[name]

    def payload_signals(self, name: str) -> list:
        """The PDU's cantools signals outside its E2E header."""
        return self._payload[name]

    def spec_of(self, pdu_id: int) -> PduSpec | None:
        return self._by_id.get(pdu_id)

    def encode(self, name: str, values: dict, counter: int, strict: bool = True) -> Pdu:
        """One protected PDU; ``strict=False`` lets out-of-range values through (tests only)."""
        spec = self.spec(name)
        data = bytearray(spec.message.encode({**values, **self._header[name]}, scaling=True,
                                             strict=strict))
        self._protection[name].protect(data, counter)
        return Pdu(spec.id, bytes(data), fd=spec.fd)

    def lookup(self, pdu: Pdu) -> PduSpec:
        """The description's PDU for a received one; FrameError for an unknown id or format."""
        spec = self._by_id.get(pdu.id)
        if spec is None:
            raise FrameError(Fault.UNKNOWN_ID, f'id 0x{pdu.id:x}')
        if pdu.fd is not None and spec.fd is not None and pdu.fd != spec.fd:
            raise FrameError(Fault.FORMAT, f'{spec.name}: {"CAN FD" if pdu.fd else "classic"} '
                                           f'frame')
        return spec

    def unpack(self, name: str, data: bytes) -> dict:
        """Payload signal values of an intact PDU (E2E header fields left out)."""
        values = self.spec(name).message.decode(data, decode_choices=False, scaling=True)
        header = self._header[name]
        return {k: v for k, v in values.items() if k not in header}

    def decode(self, pdu: Pdu) -> Frame:
        """Check id, format, length and E2E header (no receiver state) and decode."""
        spec = self.lookup(pdu)
        prot = self._protection[spec.name]
        error = prot.verify(pdu.data)
        if error is not None:
            raise FrameError(Fault(error), spec.name)
        return Frame(spec.name, prot.counter(pdu.data), self.unpack(spec.name, pdu.data))

    def check_range(self, frame: Frame) -> None:
        """Raise FrameError(RANGE) if a signal lies outside its [min|max]."""
        for sig, lo, hi in self._limits[frame.name]:
            if not lo <= frame.values[sig] <= hi:
                raise FrameError(Fault.RANGE, f'{frame.name}.{sig} = {frame.values[sig]}')

    def saturate(self, name: str, values: dict) -> dict:
        """Clip values to the range of their signals (a gateway saturates, it cannot fail)."""
        sigs = {s.name: s for s in self._payload[name]}
        return {k: min(max(v, sigs[k].minimum), sigs[k].maximum) for k, v in values.items()}

    def state_signals(self, state: VehicleState) -> dict[str, dict]:
        """Signal values of every GATEWAY PDU for ``state`` (PDU name -> {signal: value}); the
        inertial sensor's yaw rate ``r_imu`` is the state's ``r``."""
        fields = {'vx': state.vx, 'vy': state.vy, 'V': state.V, 'r': state.r,
                  'r_imu': state.r, 'beta': state.beta, 'ax': state.ax, 'ay': state.ay,
                  'delta': state.delta, 'steering_torque': state.steering_torque,
                  'drive_torque': state.drive_torque,
                  'brake_pedal': int(bool(state.brake_pedal)), 'x': state.x, 'y': state.y,
                  'yaw': math.atan2(math.sin(state.yaw), math.cos(state.yaw))}
        fields.update(zip(WHEELS, state.wheel_speeds))
        return {name: self._values(name, fields) for name in self.gateway_pdus}

    def sensor_signals(self, samples: dict[str, tuple], brake_pedal: bool = False) \
            -> dict[str, dict]:
        """Signal values of the GATEWAY PDUs that go out with one step's sensor samples
        (unit -> values in the order of ``SENSOR_SIGNALS[unit]``).

        A PDU goes out when every unit it carries has a sample here (a PDU of units at several
        rates at the slowest one's), a PDU of no unit every time. The INS's speed and sideslip
        give ``vx`` and ``vy``; a signal of no unit and no state field reads 0.
        """
        fields = {'brake_pedal': int(bool(brake_pedal))}
        for unit, values in samples.items():
            fields.update(zip(SENSOR_SIGNALS[unit], values))
        if 'ins' in samples:
            V, beta = fields['V'], fields['beta']
            fields.update(vx=V * math.cos(beta), vy=V * math.sin(beta),
                          yaw=math.atan2(math.sin(fields['yaw']), math.cos(fields['yaw'])))
        return {name: self._values(name, fields) for name in self.gateway_pdus
                if all(u in samples for u in self.pdu_units[name])}

    def _values(self, name: str, fields: dict) -> dict:
        return {s.name: fields.get(s.name, 0.0) for s in self._payload[name]}

    def frame_fields(self, frame: Frame) -> dict:
        """The VehicleState field values a decoded state PDU carries."""
        return {field: float(frame.values[sig])
                for sig, field in self.state_frames.get(frame.name, {}).items()}


def load_description(path: str | os.PathLike) -> Description:
    """Read a ``.dbc`` or ``.arxml`` file; ParamError (one line) when it cannot serve the codec."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == '.dbc':
        from drift_vehicle_bridge.dbc import load_dbc
        return load_dbc(path)
    if suffix == '.arxml':           # autosar-data only where an ARXML is read
        from drift_vehicle_bridge.arxml import load_arxml
        return load_arxml(path)
    raise ParamError(f'{path}: unknown bus description type {suffix!r} (.dbc or .arxml)')


def signal_bits(signal) -> frozenset[int]:
    """Bit positions (byte * 8 + bit, LSB 0) a cantools signal occupies."""
    if signal.byte_order == 'little_endian':
        return frozenset(range(signal.start, signal.start + signal.length))
    bits, pos = set(), signal.start    # big-endian: from the MSB, sawtooth numbering
    for _ in range(signal.length):
        bits.add(pos)
        pos = pos - 1 if pos % 8 else pos + 15
    return frozenset(bits)


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


def steer_signals(cmd: Command) -> dict:
    return {'steer_request': 1, 'delta_req': cmd.delta, 'delta_rate_req': cmd.delta_rate}


def torque_signals(cmd: Command) -> dict:
    return {'torque_request': 1, 'torque_req': cmd.drive_torque}


def command_from_signals(status: dict, steer: dict | None, torque: dict | None,
                         stamp: float) -> Command | None:
    """What the car must apply: None unless the bridge is ACTIVE and its request PDUs are valid.

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


__all__ = ['CMD_STATUS', 'CMD_STEER', 'CMD_TORQUE', 'COMMAND_FRAMES', 'COMMAND_SIGNALS', 'Codec',
           'Fault', 'Frame', 'FrameError', 'SENSOR_SIGNALS', 'STATE_SIGNALS', 'VALIDITY_SIGNALS',
           'WHEELS', 'command_from_signals', 'load_description', 'signal_bits',
           'state_from_fields', 'steer_signals', 'torque_signals']
