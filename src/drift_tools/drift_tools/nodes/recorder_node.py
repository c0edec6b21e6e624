"""Records every stack topic, as serialized CDR, into a rosbag2 MCAP directory."""
import importlib
import json
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header, String

from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import leave_real_time
from drift_control.nodes.spin import run_node
from drift_control.params import ParamError, config_dir
from drift_tools.bag_writer import DEFAULT_CHUNK_SIZE, BagWriter
from drift_tools.disk import MIB, DiskLevel, DiskLimits, DiskWatch
from drift_tools.recording import KEPT_TOPICS, STACK_NAMESPACES, STACK_TOPICS, TopicSelector
from drift_tools.run_info import RECORD_NAME


DISK_PARAMS = ('disk_warn_free_mb', 'disk_warn_minutes', 'disk_stop_free_mb')   # run-time


def message_class(msgtype: str):
    """``pkg/msg/Name`` -> the generated Python class."""
    pkg, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


# messages a subscription holds while the node is busy (a chunk compressed, a stall): a lock-step
# run sends state at ~800 Hz of wall time, where 100 would last 0.12 s
QUEUE_DEPTH = 10_000


def make_qos(reliable: bool, latched: bool) -> QoSProfile:
    """Deep keep-last queue; reliability and durability as given."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=QUEUE_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class RecorderNode(Node):
    """Subscribes raw to the stack's topics (and new ones under its namespaces) and writes them.

    The stack's own topics are subscribed at once with the types and QoS the stack uses; polling
    the graph adds new topics and re-subscribes where publishers offer a weaker QoS (as rosbag2).
    Log times come from the node's clock: sim time under ``use_sim_time`` (a lock-step run), as
    ``ros2 bag record --use-sim-time``. ``run_info_file`` (JSON, from run_stack) becomes the bag's
    ``drift_run`` metadata record.
    Its health is on ``/diagnostics`` once per ``health_period``: disk space (a warning before
    it runs out, a clean stop just before) and write failures. A recording that stopped early
    keeps the node alive, reporting, and makes it exit 1 at the end.
    """

    def __init__(self):
        super().__init__('recorder')
        leave_real_time()   # never hold a core against the control loop (a launch under chrt)
        self.declare_parameter('config_dir', str(config_dir()))
        self.declare_parameter('scenario', '')
        bag_dir = self.declare_parameter('bag_dir', '').value
        namespaces = self.declare_parameter('namespaces', list(STACK_NAMESPACES)).value
        extra = self.declare_parameter('extra_topics', ['']).value
        period = self.declare_parameter('discovery_period', 1.0).value
        chunk_size = self.declare_parameter('chunk_size', DEFAULT_CHUNK_SIZE).value
        compress = self.declare_parameter('compression', True).value   # zstd, chunk by chunk
        flush_period = self.declare_parameter('flush_period', 1.0).value
        health_period = self.declare_parameter('health_period', 1.0).value
        run_info_file = self.declare_parameter('run_info_file', '').value
        limits = DiskLimits(
            warn_free=self._declare_live('disk_warn_free_mb', 2048.0,
                                         'warn below this much free disk [MiB]') * MIB,
            warn_time_left=self._declare_live('disk_warn_minutes', 10.0,
                                              'warn when the free disk lasts less at the write '
                                              'rate [min]') * 60.0,
            stop_free=self._declare_live('disk_stop_free_mb', 64.0,
                                         'close the bag below this much free disk [MiB]') * MIB)
        if not bag_dir:
            raise ParamError('recorder: parameter bag_dir is required')
        resolve = self.resolve_topic_name
        self._selector = TopicSelector(
            topics=tuple(resolve(t) for t in (*STACK_TOPICS, *extra) if t),
            namespaces=tuple(resolve(ns) for ns in namespaces if ns))
        self._writer = BagWriter(bag_dir, chunk_size=chunk_size, compression=compress)
        if run_info_file:
            self._writer.add_metadata(RECORD_NAME, _load_run_info(run_info_file))
        self._disk = DiskWatch(self._writer.bag_dir, limits)
        self.failure = ''          # why the recording stopped early; '' while it records
        self._dropped = 0          # messages that came after that
        self._warned_at = None
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self._subs = {}        # topic -> (subscription, type, QoS), or None: cannot record
        for topic, (msgtype, latched) in STACK_TOPICS.items():
            self._subscribe(resolve(topic), msgtype,
                            make_qos(True, latched or topic in KEPT_TOPICS))
        # which publishers each subscription is matched with: a lock-step simulator starts the
        # run only once the recorder hears all of them (nothing of the run is lost)
        self._matched_pub = self.create_publisher(String, '/recorder/matched', make_qos(True, True))
        self._matched = None
        # wall-clock timers: under sim time /clock may stand still (a lock-step simulator waits
        # for us), while discovery, flushes and the disk watch must go on
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(flush_period, self._flush, clock=steady)
        self.create_timer(health_period, self._on_health, clock=steady)
        lock_parameters(self, {name: self._disk_setter(name) for name in DISK_PARAMS})
        self.get_logger().info(f'recording to {bag_dir}')

    def _subscribe(self, topic, msgtype, qos):
        try:
            cls = message_class(msgtype)
        except (ImportError, AttributeError, ValueError) as err:
            self.get_logger().warning(f'not recording {topic} ({msgtype}): {err}')
            self._subs[topic] = None
            return
        sub = self.create_subscription(
            cls, topic, lambda data, info, t=topic, m=msgtype: self._on_message(t, m, data, info),
            qos, raw=True)
        self._subs[topic] = (sub, msgtype, qos)

    def _declare_live(self, name: str, default: float, description: str) -> float:
        """A parameter applied while recording (``drift param set``), with its descriptor."""
        descriptor = ParameterDescriptor(
            description=description + ' (applied live)', type=ParameterType.PARAMETER_DOUBLE,
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1e12)])
        return self.declare_parameter(name, default, descriptor).value

    def _disk_setter(self, name: str):
        """``param set`` of one disk threshold: all three validated together, then used."""
        def apply(value):
            v = {n: self.get_parameter(n).value for n in DISK_PARAMS}
            v[name] = value
            try:
                self._disk.limits = DiskLimits(warn_free=v['disk_warn_free_mb'] * MIB,
                                               warn_time_left=v['disk_warn_minutes'] * 60.0,
                                               stop_free=v['disk_stop_free_mb'] * MIB)
            except (TypeError, ValueError) as err:
                raise ParamError(str(err)) from None
            self._warned_at = None       # a new threshold: say at once where we stand
        return apply

    def _on_message(self, topic, msgtype, data, info=None):
        if self.failure:
            self._dropped += 1
            return
        try:
            if topic not in self._writer.topics:       # the bag lists only topics that had data
                qos = self._subs[topic][2]
                self._writer.add_topic(
                    topic, msgtype, reliable=qos.reliability == ReliabilityPolicy.RELIABLE,
                    latched=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL)
                self.get_logger().info(f'recording {topic} [{msgtype}]')
            # publish time: the publisher's wall clock at publish (DDS source timestamp), so a
            # path's latency can be read without this node's own delays (scripts/latency.py)
            self._writer.write(topic, data, self.get_clock().now().nanoseconds,
                               (info or {}).get('source_timestamp') or None)
        except OSError as err:
            self._stop_recording(f'write failed: {err.strerror or err}')

    def _flush(self):
        if self.failure:
            return
        try:
            self._writer.flush()
        except OSError as err:
            self._stop_recording(f'write failed: {err.strerror or err}')

    def _stop_recording(self, reason: str) -> None:
        """End the bag early: closed with its summary if the disk lets us, else as flushed."""
        self.failure = reason
        try:
            self._writer.close()
        except OSError:
            self._writer.abandon()
            reason += '; bag left unfinished (scripts/bag.py recover)'
        self.get_logger().error(f'recording stopped: {reason}; the bag keeps what came before')

    def _on_health(self):
        now = time.monotonic()
        disk = self._disk.check(self._writer.bytes_written, now)
        if not self.failure and disk.level == DiskLevel.STOP:
            self._stop_recording(disk.message)
        elif disk.level == DiskLevel.WARN and (self._warned_at is None
                                               or now - self._warned_at > 60.0):
            self._warned_at = now
            self.get_logger().warning(disk.message)
        status = DiagnosticStatus(name='recorder', hardware_id=str(self._writer.bag_dir))
        if self.failure:
            status.level = DiagnosticStatus.ERROR
            status.message = f'not recording: {self.failure}'
        else:
            status.level = DiagnosticStatus.WARN if disk.level else DiagnosticStatus.OK
            status.message = f'recording; {disk.message}'
        values = {'messages': sum(self._writer.counts().values()), 'dropped': self._dropped,
                  'bytes': self._writer.bytes_written, 'free_bytes': disk.free,
                  'time_left_s': f'{disk.time_left:.0f}'}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        self._diag_pub.publish(DiagnosticArray(
            header=Header(stamp=self.get_clock().now().to_msg()), status=[status]))


    def _discover(self):
        self._rediscover()
        matched = {topic: entry[0].get_publisher_count()
                   for topic, entry in self._subs.items() if entry is not None}
        if matched != self._matched:
            self._matched = matched
            self._matched_pub.publish(String(data=json.dumps(matched, sort_keys=True)))

    def _rediscover(self):
        for topic, msgtype in self._selector.select(self.get_topic_names_and_types()):
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs or self._subs.get(topic, ()) is None:
                continue
            qos = make_qos(
                all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs),
                all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs))
            current = self._subs.get(topic)
            if current is not None:
                sub, old_type, old_qos = current
                if (old_type, old_qos.reliability, old_qos.durability) == \
                        (msgtype, qos.reliability, qos.durability):
                    continue
                if old_type != msgtype and topic in self._writer.topics:
                    self.get_logger().warning(f'{topic} changed type to {msgtype}: ignored')
                    continue
                self.destroy_subscription(sub)
            self._subscribe(topic, msgtype, qos)
            self.get_logger().info(f'subscribed to {topic} [{msgtype}], {qos.reliability.name} '
                                   f'{qos.durability.name}')

    def close(self):
        """Write the bag's summary and final metadata; ``exit_code`` 1 if recording failed."""
        if not self.failure:
            try:
                self._writer.close()
            except OSError as err:
                self._writer.abandon()
                self.failure = f'closing the bag failed: {err.strerror or err}'
        if self.failure:
            self.exit_code = 1
            self.get_logger().error(f'recording incomplete: {self.failure}; '
                                    f'{self._dropped} messages not recorded')


def _load_run_info(path) -> dict:
    try:
        with open(path, encoding='utf-8') as fh:
            info = json.load(fh)
    except (OSError, ValueError) as err:
        raise ParamError(f'recorder: run_info_file {path}: {err}') from None
    if not isinstance(info, dict):
        raise ParamError(f'recorder: run_info_file {path}: expected a JSON object')
    return info


def main(args=None) -> int:
    return run_node(RecorderNode, 'recorder', args)


if __name__ == '__main__':
    sys.exit(main())
