"""``drift``: the operator's command line (PyPI has no ros2cli). One entry point, subcommands:

    drift arm | disarm | status              the vehicle bridge: arm, release, its diagnostics
    drift topic list | echo | hz | pub       live topics
    drift service call SERVICE TYPE [YAML]   any service
    drift param list | get | set NODE ...    node parameters
    drift bag info | recover | slice | export   recorded runs (bags are only read)

Exit codes: 0 done, 1 refused or nothing heard (the reason on stderr), 2 bad input. Uses
ROS_DOMAIN_ID from the environment; ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from collections import deque
from pathlib import Path

import yaml

BRIDGE_ARM = '/bridge/arm'


class CliError(Exception):
    """A refusal with its one-line reason and exit code."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


# --- messages ---------------------------------------------------------------------------------

def interface_class(name: str, kind: str = 'msg'):
    """``pkg/msg/Name`` (or ``pkg/Name``) -> the generated class; ``kind`` msg or srv."""
    parts = name.strip('/').split('/')
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or parts[1] != kind:
        raise CliError(f'{name!r} is not a {kind} type name (pkg/{kind}/Name)', 2)
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{kind}'), parts[2])
    except (ImportError, AttributeError):
        raise CliError(f'{kind} type {name} is not installed here', 2) from None


def to_plain(msg):
    """A message as nested dicts and lists (for YAML output)."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {name: to_plain(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or type(msg).__name__ in ('ndarray', 'array'):
        return [to_plain(x) for x in msg]
    if isinstance(msg, bytes):
        return list(msg)
    if hasattr(msg, 'item'):          # numpy scalar
        return msg.item()
    return msg


def fill(msg, values: dict, where: str = ''):
    """Set ``msg``'s fields from a (nested) dict; an unknown field is a CliError naming it."""
    if not isinstance(values, dict):
        raise CliError(f'{where or "message"}: expected a mapping of fields, got {values!r}', 2)
    fields = msg.get_fields_and_field_types()
    for key, value in values.items():
        if key not in fields:
            raise CliError(f'{where}{key}: no such field; have {sorted(fields)}', 2)
        current = getattr(msg, key)
        try:
            if hasattr(current, 'get_fields_and_field_types'):
                fill(current, value, f'{where}{key}.')
            else:
                setattr(msg, key, _coerce(fields[key], value, f'{where}{key}'))
        except (TypeError, ValueError, AssertionError) as err:
            raise CliError(f'{where}{key}: {err}', 2) from None
    return msg


_INT_BITS = {'int8': 8, 'int16': 16, 'int32': 32, 'int64': 64, 'uint8': 8, 'uint16': 16,
             'uint32': 32, 'uint64': 64, 'byte': 8, 'octet': 8, 'char': 8}


def _coerce(kind: str, value, where: str):
    """``value`` checked against a field type of ``get_fields_and_field_types`` (rclpy's own
    checks are off by default: a string would silently become True in a bool field)."""
    if kind.startswith('sequence<') or kind.endswith(']'):
        inner = kind[len('sequence<'):].split('>')[0].split(',')[0] if kind.startswith(
            'sequence<') else kind[:kind.index('[')]
        if not isinstance(value, list):
            raise CliError(f'{where}: expected a list for {kind}, got {value!r}', 2)
        return [_coerce(inner, v, f'{where}[{i}]') for i, v in enumerate(value)]
    if kind == 'boolean':
        if not isinstance(value, bool):
            raise CliError(f'{where}: expected true or false, got {value!r}', 2)
        return value
    if kind in ('float', 'double'):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CliError(f'{where}: expected a number, got {value!r}', 2)
        return float(value)
    if kind in _INT_BITS:
        if isinstance(value, bool) or not isinstance(value, int):
            raise CliError(f'{where}: expected an integer, got {value!r}', 2)
        bits, signed = _INT_BITS[kind], kind.startswith('int')
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        if not lo <= value <= hi:
            raise CliError(f'{where}: {value} outside {kind} [{lo}, {hi}]', 2)
        return value
    if kind.startswith(('string', 'wstring')):
        if not isinstance(value, str):
            raise CliError(f'{where}: expected a string, got {value!r}', 2)
    return value


def parse_yaml(text: str, what: str):
    try:
        value = yaml.safe_load(text) if text else {}
    except yaml.YAMLError as err:
        raise CliError(f'{what}: not YAML ({str(err).splitlines()[0]})', 2) from None
    return {} if value is None else value


def absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


# --- the ROS side -----------------------------------------------------------------------------

class Ros:
    """One short-lived node for a command; discovery waits are condition-based."""

    def __init__(self):
        os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
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


def matching_qos(pubs):
    """Reliable only if every publisher is; transient-local only if every publisher is."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
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
                                 lambda m: (seen.append(1), dump(m)), matching_qos(pubs))
    if not ros.spin_until(lambda: bool(seen), args.timeout):
        raise CliError(f'nothing received on {args.topic} within {args.timeout:g} s')
    ros.spin_until(lambda: args.count and len(seen) >= args.count, float('inf'))
    return 0


def topic_hz(ros: Ros, args) -> int:
    msgtype, pubs = ros.wait_publishers(args.topic, args.timeout)
    stamps = deque(maxlen=args.window)
    ros.node.create_subscription(interface_class(msgtype), args.topic,
                                 lambda _m: stamps.append(time.monotonic()), matching_qos(pubs),
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


def _node_service(ros: Ros, node: str, suffix: str) -> str:
    node = absolute(node)
    services = {}
    ok = ros.spin_until(lambda: services.update(dict(ros.node.get_service_names_and_types()))
                        or f'{node}/{suffix}' in services, 3.0, 0.1)
    if not ok:
        nodes = sorted('/' + n.lstrip('/') for n in ros.node.get_node_names())
        raise CliError(f'no node {node} (nodes: {nodes})', 2)
    return f'{node}/{suffix}'


def param_list(ros: Ros, args) -> int:
    response = ros.call(_node_service(ros, args.node, 'list_parameters'),
                        'rcl_interfaces/srv/ListParameters', {}, args.timeout)
    for name in sorted(response.result.names):
        print(name)
    return 0


def param_get(ros: Ros, args) -> int:
    from rcl_interfaces.msg import ParameterType
    response = ros.call(_node_service(ros, args.node, 'get_parameters'),
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
    current = ros.call(_node_service(ros, args.node, 'get_parameters'),
                       'rcl_interfaces/srv/GetParameters', {'names': [args.name]}, args.timeout)
    kind = current.values[0].type if current.values else ParameterType.PARAMETER_NOT_SET
    if kind == ParameterType.PARAMETER_NOT_SET:
        raise CliError(f'{args.node}: no parameter {args.name!r}', 2)
    if kind == ParameterType.PARAMETER_DOUBLE and isinstance(value, int) \
            and not isinstance(value, bool):
        value = float(value)             # '5' for a double parameter means 5.0
    msg = Parameter(args.name, value=value).to_parameter_msg()
    from rcl_interfaces.srv import SetParameters
    service = _node_service(ros, args.node, 'set_parameters')
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


# --- bag ----------------------------------------------------------------------------------------

def bag_info(args) -> int:
    from drift_tools.bag_tools import bag_overview
    lines, problems = bag_overview(args.bag)
    print('\n'.join(lines))
    return 1 if problems else 0


def bag_recover(args) -> int:
    from drift_tools.bag_salvage import recover_bag
    print('\n'.join(recover_bag(args.bag, args.out).lines()))
    return 0


def bag_slice(args) -> int:
    from drift_tools.bag_tools import slice_bag
    kept = slice_bag(args.bag, args.out, args.start, args.end, args.topics)
    print(f'{args.out}: {sum(kept.values())} messages ' +
          ', '.join(f'{t} {n}' for t, n in sorted(kept.items())))
    return 0


def bag_export(args) -> int:
    from drift_tools.bag_tools import export_csv
    for path, rows in export_csv(args.bag, args.out, args.topics):
        print(f'{path}: {rows} rows')
    return 0


# --- the command line ---------------------------------------------------------------------------

ROS_COMMANDS = {('topic', 'list'): topic_list, ('topic', 'echo'): topic_echo,
                ('topic', 'hz'): topic_hz, ('topic', 'pub'): topic_pub,
                ('service', 'call'): service_call, ('arm', None): bridge_arm,
                ('disarm', None): bridge_arm, ('status', None): bridge_status,
                ('param', 'list'): param_list, ('param', 'get'): param_get,
                ('param', 'set'): param_set}
BAG_COMMANDS = {'info': bag_info, 'recover': bag_recover, 'slice': bag_slice,
                'export': bag_export}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='drift', description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest='command', required=True)
    for name, helptext in (('arm', 'arm the vehicle bridge'), ('disarm', 'release the car')):
        s = sub.add_parser(name, help=helptext)
        s.add_argument('--timeout', type=float, default=10.0)
    s = sub.add_parser('status', help='the bridge\'s diagnostics (mode, rates, recording)')
    s.add_argument('--name', default='vehicle_bridge', help='status name prefix')
    s.add_argument('--timeout', type=float, default=5.0)

    topic = sub.add_parser('topic', help='live topics').add_subparsers(dest='sub', required=True)
    s = topic.add_parser('list', help='topics in the graph')
    s.add_argument('-t', '--types', action='store_true', help='show the message types')
    s.add_argument('--wait', type=float, default=2.5, help='discovery time before listing [s]')
    s = topic.add_parser('echo', help='print messages of a topic')
    s.add_argument('topic', type=absolute)
    s.add_argument('-n', '--count', type=int, default=0, help='stop after N messages (0: never)')
    s.add_argument('--timeout', type=float, default=10.0, help='give up after this long [s]')
    s = topic.add_parser('hz', help='receive rate of a topic, printed every second')
    s.add_argument('topic', type=absolute)
    s.add_argument('--window', type=int, default=100, help='messages averaged over')
    s.add_argument('--duration', type=float, default=0.0, help='stop after [s] (0: never)')
    s.add_argument('--timeout', type=float, default=10.0, help='wait for a publisher [s]')
    s = topic.add_parser('pub', help='publish a message (fields in YAML)')
    s.add_argument('topic', type=absolute)
    s.add_argument('type', help='pkg/msg/Name')
    s.add_argument('values', nargs='?', default='', help="e.g. '{data: 1.5}'")
    s.add_argument('-n', '--count', type=int, default=1, help='messages (0: until stopped)')
    s.add_argument('-r', '--rate', type=float, default=10.0, help='[Hz]')
    s.add_argument('--stamp', action='store_true', help='stamp the header with the node clock')
    s.add_argument('--timeout', type=float, default=10.0, help='wait for a subscriber [s]')

    service = sub.add_parser('service', help='services').add_subparsers(dest='sub', required=True)
    s = service.add_parser('call', help='call a service (request fields in YAML)')
    s.add_argument('service', type=absolute)
    s.add_argument('type', nargs='?', default=None, help='pkg/srv/Name (default: the graph\'s)')
    s.add_argument('values', nargs='?', default='', help="e.g. '{data: true}'")
    s.add_argument('--timeout', type=float, default=10.0)

    param = sub.add_parser('param', help='node parameters').add_subparsers(dest='sub',
                                                                            required=True)
    for name in ('list', 'get', 'set'):
        s = param.add_parser(name, help=f'{name} parameters of a node')
        s.add_argument('node')
        if name in ('get', 'set'):
            s.add_argument('name')
        if name == 'set':
            s.add_argument('value', help='YAML value')
        s.add_argument('--timeout', type=float, default=10.0)

    bag = sub.add_parser('bag', help='recorded runs (read only)').add_subparsers(dest='sub',
                                                                                required=True)
    s = bag.add_parser('info', help='topics, counts, time span, run settings, damage')
    s.add_argument('bag', type=Path)
    s = bag.add_parser('recover', help='a repaired copy of a damaged or unfinished bag')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path)
    s = bag.add_parser('slice', help='a new bag with a time window and/or some topics')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path)
    s.add_argument('--start', type=float, default=0.0, help='[s] after the first message')
    s.add_argument('--end', type=float, default=None, help='[s] after the first message')
    s.add_argument('--topics', nargs='*', default=None)
    s = bag.add_parser('export', help='one CSV per topic (flattened fields)')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path, help='directory for the CSV files')
    s.add_argument('--topics', nargs='*', default=None)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == 'bag':
            return BAG_COMMANDS[args.sub](args)
        command = ROS_COMMANDS[(args.command, getattr(args, 'sub', None))]
        ros = Ros()
        try:
            return command(ros, args)
        finally:
            ros.close()
    except CliError as err:
        print(f'drift: {err}', file=sys.stderr)
        return err.code
    except BrokenPipeError:          # `drift ... | head`: the reader has what it wanted
        sys.stdout = open(os.devnull, 'w', encoding='utf-8')
        return 0
    except (OSError, ValueError, LookupError) as err:
        print(f'drift: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0


if __name__ == '__main__':
    sys.exit(main())
