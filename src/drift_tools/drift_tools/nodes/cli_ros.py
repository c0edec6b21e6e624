"""The ROS side of the operator CLI (``drift_tools.operator``): one short-lived rclpy node per
command for topics, services, parameters and the vehicle bridge."""
from __future__ import annotations

import os
import time
from collections import deque

import yaml

from drift_tools.dds import use_udp_here
from drift_tools.operator import CliError, absolute, fill, interface_class, parse_yaml, to_plain

BRIDGE_ARM = '/bridge/arm'


# --- the ROS side -----------------------------------------------------------------------------

class Ros:
    """One short-lived node for a command; discovery waits are condition-based."""

    def __init__(self):
        use_udp_here()
        import rclpy
        from rclpy.signals import SignalHandlerOptions
        self.rclpy = rclpy
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f'drift_cli_{os.getpid()}')

    def close(self):
        self.node.destroy_node()
        self.rclpy.try_shutdown()

    def spin_until(self, cond, timeout: float, step: float = 0.05) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() >= deadline:
                return False
            self.rclpy.spin_once(self.node, timeout_sec=step)
        return True

    def wait_publishers(self, topic: str, timeout: float):
        """(type, publishers' info) of ``topic`` once it has a publisher."""
        found = {}

        def ready():
            types = dict(self.node.get_topic_names_and_types()).get(topic)
            pubs = self.node.get_publishers_info_by_topic(topic)
            if types and pubs:
                found['v'] = (types[0], pubs)
            return bool(found)
        if not self.spin_until(ready, timeout, 0.1):
            raise CliError(f'no publisher on {topic} within {timeout:g} s')
        return found['v']

    def call(self, service: str, srv_type: str | None, request: dict, timeout: float):
        """Call ``service`` (its type from the graph when not given); returns the response."""
        service = absolute(service)
        if srv_type is None:
            types = {}
            if not self.spin_until(lambda: types.update(
                    dict(self.node.get_service_names_and_types())) or service in types,
                    timeout, 0.1):
                raise CliError(f'no service {service} within {timeout:g} s')
            srv_type = types[service][0]
        cls = interface_class(srv_type, 'srv')
        client = self.node.create_client(cls, service)
        if not self.spin_until(client.service_is_ready, timeout, 0.1):
            raise CliError(f'no service {service} within {timeout:g} s')
        future = client.call_async(fill(cls.Request(), request))
        if not self.spin_until(future.done, timeout, 0.02):
            raise CliError(f'{service}: no response within {timeout:g} s')
        return future.result()


def matching_qos(pubs, topic: str = ''):
    """Reliable only if every publisher is; transient-local only if every publisher is and
    ``topic`` is not one of the loop's kept topics (their history is for a recorder matched late:
    echo and hz show what is sent now)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from drift_tools.recording import KEPT_TOPICS
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs) \
        and not {topic, topic.lstrip('/')} & KEPT_TOPICS
    return QoSProfile(
        depth=100,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def dump(msg) -> None:
    print(yaml.safe_dump(to_plain(msg), sort_keys=False, default_flow_style=None).rstrip())
    print('---', flush=True)


# --- topic ------------------------------------------------------------------------------------

def topic_list(ros: Ros, args) -> int:
    ros.spin_until(lambda: False, args.wait, 0.1)          # let discovery fill the graph
    for name, types in sorted(ros.node.get_topic_names_and_types()):
        print(f'{name} [{", ".join(types)}]' if args.types else name)
    return 0


def topic_echo(ros: Ros, args) -> int:
    msgtype, pubs = ros.wait_publishers(args.topic, args.timeout)
    seen = []
    ros.node.create_subscription(interface_class(msgtype), args.topic,
                                 lambda m: (seen.append(1), dump(m)),
                                 matching_qos(pubs, args.topic))
    if not ros.spin_until(lambda: bool(seen), args.timeout):
        raise CliError(f'nothing received on {args.topic} within {args.timeout:g} s')
    ros.spin_until(lambda: args.count and len(seen) >= args.count, float('inf'))
    return 0


def topic_hz(ros: Ros, args) -> int:
    msgtype, pubs = ros.wait_publishers(args.topic, args.timeout)
    stamps = deque(maxlen=args.window)
    ros.node.create_subscription(interface_class(msgtype), args.topic,
                                 lambda _m: stamps.append(time.monotonic()),
                                 matching_qos(pubs, args.topic),
                                 raw=True)
    start = time.monotonic()
    next_print = start + 1.0
    while not args.duration or time.monotonic() < start + args.duration:
        ros.rclpy.spin_once(ros.node, timeout_sec=0.05)
        if time.monotonic() >= next_print:
            next_print += 1.0
            if len(stamps) < 2:
                print(f'{args.topic}: no messages', flush=True)
                continue
            dt = [b - a for a, b in zip(list(stamps)[:-1], list(stamps)[1:])]
            mean = sum(dt) / len(dt)
            print(f'{args.topic}: rate {1.0 / mean:.2f} Hz  min {min(dt):.4f} s  '
                  f'max {max(dt):.4f} s  window {len(stamps)}', flush=True)
    return 0


def topic_pub(ros: Ros, args) -> int:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    cls = interface_class(args.type)
    msg = fill(cls(), parse_yaml(args.values, 'values'))
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pub = ros.node.create_publisher(cls, args.topic, qos)
    if not ros.spin_until(lambda: pub.get_subscription_count() > 0, args.timeout):
        raise CliError(f'no subscriber on {args.topic} within {args.timeout:g} s')
    sent = 0
    while not args.count or sent < args.count:
        if 'header' in cls.get_fields_and_field_types() and args.stamp:
            msg.header.stamp = ros.node.get_clock().now().to_msg()
        pub.publish(msg)
        sent += 1
        if args.count and sent >= args.count:
            break
        ros.spin_until(lambda: False, 1.0 / args.rate, 0.01)
    ros.spin_until(lambda: False, 0.2)           # let a reliable message leave
    print(f'published {sent} message(s) on {args.topic}')
    return 0


# --- service, bridge ----------------------------------------------------------------------------

def service_call(ros: Ros, args) -> int:
    dump(ros.call(args.service, args.type, parse_yaml(args.values, 'request'), args.timeout))
    return 0


def bridge_arm(ros: Ros, args) -> int:
    response = ros.call(BRIDGE_ARM, 'std_srvs/srv/SetBool', {'data': args.command == 'arm'},
                        args.timeout)
    print(f'{args.command}: {response.message}')
    if not response.success:
        raise CliError(f'{args.command} refused: {response.message}')
    return 0


def bridge_status(ros: Ros, args) -> int:
    from diagnostic_msgs.msg import DiagnosticArray
    got = {}

    def on_diag(msg):
        for status in msg.status:
            if status.name.startswith(args.name):
                got[status.name] = status
    ros.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    if not ros.spin_until(lambda: bool(got), args.timeout):
        raise CliError(f'no {args.name!r} status on /diagnostics within {args.timeout:g} s')
    ros.spin_until(lambda: False, 0.3)            # the other statuses of the same round
    levels = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
    for name, status in sorted(got.items()):
        level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
        print(f'{name}: {levels.get(level, level)} {status.message}')
        for kv in status.values:
            print(f'  {kv.key}: {kv.value}')
    return 0


# --- param --------------------------------------------------------------------------------------

def _param_value(value):
    """A ParameterValue message as Python."""
    from rcl_interfaces.msg import ParameterType as T
    return {T.PARAMETER_BOOL: value.bool_value, T.PARAMETER_INTEGER: value.integer_value,
            T.PARAMETER_DOUBLE: value.double_value, T.PARAMETER_STRING: value.string_value,
            T.PARAMETER_BYTE_ARRAY: list(value.byte_array_value),
            T.PARAMETER_BOOL_ARRAY: list(value.bool_array_value),
            T.PARAMETER_INTEGER_ARRAY: list(value.integer_array_value),
            T.PARAMETER_DOUBLE_ARRAY: list(value.double_array_value),
            T.PARAMETER_STRING_ARRAY: list(value.string_array_value)}.get(value.type, None)


def _node_service(ros: Ros, node: str, suffix: str, timeout: float) -> str:
    """The name of ``node``'s parameter service, once discovery has shown it (~2.5 s)."""
    node = absolute(node)
    services = {}
    ok = ros.spin_until(lambda: services.update(dict(ros.node.get_service_names_and_types()))
                        or f'{node}/{suffix}' in services, timeout, 0.1)
    if not ok:
        nodes = sorted('/' + n.lstrip('/') for n in ros.node.get_node_names())
        raise CliError(f'no node {node} (nodes: {nodes})', 2)
    return f'{node}/{suffix}'


