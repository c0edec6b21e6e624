"""PDUs over UDP as an AUTOSAR Socket Adaptor with the PDU header option frames them.

Wire format (AUTOSAR SWS Socket Adaptor, "PDU header option"): per PDU a big-endian uint32 header
ID, a big-endian uint32 payload length, then the payload; several PDUs follow each other in one
UDP datagram. Checked against Wireshark's dissector for it, ``epan/dissectors/
packet-pdu-transport.c`` (wireshark/wireshark at 057436ff81dc): ``dissect_pdu_transport`` reads
the ID at offset 0 and the length at offset 4 with ``ENC_BIG_ENDIAN``, the payload from offset 8;
``get_pdu_transport_message_len`` = 8 + length; ``udp_dissect_pdus`` (packet-udp.c) repeats that
to the end of the datagram. Wireshark flags a payload running past the datagram's end
("PDU Transport Truncated message!", PI_MALFORMED) and shows fewer than 8 trailing bytes as a
malformed header; a length of 0 is an ordinary 8-byte PDU there.

Malformed datagrams: :func:`unpack` raises :class:`DatagramError` (a ValueError) naming the fault
('truncated_header': 1..7 bytes left after the last whole PDU; 'length_past_end': a header whose
length runs past the datagram's end) and carries the whole PDUs before it: each was delimited by
its own header, as Wireshark dissects them too, and the E2E check above judges their contents.
A zero-length PDU is well formed on the wire and handed over with ``data=b''``; no PDU of a
description is empty, so the receiver's length check rejects it by name. :class:`UdpTransport`
never raises on what arrives: it counts each fault in ``errors`` and goes on.
"""
from __future__ import annotations

import ipaddress
import logging
import select
import socket
import struct
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable

from drift_control.params import ParamError
from drift_vehicle_bridge.pdu import Pdu

log = logging.getLogger(__name__)

HEADER = struct.Struct('>II')     # header ID, payload length [bytes]
MAX_ID = 0xFFFFFFFF
# Largest datagram sent without IP fragmentation on a 1500-byte Ethernet MTU (automotive
# Ethernet's too): MTU - IP header (IPv4 20, IPv6 40) - UDP header 8.
MAX_DATAGRAM = {socket.AF_INET: 1472, socket.AF_INET6: 1452}
MAX_UDP_PAYLOAD = 65507           # IPv4: 65535 - 20 - 8; a bigger PDU cannot be sent at all
MAX_DATAGRAMS_PER_RECV = 1000     # a flood of garbage must not hold one recv() forever


class DatagramError(ValueError):
    """A datagram that does not split into whole PDUs.

    Attributes
    ----------
    reason : str
        'truncated_header' or 'length_past_end' (the key counted in ``UdpTransport.errors``).
    offset : int
        Byte offset of the faulty PDU header in the datagram.
    pdus : list of Pdu
        The whole PDUs before the fault, in order.
    """

    def __init__(self, reason: str, offset: int, detail: str, pdus: list[Pdu]):
        super().__init__(f'{reason.replace("_", " ")} at byte {offset}: {detail}')
        self.reason, self.offset, self.pdus = reason, offset, pdus


def pack(pdus: Iterable[Pdu]) -> bytes:
    """One datagram's payload: each PDU's header (ID, length) and payload, in order.

    Raises ValueError for a header ID outside 0..2**32-1.
    """
    parts = []
    for pdu in pdus:
        if not 0 <= pdu.id <= MAX_ID:
            raise ValueError(f'PDU header ID {pdu.id:#x} does not fit in 32 bits')
        parts += (HEADER.pack(pdu.id, len(pdu.data)), bytes(pdu.data))
    return b''.join(parts)


