"""DBC bus descriptions (classic CAN or CAN FD) as a ``Description``; E2E from attributes."""
from __future__ import annotations

import os

import cantools

from drift_control.params import ParamError
from drift_vehicle_bridge.description import Description, PduSpec
from drift_vehicle_bridge.e2e import E2EConfig
from drift_vehicle_bridge.pdu import CAN_EFF_FLAG

DEFAULT_PROFILE = 'P01'    # a DBC without an E2E_Profile attribute


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


__all__ = ['DEFAULT_PROFILE', 'load_dbc']
