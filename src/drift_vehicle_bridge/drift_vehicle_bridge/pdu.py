"""One protocol data unit as the transports hand it over: an id and a payload, no bus details."""
from __future__ import annotations

from dataclasses import dataclass

# SocketCAN's can_id flags: an extended, remote or error frame never equals an 11-bit id.
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000


@dataclass(frozen=True, slots=True)
class Pdu:
    """A received or outgoing PDU.

    Attributes
    ----------
    id : int
        CAN: the SocketCAN-style ``can_id`` (11- or 29-bit identifier with the EFF/RTR/ERR flags);
        PDUs over UDP: the Socket Adaptor header ID.
    data : bytes
        The payload.
    fd : bool or None
        CAN FD frame format; None where the transport carries no frame format (PDUs over UDP).
    timestamp : float
        Reception time from the transport, when it knows one [s].
    """

    id: int
    data: bytes
    fd: bool | None = None
    timestamp: float = 0.0


__all__ = ['CAN_EFF_FLAG', 'CAN_ERR_FLAG', 'CAN_RTR_FLAG', 'Pdu']
