"""Test node: sends every DriftReference from ``ping`` straight back on ``pong``."""
import sys

from drift_msgs.msg import DriftReference
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from drift_control.nodes.spin import run_node


class Echo(Node):
    def __init__(self):
        super().__init__('echo')
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(DriftReference, 'pong', qos)
        self.create_subscription(DriftReference, 'ping', self.pub.publish, qos)


if __name__ == '__main__':
    sys.exit(run_node(Echo, 'echo'))
