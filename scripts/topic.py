#!/usr/bin/env python3
"""Inspect live topics (PyPI has no ros2cli): list, echo, hz. Types are resolved from the graph.

    .venv/bin/python scripts/topic.py list -t
    .venv/bin/python scripts/topic.py echo /vehicle/state -n 1
    .venv/bin/python scripts/topic.py hz /drift/command --window 100

Uses ROS_DOMAIN_ID from the environment; ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST.
"""
import argparse
import importlib
import os
import sys
import time
from collections import deque

import yaml


def message_class(msgtype: str):
    """``pkg/msg/Name`` -> the generated Python class."""
    pkg, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def to_plain(msg):
    """A message as nested dicts and lists (for YAML output)."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {name: to_plain(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or type(msg).__name__ in ('ndarray', 'array'):
        return [to_plain(x) for x in msg]
    if hasattr(msg, 'item'):          # numpy scalar
        return msg.item()
    return msg


def wait_for_topic(node, topic, timeout):
    """Spin until ``topic`` has a publisher; return its (type, publishers info)."""
    import rclpy
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        types = dict(node.get_topic_names_and_types()).get(topic)
        pubs = node.get_publishers_info_by_topic(topic)
        if types and pubs:
            return types[0], pubs
        rclpy.spin_once(node, timeout_sec=0.1)
    raise SystemExit(f'topic.py: no publisher on {topic} within {timeout:.0f} s')


def matching_qos(pubs):
    """Reliable only if every publisher is; transient-local only if every publisher is."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
    return QoSProfile(
        depth=100,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def cmd_list(node, args):
    import rclpy
    end = time.monotonic() + args.wait
    while time.monotonic() < end:          # let discovery fill the graph
        rclpy.spin_once(node, timeout_sec=0.1)
    for name, types in sorted(node.get_topic_names_and_types()):
        print(f'{name} [{", ".join(types)}]' if args.types else name)
    return 0


def cmd_echo(node, args):
    import rclpy
    msgtype, pubs = wait_for_topic(node, args.topic, args.timeout)
    seen = []

    def on_msg(msg):
        seen.append(1)
        print(yaml.safe_dump(to_plain(msg), sort_keys=False, default_flow_style=None).rstrip())
        print('---', flush=True)

    node.create_subscription(message_class(msgtype), args.topic, on_msg, matching_qos(pubs))
    deadline = time.monotonic() + args.timeout
    while not args.count or len(seen) < args.count:
        rclpy.spin_once(node, timeout_sec=0.1)
        if not seen and time.monotonic() > deadline:
            print(f'topic.py: nothing received on {args.topic} within {args.timeout:.0f} s',
                  file=sys.stderr)
            return 1
    return 0


def cmd_hz(node, args):
    import rclpy
    msgtype, pubs = wait_for_topic(node, args.topic, args.timeout)
    stamps = deque(maxlen=args.window)
    node.create_subscription(message_class(msgtype), args.topic,
                             lambda _msg: stamps.append(time.monotonic()), matching_qos(pubs),
                             raw=True)
    start = next_print = time.monotonic() + 1.0
    while not args.duration or time.monotonic() < start - 1.0 + args.duration:
        rclpy.spin_once(node, timeout_sec=0.05)
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest='command', required=True)
    s = sub.add_parser('list', help='topics in the graph')
    s.add_argument('-t', '--types', action='store_true', help='show the message types')
    s.add_argument('--wait', type=float, default=2.5, help='discovery time before listing [s]')
    s = sub.add_parser('echo', help='print messages of a topic')
    s.add_argument('topic')
    s.add_argument('-n', '--count', type=int, default=0, help='stop after N messages (0: never)')
    s.add_argument('--timeout', type=float, default=10.0, help='give up after this long [s]')
    s = sub.add_parser('hz', help='receive rate of a topic, printed every second')
    s.add_argument('topic')
    s.add_argument('--window', type=int, default=100, help='messages averaged over')
    s.add_argument('--duration', type=float, default=0.0, help='stop after [s] (0: never)')
    s.add_argument('--timeout', type=float, default=10.0, help='wait for a publisher [s]')
    args = p.parse_args(argv)
    if getattr(args, 'topic', '/').lstrip('/') == getattr(args, 'topic', '/'):
        args.topic = '/' + args.topic

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rclpy.init()
    node = rclpy.create_node(f'topic_tool_{os.getpid()}')
    try:
        return {'list': cmd_list, 'echo': cmd_echo, 'hz': cmd_hz}[args.command](node, args)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
