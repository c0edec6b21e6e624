"""A Foxglove WebSocket server relaying ROS 2 messages as CDR with their bags' ``ros2msg`` schemas.

Built on ``foxglove-sdk`` (module ``foxglove``): one channel per topic, opened at its first
message with the schema ``drift_tools.msgdef`` writes into every bag, so the Foxglove app
decodes a live run and a recorded one alike. The WebSocket protocol has no latching: the last
message of a latched topic (the path) is logged again whenever a client subscribes to it.
The server announces its clock (the ROS time of the messages, sim time in a lock-step run), so
the app's time and plots follow that clock rather than the wall clock.
"""
from __future__ import annotations

import logging
import threading

import foxglove
from foxglove import Capability, Channel, Context, Schema
from foxglove.websocket import ServerListener

from drift_tools.msgdef import MsgDefError, message_definition

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
TIME_STEP_NS = 20_000_000      # announce the clock at most every 20 ms of it
TIME_JUMP_NS = 1_000_000_000   # a clock running back by more than 1 s is a new run


class _Subscriptions(ServerListener):
    """Forwards the SDK's subscribe events (called on the server's own thread)."""

    def __init__(self, on_subscribe):
        self._on_subscribe = on_subscribe

    def on_subscribe(self, client, channel) -> None:
        self._on_subscribe(channel.topic)


class FoxgloveView:
    """The server and its channels.

    Parameters
    ----------
    host : str
        Address to listen on: ``127.0.0.1`` for this machine only, ``0.0.0.0`` for every
        interface.
    port : int
        TCP port; 0 picks a free one (see ``port``).
    latched : iterable of str
        Topics whose last message a new subscriber gets at once.
    name : str
        The server name the app shows.

    Raises
    ------
    RuntimeError
        If the server cannot listen there (the port is taken).
    """

    def __init__(self, host: str = '127.0.0.1', port: int = DEFAULT_PORT, latched=(),
                 name: str = 'drift stack'):
        self.host = host
        self._context = Context()      # our own: channels of another view never mix in
        self._channels = {}            # topic -> Channel
        self.unserved = {}             # topic -> why it has no channel
        self._latched = frozenset(latched)
        self._last = {}                # latched topic -> (payload, log time [ns])
        self._lock = threading.Lock()  # the server thread reads _channels and _last
        self._time = self._announced = None
        self._server = foxglove.start_server(
            name=name, host=host, port=port, context=self._context,
            capabilities=[Capability.Time], supported_encodings=['cdr'],
            server_listener=_Subscriptions(self._replay_latched))

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return self._server.port

    @property
    def url(self) -> str:
        """``ws://host:port`` for the app's "Open connection" (localhost for any interface)."""
        host = 'localhost' if self.host in ('0.0.0.0', '::', '127.0.0.1') else self.host
        return f'ws://{host}:{self.port}'

    def log(self, topic: str, msgtype: str, data: bytes, log_time: int) -> bool:
        """Send one CDR message of ``msgtype`` (``pkg/msg/Name``) on ``topic``.

        ``log_time`` [ns] is the time the app files it under. Returns False when the topic
        cannot be served (no ``.msg`` definition of its type: the reason is in ``unserved``).
        """
        channel = self._channels.get(topic) or self._open(topic, msgtype)
        if channel is None:
            return False
        if topic in self._latched:
            with self._lock:
                self._last[topic] = (data, log_time)
        channel.log(data, log_time=log_time)
        return True

    def _open(self, topic: str, msgtype: str) -> Channel | None:
        if topic in self.unserved:
            return None
        try:
            schema = Schema(name=msgtype, encoding='ros2msg',
                            data=message_definition(msgtype).encode())
        except MsgDefError as err:
            self.unserved[topic] = str(err)
            return None
        channel = Channel(topic, schema=schema, message_encoding='cdr', context=self._context)
        with self._lock:
            self._channels[topic] = channel
        return channel

    def _replay_latched(self, topic: str) -> None:
        with self._lock:
            channel, last = self._channels.get(topic), self._last.get(topic)
        if channel is not None and last is not None:
            # to every subscriber: the SDK cannot address one client; a repeat is harmless
            channel.log(last[0], log_time=last[1])

    def set_time(self, now: int) -> None:
        """Announce the clock, ``now`` [ns]; a jump back starts a new session in the app."""
        if self._time is not None and now < self._time - TIME_JUMP_NS:
            self._server.clear_session()
            self._announced = None
        self._time = now
        if self._announced is None or not 0 <= now - self._announced < TIME_STEP_NS:
            self._announced = now
            self._server.broadcast_time(now)

    def close(self) -> None:
        """Stop the server (clients are disconnected)."""
        self._server.stop()
