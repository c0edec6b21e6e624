"""Bus descriptions: which PDUs the interface has, their bit layout and their E2E protection.

A DBC (classic CAN or CAN FD, ``dbc.py``) and a FlexRay ARXML (``arxml.py``) describe the same
interface; both load into a ``Description`` that the one codec serves. The signal names are the
contract, whatever PDU carries them (``STATE_SIGNALS``); the command PDUs are always
DS_CMD_STEER, DS_CMD_TORQUE and DS_CMD_STATUS.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from drift_control.signals import Validity
from drift_vehicle_bridge.e2e import E2EConfig

WHEELS = ('omega_FL', 'omega_FR', 'omega_RL', 'omega_RR')   # order of VehicleState.wheel_speeds

# State signal -> VehicleState field (wheel speeds go to wheel_speeds[i]).
STATE_SIGNALS: dict[str, str] = {
    'vx': 'vx', 'vy': 'vy', 'V': 'V', 'r': 'r', 'beta': 'beta', 'ax': 'ax', 'ay': 'ay',
    **{w: w for w in WHEELS}, 'delta': 'delta', 'steering_torque': 'steering_torque',
    'drive_torque': 'drive_torque', 'brake_pedal': 'brake_pedal', 'x': 'x', 'y': 'y',
    'yaw': 'yaw'}

# Which signals each validity bit needs: the bit is set while every PDU carrying one is valid.
VALIDITY_SIGNALS: dict[Validity, tuple[str, ...]] = {
    Validity.V: ('V',),
    Validity.VX_VY: ('vx', 'vy'),
    Validity.BETA: ('beta',),
    Validity.R: ('r',),
    Validity.AX_AY: ('ax', 'ay'),
    Validity.WHEEL_SPEEDS: WHEELS,
    Validity.DELTA: ('delta',),
    Validity.STEERING_TORQUE: ('steering_torque',),
    Validity.DRIVE_TORQUE: ('drive_torque',),
    Validity.BRAKE_PEDAL: ('brake_pedal',),
    Validity.POSE: ('x', 'y', 'yaw'),
}

# Sensor mode: each sensor unit's signals in the order of drift_control.estimator.FIELDS[unit],
# what the bridge hands the state estimator as one sample. The INS's yaw rate is ``r``, the car's
# own inertial sensor's ``r_imu`` (biased, not compensated).
SENSOR_SIGNALS: dict[str, tuple[str, ...]] = {
    'ins': ('V', 'beta', 'r', 'x', 'y', 'yaw'),
    'imu': ('ax', 'ay', 'r_imu'),
    'wheels': WHEELS,
    'steering': ('delta', 'steering_torque'),
    'torque': ('drive_torque',),
}

CMD_STEER = 'DS_CMD_STEER'
CMD_TORQUE = 'DS_CMD_TORQUE'
CMD_STATUS = 'DS_CMD_STATUS'
COMMAND_SIGNALS: dict[str, tuple[str, ...]] = {
    CMD_STEER: ('steer_request', 'delta_req', 'delta_rate_req'),
    CMD_TORQUE: ('torque_request', 'torque_req'),
    CMD_STATUS: ('bridge_mode', 'drop_reason'),
}
COMMAND_FRAMES = tuple(COMMAND_SIGNALS)
STATE_SENDER, COMMAND_SENDER = 'GATEWAY', 'DRIFT_STACK'


@dataclass(frozen=True)
class PduSpec:
    """One PDU of a description.

    Attributes
    ----------
    name : str
        PDU (or CAN message) name, e.g. ``DS_VELOCITY``.
    id : int
        Transport id: the CAN id (DBC) or the Socket Adaptor header ID (ARXML).
    length : int
        Payload length [bytes].
    message : cantools.database.can.Message
        The payload's bit layout; cantools packs and unpacks it.
    e2e : E2EConfig
        The E2E profile and data ID protecting it.
    senders : tuple of str
        ``GATEWAY`` (vehicle state) or ``DRIFT_STACK`` (commands).
    cycle : float
        Transmission period [s].
    fd : bool or None
        CAN descriptions: whether it is a CAN FD frame; None for PDUs without a CAN frame format.
    bus : dict
        Further facts of the description for docs and the probe (FlexRay slot, cycle, frame).
    """

    name: str
    id: int
    length: int
    message: object
    e2e: E2EConfig
    senders: tuple[str, ...]
    cycle: float = 0.01
    fd: bool | None = None
    bus: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Description:
    """The PDUs of one bus description (``kind``: ``can``, ``canfd`` or ``flexray``)."""

    source: str
    kind: str
    pdus: tuple[PduSpec, ...]


__all__ = ['CMD_STATUS', 'CMD_STEER', 'CMD_TORQUE', 'COMMAND_FRAMES', 'COMMAND_SENDER',
           'COMMAND_SIGNALS', 'Description', 'PduSpec', 'SENSOR_SIGNALS', 'STATE_SENDER',
           'STATE_SIGNALS', 'VALIDITY_SIGNALS', 'WHEELS']