def unpack(datagram: bytes, timestamp: float = 0.0) -> list[Pdu]:
    """The PDUs of one datagram, in order, each with ``timestamp`` [s] (the datagram's arrival).

    An empty datagram holds no PDUs. Raises :class:`DatagramError` for a truncated header or a
    length past the end (see the module docstring); its ``pdus`` are the whole ones before it.
    """
    view = memoryview(datagram)
    pdus: list[Pdu] = []
    offset, end = 0, len(view)
    while offset < end:
        if end - offset < HEADER.size:
            raise DatagramError('truncated_header', offset,
                                f'{end - offset} of {HEADER.size} header bytes', pdus)
        pdu_id, length = HEADER.unpack_from(view, offset)
        start = offset + HEADER.size
        if length > end - start:
            raise DatagramError('length_past_end', offset,
                                f'PDU {pdu_id:#x} says {length} bytes, {end - start} left', pdus)
        pdus.append(Pdu(pdu_id, bytes(view[start:start + length]), timestamp=timestamp))
        offset = start + length
    return pdus


def parse_endpoint(text: str, key: str = 'endpoint') -> tuple[str, int]:
    """``'host:port'`` (IPv6 as ``'[::1]:30501'``) from a config file -> (host, port).

    Raises ParamError, one line naming ``key``, for anything else.
    """
    if not isinstance(text, str):
        raise ParamError(f'{key}: expected "host:port", got {type(text).__name__} {text!r}')
    host, sep, port = text.strip().rpartition(':')
    if host.startswith('[') and host.endswith(']'):
        host = host[1:-1]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ParamError(f'{key}: {text!r} has no IPv6 address inside [...]') from None
    elif ':' in host:
        raise ParamError(f'{key}: {text!r}: write an IPv6 address as [addr]:port')
    if not (sep and host and port.isascii() and port.isdigit() and int(port) <= 65535):
        raise ParamError(f'{key}: expected "host:port" with a port 0..65535, got {text!r}')
    return host, int(port)


