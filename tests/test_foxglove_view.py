"""The live view: a Foxglove WebSocket client decodes the stack's messages by the advertised schemas.

The view node runs as its own process; a real rclpy publisher in this process plays the car. The
client speaks the SDK's subprotocol (``foxglove.sdk.v1``) with the ``websockets`` package and
decodes with ``mcap_ros2``'s dynamic decoder, from nothing but what the server advertised.
"""
import itertools
import json
import os
import re
import select
import struct
import subprocess
import time

import pytest
from mcap_ros2._dynamic import generate_dynamic

from conftest import PYTHON
from drift_tools.msgdef import message_definition

websockets_sync = pytest.importorskip('websockets.sync.client')

SUBPROTOCOL = 'foxglove.sdk.v1'
TIMEOUT = 20.0                           # every wait below ends by then [s]
_DOMAINS = itertools.cycle(range(160, 170))


@pytest.fixture
def view_env():
    """A child environment on this test's own ROS domain (160..169), localhost discovery."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(next(_DOMAINS)),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    return env


def start_view(env, *params):
    argv = [PYTHON, '-m', 'drift_tools.nodes.foxglove_node', '--ros-args']
    for p in params:
        argv += ['-p', p]
    return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def wait_for_port(proc, deadline) -> int:
    """The port the node logs once it serves (it was started with port 0: any free one)."""
    lines = []
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if ready:
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                break
            lines.append(line)
            found = re.search(r'open connection ws://[^:]+:(\d+)', line)
            if found:
                return int(found.group(1))
    raise AssertionError(f'the view never said its port: {"".join(lines)}')


def wait_until(condition, deadline, what):
    while not condition():
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.02)


class Client:
    """A minimal Foxglove client: remembers advertised channels and collects binary messages."""

    def __init__(self, ws):
        self.ws, self.channels, self.messages, self.times = ws, {}, {}, []
        self._subs, self._ids = {}, itertools.count(1)

    def pump(self, timeout):
        """Read every frame that arrives until none has come for ``timeout`` [s]."""
        while True:
            try:
                frame = self.ws.recv(timeout=timeout)
            except TimeoutError:
                return
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg['op'] == 'advertise':
                    self.channels.update({c['topic']: c for c in msg['channels']})
            elif frame[0] == 1:                          # message data
                sub, log_time = struct.unpack_from('<IQ', frame, 1)
                self.messages.setdefault(self._subs[sub], []).append((log_time, frame[13:]))
            elif frame[0] == 2:                          # the server's time
                self.times.append(struct.unpack_from('<Q', frame, 1)[0])

    def subscribe(self, topic):
        sub = next(self._ids)
        self._subs[sub] = topic
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': sub, 'channelId': self.channels[topic]['id']}]}))

    def decode(self, topic, payload):
        """Decode by the advertised schema alone."""
        channel = self.channels[topic]
        assert (channel['encoding'], channel['schemaEncoding']) == ('cdr', 'ros2msg')
        name = channel['schemaName']
        return generate_dynamic(name, channel['schema'])[name](payload)


def car_state(VehicleState, k):
    """The k-th state of a car circling at 12 m/s, 10 ms apart."""
    msg = VehicleState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 7, k * 10_000_000
    msg.v, msg.beta, msg.r, msg.delta = 12.5, -0.4, 0.8, -0.12
    msg.wheel_speeds = [40.0, 41.0, 42.0, 43.0]
    msg.x, msg.y, msg.yaw = 3.0 + 0.1 * k, -2.0, 1.0
    msg.validity = VehicleState.VALID_ALL
    return msg


@pytest.mark.ros
def test_a_foxglove_client_decodes_live_messages_by_the_advertised_schemas(view_env,
                                                                           monkeypatch):
    import rclpy
    from drift_msgs.msg import VehicleState
    from nav_msgs.msg import Path
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    deadline = time.monotonic() + TIMEOUT
    proc = start_view(view_env, 'port:=0', 'scene_period:=0.01')
    for name in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(name, view_env[name])
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node('fake_car', context=context)
    try:
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        path_pub = node.create_publisher(Path, 'drift/path', latched)
        path = Path(poses=[PoseStamped() for _ in range(30)])
        path.header.frame_id = 'map'
        path_pub.publish(path)      # once, before the view is up: it must come latched
        state_pub = node.create_publisher(VehicleState, 'vehicle/state', 10)
        port = wait_for_port(proc, deadline)
        wait_until(lambda: state_pub.get_subscription_count() > 0
                   and path_pub.get_subscription_count() > 0, deadline, 'the view to subscribe')

        # the server does not always answer a close frame: do not wait long for it
        with websockets_sync.connect(f'ws://127.0.0.1:{port}', subprotocols=[SUBPROTOCOL],
                                     open_timeout=TIMEOUT, close_timeout=1.0) as ws:
            client, sent = Client(ws), {}
            wanted = ('/vehicle/state', '/drift/view/markers', '/drift/view/tf', '/drift/path')
            subscribed = set()
            for k in itertools.count():
                assert time.monotonic() < deadline, (
                    f'timed out: advertised {sorted(client.channels)}, '
                    f'received {sorted(client.messages)}')
                sent[k] = car_state(VehicleState, k)
                state_pub.publish(sent[k])
                client.pump(0.02)
                for topic in set(wanted) - subscribed:
                    if topic in client.channels:
                        client.subscribe(topic)
                        subscribed.add(topic)
                if all(topic in client.messages for topic in wanted):
                    break

        channel = client.channels['/vehicle/state']
        assert channel['schemaName'] == 'drift_msgs/msg/VehicleState'
        assert channel['schema'] == message_definition('drift_msgs/msg/VehicleState')  # the bag's
        state = client.decode('/vehicle/state', client.messages['/vehicle/state'][0][1])
        published = sent[state.header.stamp.nanosec // 10_000_000]
        assert state.header.stamp.sec == 7
        assert (state.v, state.beta, state.r, state.delta) == (12.5, -0.4, 0.8, -0.12)
        assert list(state.wheel_speeds) == [40.0, 41.0, 42.0, 43.0]
        assert (state.x, state.y, state.yaw) == (published.x, published.y, published.yaw)
        assert state.validity == VehicleState.VALID_ALL

        # the car in 3D: its transform and markers where the state put it
        transform = client.decode('/drift/view/tf', client.messages['/drift/view/tf'][0][1])
        drawn = sent[transform.header.stamp.nanosec // 10_000_000]
        assert (transform.transform.translation.x, transform.transform.translation.y) == \
            pytest.approx((drawn.x, drawn.y))
        markers = client.decode('/drift/view/markers', client.messages['/drift/view/markers'][0][1])
        assert {m.ns for m in markers.markers} >= {'car', 'wheels', 'velocity', 'steering'}
        # the path was published once, before this client came: the view hands it on
        assert len(client.decode('/drift/path', client.messages['/drift/path'][0][1]).poses) == 30
        assert client.times, 'the server never announced its time'
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        proc.terminate()
        proc.wait(timeout=10)
    assert proc.returncode == 0


@pytest.mark.ros
def test_a_bad_port_is_one_line(view_env):
    proc = start_view(view_env, 'port:=70000')
    out, _ = proc.communicate(timeout=TIMEOUT)
    assert proc.returncode == 1
    assert out.strip().count('\n') == 0 and 'port must be in 0..65535' in out
