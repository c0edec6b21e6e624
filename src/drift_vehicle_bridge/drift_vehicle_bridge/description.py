"""Bus descriptions: which PDUs the interface has, their bit layout and their E2E protection.

A DBC (classic CAN or CAN FD) and a FlexRay ARXML describe the same interface; both load into a
``Description`` that the one codec serves. The signal names are the contract, whatever PDU carries
them (``codec.STATE_SIGNALS``); the command PDUs are always DS_CMD_STEER, DS_CMD_TORQUE and
DS_CMD_STATUS.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cantools

from drift_control.params import ParamError
from drift_vehicle_bridge.e2e import E2EConfig
from drift_vehicle_bridge.pdu import CAN_EFF_FLAG

DEFAULT_PROFILE = 'P01'    # a DBC without an E2E_Profile attribute


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


def load_description(path: str | os.PathLike) -> Description:
    """Read a ``.dbc`` or ``.arxml`` file; ParamError (one line) when it cannot serve the codec."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == '.dbc':
        return load_dbc(path)
    if suffix == '.arxml':
        from drift_vehicle_bridge.arxml import load_arxml
        return load_arxml(path)
    raise ParamError(f'{path}: unknown bus description type {suffix!r} (.dbc or .arxml)')


def load_dbc(path: str | os.PathLike) -> Description:
    """A DBC's messages as PDUs; E2E from the ``E2E_Profile`` / ``E2E_DataID`` attributes."""
    try:
        db = cantools.database.load_file(str(path), database_format='dbc', strict=True)
    except (OSError, cantools.database.UnsupportedDatabaseFormatError) as err:
        raise ParamError(f'{path}: cannot read the DBC: {_one_line(err)}') from None
    pdus = []
    for m in db.messages:
        profile = str(_attribute(db, m, 'E2E_Profile', DEFAULT_PROFILE))
        data_id = _attribute(db, m, 'E2E_DataID', 0)
        cycle_ms = m.cycle_time or _attribute(db, m, 'GenMsgCycleTime', 0)
        if not cycle_ms:
            raise ParamError(f'{path}: {m.name} has no cycle time (GenMsgCycleTime)')
        pdus.append(PduSpec(
            name=m.name, id=m.frame_id | (CAN_EFF_FLAG if m.is_extended_frame else 0),
            length=m.length, message=m,
            e2e=E2EConfig(profile=profile, data_id=int(data_id),
                          offset=int(_attribute(db, m, 'E2E_Offset', 0))),
            senders=tuple(m.senders), cycle=cycle_ms / 1000.0, fd=bool(m.is_fd)))
    kind = 'canfd' if any(p.fd for p in pdus) else 'can'
    return Description(str(path), kind, tuple(pdus))


def _attribute(db, message, name: str, default):
    """A message attribute, else the DBC's default for it, else ``default``."""
    attr = message.dbc.attributes.get(name) if message.dbc else None
    if attr is not None:
        return attr.value
    definition = (db.dbc.attribute_definitions.get(name) if db.dbc else None)
    if definition is not None and definition.default_value is not None:
        return definition.default_value
    return default


def _one_line(err: Exception) -> str:
    return ' '.join(str(err).split())


__all__ = ['DEFAULT_PROFILE', 'Description', 'PduSpec', 'load_dbc', 'load_description']
