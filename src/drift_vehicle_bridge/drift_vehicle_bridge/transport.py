"""The transport seam: PDUs to and from the car, over python-can or over UDP (Socket Adaptor).

Every transport has ``send(pdu)``, ``flush()`` (end of a cycle: a datagram transport sends what it
queued), ``recv(timeout) -> Pdu | None`` and ``shutdown()``. Failures are ``OSError`` (or
``can.CanError``); a received datagram or frame that cannot be a PDU is counted, never raised.
"""
from __future__ import annotations

import can

from drift_vehicle_bridge.pdu import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG, Pdu

SEND_TIMEOUT = 0.005    # a full transmit queue must not stall the 10 ms cycle [s]


class CanTransport:
    """PDUs as CAN or CAN FD frames on any python-can bus (the transport owns and closes it)."""

    def __init__(self, bus: can.BusABC):
        self.bus = bus

    def send(self, pdu: Pdu) -> None:
        self.bus.send(can.Message(
            arbitration_id=pdu.id & ~(CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG),
            is_extended_id=bool(pdu.id & CAN_EFF_FLAG), data=pdu.data, is_fd=bool(pdu.fd),
            bitrate_switch=bool(pdu.fd)), timeout=SEND_TIMEOUT)

    def flush(self) -> None:
        """Frames go out as they are sent."""

    def recv(self, timeout: float = 0.0) -> Pdu | None:
        msg = self.bus.recv(timeout=timeout)
        return None if msg is None else pdu_of(msg)

    def shutdown(self) -> None:
        self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


def discard_pending(transport, limit: int) -> int:
    """Read and drop what ``transport`` has queued, at most ``limit`` PDUs (a link that keeps
    failing or babbling must not hold the caller); a bad datagram counts as one. Returns how
    many."""
    n = 0
    while n < limit:
        try:
            if transport.recv(timeout=0.0) is None:
                break
        except (can.CanError, OSError, ValueError):
            pass
        n += 1
    return n


def pdu_of(msg: can.Message) -> Pdu:
    """A received frame as a PDU; extended, remote and error frames keep SocketCAN's flags."""
    can_id = msg.arbitration_id | (CAN_EFF_FLAG if msg.is_extended_id else 0) \
        | (CAN_RTR_FLAG if msg.is_remote_frame else 0) | (CAN_ERR_FLAG if msg.is_error_frame else 0)
    return Pdu(can_id, bytes(msg.data or b'')[:msg.dlc] if not msg.is_remote_frame else b'',
               fd=bool(msg.is_fd), timestamp=msg.timestamp)


def as_transport(link):
    """A transport as given, or a python-can bus wrapped in a CanTransport."""
    return CanTransport(link) if isinstance(link, can.BusABC) else link


def open_transport(params, car_side: bool = False):
    """The transport ``params`` (BridgeParams) names; ``car_side``: the gateway's end of it."""
    if params.transport == 'udp':
        from drift_vehicle_bridge.soad import UdpTransport, parse_endpoint
        udp = params.udp.swapped() if car_side else params.udp
        return UdpTransport(local=parse_endpoint(udp.local), remote=parse_endpoint(udp.remote))
    return CanTransport(can.Bus(**params.bus.kwargs()))


__all__ = ['CanTransport', 'as_transport', 'open_transport', 'pdu_of']
