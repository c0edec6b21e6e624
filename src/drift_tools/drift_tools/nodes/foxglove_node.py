"""Live view node: the stack's topics and the car in 3D, served to the Foxglove app over WebSocket."""
import sys

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import leave_real_time
from drift_control.nodes.spin import run_node
from drift_control.params import ParamError, config_dir, default_vehicle, load_vehicle
from drift_control.scenario import load_scenario_spec
from drift_tools.car_scene import VIEW_TOPICS, CarScene, CarShape
from drift_tools.foxglove_view import DEFAULT_PORT, FoxgloveView
from drift_tools.nodes.recorder_node import message_class
from drift_tools.recording import STACK_TOPICS

VIEW_CLASSES = {'visualization_msgs/msg/MarkerArray': MarkerArray,
                'geometry_msgs/msg/TransformStamped': TransformStamped}


class FoxgloveNode(Node):
    """Relays the stack's topics raw (CDR) to Foxglove and publishes the car's markers.

    The markers and the body transform go out on ROS too (``drift/view/*``), so a recorder
    running beside the view keeps them in the bag and the same layout shows a recorded run.
    """

    def __init__(self):
        super().__init__('view')
        leave_real_time()   # a viewer never holds a core against the control loop
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        vehicle = self.declare_parameter('vehicle', '').value     # '' = the scenario's
        host = self.declare_parameter('host', '127.0.0.1').value
        port = self.declare_parameter('port', DEFAULT_PORT).value
        track = self.declare_parameter('track', 1.55).value      # the model has none [m]
        period = self.declare_parameter('scene_period', 0.05).value
        arrow_time = self.declare_parameter('velocity_arrow_time', 0.25).value
        if not 0 <= port <= 65535:
            raise ParamError(f'view node: port must be in 0..65535 (0: any free one), got {port}')
        if not vehicle:
            vehicle = (load_scenario_spec(scenario, config=cfg).vehicle if scenario
                       else default_vehicle(cfg))
        shape = CarShape.from_vehicle(load_vehicle(vehicle, cfg), track)
        self._scene = CarScene(shape, period, arrow_time)
        resolve = self.resolve_topic_name
        self._view_pubs = {topic: (resolve(topic), msgtype, self.create_publisher(
            VIEW_CLASSES[msgtype], topic, 10)) for topic, msgtype in VIEW_TOPICS.items()}
        latched = [resolve(t) for t, (_, is_latched) in STACK_TOPICS.items() if is_latched]
        try:
            self._view = FoxgloveView(host, port, latched=latched)
        except RuntimeError as err:
            raise ParamError(f'view node: cannot serve on {host}:{port}: {err}') from None
        self._names = {topic: resolve(topic) for topic in STACK_TOPICS}
        self._warned, self._rejected = set(), 0
        for topic, (msgtype, is_latched) in STACK_TOPICS.items():
            # best effort takes any publisher; a latched topic needs its publisher's durability
            qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
            if is_latched:
                qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.create_subscription(
                message_class(msgtype), topic,
                lambda data, t=topic, m=msgtype: self._on_message(t, m, data), qos, raw=True)
        lock_parameters(self)
        self.get_logger().info(f'the stack and the {vehicle} car in Foxglove: open connection '
                               f'{self._view.url}')

    def _on_message(self, topic, msgtype, data):
        now = self.get_clock().now().nanoseconds
        name = self._names[topic]
        if not self._view.log(name, msgtype, data, now) and name not in self._warned:
            self._warned.add(name)
            self.get_logger().warning(f'not serving {name}: {self._view.unserved.get(name)}')
        for out_topic, payload in self._scene.offer(topic, data):
            out_name, out_type, pub = self._view_pubs[out_topic]
            pub.publish(payload)
            self._view.log(out_name, out_type, payload, now)
        if self._scene.rejected > self._rejected:
            self._rejected = self._scene.rejected
            self.get_logger().warning(f'{self._rejected} message(s) not drawn; last: '
                                      f'{self._scene.last_error}', throttle_duration_sec=10.0)
        self._view.set_time(now)

    def close(self):
        """Stop the WebSocket server."""
        self._view.close()


def main(args=None) -> int:
    return run_node(FoxgloveNode, 'view', args)


if __name__ == '__main__':
    sys.exit(main())