def param_list(ros: Ros, args) -> int:
    response = ros.call(_node_service(ros, args.node, 'list_parameters', args.timeout),
                        'rcl_interfaces/srv/ListParameters', {}, args.timeout)
    for name in sorted(response.result.names):
        print(name)
    return 0


def param_get(ros: Ros, args) -> int:
    from rcl_interfaces.msg import ParameterType
    response = ros.call(_node_service(ros, args.node, 'get_parameters', args.timeout),
                        'rcl_interfaces/srv/GetParameters', {'names': [args.name]}, args.timeout)
    value = response.values[0] if response.values else None
    if value is None or value.type == ParameterType.PARAMETER_NOT_SET:
        raise CliError(f'{args.node}: no parameter {args.name!r}', 2)
    print(yaml.safe_dump(_param_value(value), default_flow_style=True).strip().removesuffix('...')
          .strip())
    return 0


def parse_value(text: str):
    """A parameter value from the command line: a number first (YAML 1.1 reads ``1e9`` as a
    string), else YAML (bools, lists, strings)."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return parse_yaml(text, 'value')


def param_set(ros: Ros, args) -> int:
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter
    value = parse_value(args.value)
    if isinstance(value, dict) or value == {}:
        raise CliError(f'value: a number, bool, string or list, not {args.value!r}', 2)
    current = ros.call(_node_service(ros, args.node, 'get_parameters', args.timeout),
                       'rcl_interfaces/srv/GetParameters', {'names': [args.name]}, args.timeout)
    kind = current.values[0].type if current.values else ParameterType.PARAMETER_NOT_SET
    if kind == ParameterType.PARAMETER_NOT_SET:
        raise CliError(f'{args.node}: no parameter {args.name!r}', 2)
    if kind == ParameterType.PARAMETER_DOUBLE and isinstance(value, int) \
            and not isinstance(value, bool):
        value = float(value)             # '5' for a double parameter means 5.0
    msg = Parameter(args.name, value=value).to_parameter_msg()
    from rcl_interfaces.srv import SetParameters
    service = _node_service(ros, args.node, 'set_parameters', args.timeout)
    request = SetParameters.Request(parameters=[msg])
    client = ros.node.create_client(SetParameters, service)
    if not ros.spin_until(client.service_is_ready, args.timeout, 0.1):
        raise CliError(f'no service {service} within {args.timeout:g} s')
    future = client.call_async(request)
    if not ros.spin_until(future.done, args.timeout, 0.02):
        raise CliError(f'{service}: no response within {args.timeout:g} s')
    result = future.result().results[0]
    if not result.successful:
        raise CliError(f'{args.node} refused {args.name}: {result.reason}')
    print(f'{args.node}: {args.name} = {value!r}')
    return 0
