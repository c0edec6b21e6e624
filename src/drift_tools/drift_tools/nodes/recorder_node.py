"""Records every stack topic, as serialized CDR, into a rosbag2 MCAP directory."""
import importlib
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from drift_control.params import config_dir
from drift_tools.bag_writer import DEFAULT_CHUNK_SIZE, BagWriter
from drift_tools.recording import STACK_NAMESPACES, STACK_TOPICS, TopicSelector


def message_class(msgtype: str):
    """``pkg/msg/Name`` -> the generated Python class."""
    pkg, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


class RecorderNode(Node):
    """Subscribes (raw) to the stack's topics as their publishers appear and writes them."""

    def __init__(self):
        super().__init__('recorder')
        self.declare_parameter('config_dir', str(config_dir()))
        self.declare_parameter('scenario', '')
        bag_dir = self.declare_parameter('bag_dir', '').value
        namespaces = self.declare_parameter('namespaces', list(STACK_NAMESPACES)).value
        extra = self.declare_parameter('extra_topics', ['']).value
        period = self.declare_parameter('discovery_period', 1.0).value
        chunk_size = self.declare_parameter('chunk_size', DEFAULT_CHUNK_SIZE).value
        flush_period = self.declare_parameter('flush_period', 1.0).value
        if not bag_dir:
            raise ValueError('recorder: parameter bag_dir is required')
        resolve = self.resolve_topic_name
        self._selector = TopicSelector(
            topics=tuple(resolve(t) for t in (*STACK_TOPICS, *extra) if t),
            namespaces=tuple(resolve(ns) for ns in namespaces if ns))
        self._writer = BagWriter(bag_dir, chunk_size=chunk_size)
        self._subs = {}
        self.create_timer(period, self._discover)
        self.create_timer(flush_period, self._writer.flush)
        self._discover()
        self.get_logger().info(f'recording to {bag_dir}')

    def _discover(self):
        for topic, msgtype in self._selector.select(self.get_topic_names_and_types()):
            if topic in self._subs:
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs:
                continue
            try:
                cls = message_class(msgtype)
                self._writer.add_topic(topic, msgtype, type_hash=str(pubs[0].topic_type_hash))
            except (ImportError, AttributeError, LookupError, ValueError) as err:
                self.get_logger().warning(f'not recording {topic} ({msgtype}): {err}')
                self._subs[topic] = None
                continue
            self._subs[topic] = self.create_subscription(
                cls, topic, lambda data, t=topic: self._writer.write(t, data, time.time_ns()),
                self._qos_for(pubs), raw=True)
            self.get_logger().info(f'recording {topic} [{msgtype}]')

    @staticmethod
    def _qos_for(pubs) -> QoSProfile:
        """Match the publishers, as rosbag2 does: reliable/transient only if all offer it."""
        reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
        latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

    def close(self):
        """Write the bag's summary and final metadata."""
        self._writer.close()


def main(args=None):
    rclpy.init(args=args)
    node = RecorderNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
