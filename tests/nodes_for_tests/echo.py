"""Test node: sends every DriftReference from ``ping`` straight back on ``pong``."""
import rclpy
from drift_msgs.msg import DriftReference
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


class Echo(Node):
    def __init__(self):
        super().__init__('echo')
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(DriftReference, 'pong', qos)
        self.create_subscription(DriftReference, 'ping', self.pub.publish, qos)


def main(args=None):
    rclpy.init(args=args)
    node = Echo()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