class UdpTransport:
    """PDUs to and from one remote endpoint (the car's Ethernet gateway) over unicast UDP.

    ``send`` queues, ``flush`` sends the queue as one datagram (more only where it would exceed
    ``max_datagram``: the bridge flushes once per cycle, the way a gateway bundles its PDUs),
    ``recv`` hands over the PDUs of each received datagram in order. Only datagrams from
    ``remote`` (address and port, as a Socket Adaptor connection with a fixed remote address
    accepts them) are read; others are counted in ``errors['foreign_sender']``.

    Parameters
    ----------
    local : (str, int)
        Address and port to bind; port 0 takes an ephemeral one (see ``local_address``).
    remote : (str, int)
        The gateway's address and port: where datagrams go and the only sender accepted.
    clock : callable, optional
        Reception time source for ``Pdu.timestamp`` [s]; ``time.monotonic`` by default.
    max_datagram : int, optional
        Largest datagram ``flush`` builds [bytes]; by default the most that crosses a
        1500-byte MTU unfragmented. A PDU bigger than that alone goes in its own datagram.

    Attributes
    ----------
    errors : collections.Counter
        'truncated_header', 'length_past_end', 'foreign_sender', 'empty_datagram', 'rx_error',
        'tx_error'.
    sent, received : collections.Counter
        'datagrams' and 'pdus'.
    """

    def __init__(self, local: tuple[str, int], remote: tuple[str, int],
                 clock: Callable[[], float] = time.monotonic, max_datagram: int | None = None):
        family, local_addr = _resolve(local, 'local')
        _, self._remote = _resolve(remote, 'remote', family)
        if self._remote[1] == 0:
            raise ParamError(f'remote endpoint {remote!r}: port 0 cannot be sent to')
        self.max_datagram = MAX_DATAGRAM[family] if max_datagram is None else int(max_datagram)
        if not HEADER.size < self.max_datagram <= MAX_UDP_PAYLOAD:
            raise ParamError(f'max_datagram: {max_datagram} outside {HEADER.size + 1}..'
                             f'{MAX_UDP_PAYLOAD}')
        self._clock = clock
        self._tx: list[Pdu] = []
        self._rx: deque[Pdu] = deque()
        self.errors: Counter = Counter()
        self.sent: Counter = Counter()
        self.received: Counter = Counter()
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.bind(local_addr)
        except OSError:
            self._sock.close()
            raise
        self._sock.setblocking(False)

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound (host, port), with the port the OS picked for port 0."""
        return self._sock.getsockname()[:2]

    @property
    def remote_address(self) -> tuple[str, int]:
        return self._remote[:2]

    def fileno(self) -> int:
        """The socket's descriptor, to wait on several transports with ``select``."""
        return self._sock.fileno()

    def send(self, pdu: Pdu) -> None:
        """Queue ``pdu`` for the next ``flush``; ValueError if it could never be sent."""
        if not 0 <= pdu.id <= MAX_ID:
            raise ValueError(f'PDU header ID {pdu.id:#x} does not fit in 32 bits')
        if HEADER.size + len(pdu.data) > MAX_UDP_PAYLOAD:
            raise ValueError(f'PDU {pdu.id:#x}: {len(pdu.data)} bytes do not fit in a datagram')
        self._tx.append(pdu)

    def flush(self) -> None:
        """Send the queued PDUs, in order, in as few datagrams of ``max_datagram`` as they fit.

        The queue is empty afterwards either way: a command is fresh each cycle and a late one
        is worse than none. A datagram the OS refuses is counted in ``errors['tx_error']``; the
        first such OSError is raised once the rest were tried.
        """
        batches, batch, size = [], [], 0
        for pdu in self._tx:
            n = HEADER.size + len(pdu.data)
            if batch and size + n > self.max_datagram:
                batches.append(batch)
                batch, size = [], 0
            batch.append(pdu)
            size += n
        if batch:
            batches.append(batch)
        self._tx = []
        failure = None
        for batch in batches:
            try:
                self._sock.sendto(pack(batch), self._remote)
            except OSError as err:     # full send buffer, unreachable network...
                self.errors['tx_error'] += 1
                failure = failure or err
                continue
            self.sent['datagrams'] += 1
            self.sent['pdus'] += len(batch)
        if failure is not None:
            raise failure

    def recv(self, timeout: float = 0.0) -> Pdu | None:
        """The next received PDU, waiting up to ``timeout`` [s]; None if none came.

        PDUs left from the last datagram come first. Malformed or foreign datagrams are counted
        in ``errors`` and skipped (the whole PDUs before a fault are still handed over); only a
        failing socket (OSError, e.g. after ``shutdown``) raises.
        """
        if self._rx:
            return self._rx.popleft()
        deadline = time.monotonic() + max(timeout, 0.0)
        for _ in range(MAX_DATAGRAMS_PER_RECV):
            try:
                datagram, sender = self._sock.recvfrom(65536)
            except BlockingIOError:
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return None
                select.select([self._sock], [], [], remaining)
                continue
            except OSError:            # the socket's failure, not the datagram's: say so
                self.errors['rx_error'] += 1
                raise
            self._take(datagram, sender, self._clock())
            if self._rx:
                return self._rx.popleft()
        return None

    def shutdown(self) -> None:
        """Close the socket; queued PDUs are dropped. Safe to call twice."""
        self._tx, self._rx = [], deque()
        self._sock.close()

    def __enter__(self) -> 'UdpTransport':
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()

    def _take(self, datagram: bytes, sender: tuple, now: float) -> None:
        """Queue the PDUs of one datagram from ``sender``, counting what is wrong with it."""
        if sender[:2] != self._remote[:2]:
            self.errors['foreign_sender'] += 1
            return
        self.received['datagrams'] += 1
        if not datagram:
            self.errors['empty_datagram'] += 1
            return
        try:
            pdus = unpack(datagram, now)
        except DatagramError as err:
            self.errors[err.reason] += 1
            log.debug('datagram from %s: %s', sender, err)
            pdus = err.pdus
        self.received['pdus'] += len(pdus)
        self._rx.extend(pdus)


def _resolve(endpoint: tuple[str, int], key: str, family: int = socket.AF_UNSPEC
             ) -> tuple[int, tuple]:
    """(address family, socket address) of a numeric or named (host, port); '' is any address."""
    try:
        host, port = endpoint
        infos = socket.getaddrinfo(host or None, int(port), family, socket.SOCK_DGRAM,
                                   flags=socket.AI_PASSIVE)
    except (TypeError, ValueError, OSError) as err:
        raise ParamError(f'{key} endpoint {endpoint!r}: {err}') from None
    family, _, _, _, address = infos[0]
    return family, address


__all__ = ['DatagramError', 'HEADER', 'MAX_DATAGRAM', 'UdpTransport', 'pack', 'parse_endpoint',
           'unpack']
