#!/usr/bin/env python3
"""Replay a recorded bag onto its topics, or re-run the controller on its recorded states.

    replay.py BAG                       publish every topic at recorded timing
    replay.py BAG --rate 4              four times faster (--rate 0: as fast as possible)
    replay.py BAG --topics /vehicle/state --lockstep
                                        drive a live selector + NMPC in sim time: publish /clock
                                        and each state, then wait for that step's command
    replay.py BAG --rerun [--json F]    no ROS: run the NMPC core on the recorded states and
                                        references and report recorded vs recomputed commands

The ROS environment (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST by default) is taken
from the caller.
"""
import argparse
import json
import os
import sys
import time
from pathlib import Path

STATE_TOPIC = '/vehicle/state'
COMMAND_TOPIC = '/drift/command'


def publish(args) -> int:
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    from drift_tools.replay import Pacer, iter_raw, message_class

    topics = args.topics or None
    if args.lockstep and topics is None:
        topics = [STATE_TOPIC]     # the controller runs live; recorded outputs would clash
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rclpy.init()
    node = rclpy.create_node('replay')
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    publishers, commands = {}, []
    clock_pub = node.create_publisher(Clock, '/clock', 10) if args.lockstep else None
    if args.lockstep:
        from drift_msgs.msg import DriftCommand
        node.create_subscription(DriftCommand, COMMAND_TOPIC, commands.append, 10)
    pacer = Pacer(0.0 if args.lockstep else args.rate)
    sent = waited_out = 0
    try:
        for raw in iter_raw(args.bag, topics):
            if raw.topic not in publishers:
                publishers[raw.topic] = node.create_publisher(message_class(raw.msgtype),
                                                              raw.topic, qos)
                _wait_for_subscribers(node, publishers[raw.topic], args.discovery_timeout)
            pacer.wait_until(raw.t_ns)
            if clock_pub is not None:
                clock_pub.publish(_clock(raw.t_ns))
            before = len(commands)
            publishers[raw.topic].publish(raw.data)
            sent += 1
            if args.lockstep and raw.topic == STATE_TOPIC:
                deadline = time.monotonic() + args.step_timeout
                while len(commands) == before and time.monotonic() < deadline:
                    rclpy.spin_once(node, timeout_sec=0.005)
                waited_out += len(commands) == before
            else:
                rclpy.spin_once(node, timeout_sec=0.0)
    except (ValueError, LookupError) as err:
        print(f'replay: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'replay: published {sent} messages on {len(publishers)} topics'
          + (f'; {len(commands)} commands received, {waited_out} steps timed out'
             if args.lockstep else ''))
    return 0


def _wait_for_subscribers(node, pub, timeout: float) -> None:
    """Give discovery its ~2.5 s: wait until someone listens (or the timeout passes)."""
    import rclpy
    deadline = time.monotonic() + timeout
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)


def _clock(t_ns: int):
    from rosgraph_msgs.msg import Clock
    msg = Clock()
    msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
    return msg


def rerun(args) -> int:
    from drift_tools.rerun import rerun_controller
    from drift_tools.run_info import read_run_info, run_scenario
    spec = run_scenario(read_run_info(args.bag))   # the car and surface the run drove
    if spec is not None:
        args.vehicle = args.vehicle or spec.vehicle
        args.surface = args.surface or spec.surface.name
    try:
        result = rerun_controller(Path(args.bag), control_mode=args.control_mode,
                                  surface=args.surface, vehicle=args.vehicle)
    except (ValueError, LookupError, FileNotFoundError) as err:
        print(f'replay: {err}', file=sys.stderr)
        return 2
    for line in result.summary_lines():
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_dict(), indent=2))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__)
    parser.add_argument('bag', help='rosbag2 directory (metadata.yaml + .mcap)')
    parser.add_argument('--rate', type=float, default=1.0, help='speed-up factor; 0 = no pacing')
    parser.add_argument('--topics', nargs='*', help='only these topics (absolute names)')
    parser.add_argument('--lockstep', action='store_true', help='publish /clock, wait per step')
    parser.add_argument('--step-timeout', type=float, default=1.0, help='lockstep wait [s]')
    parser.add_argument('--discovery-timeout', type=float, default=5.0, help='[s]')
    parser.add_argument('--rerun', action='store_true', help='re-run the NMPC core offline')
    parser.add_argument('--control-mode', default='full', choices=('full', 'torque_only'))
    parser.add_argument('--surface', help='friction the NMPC assumes (default: the recorded '
                        'run\'s scenario, else dry)')
    parser.add_argument('--vehicle', help='the car the run drove (default: the recorded run\'s, '
                        'else config/defaults.yaml\'s)')
    parser.add_argument('--json', help='with --rerun: write the comparison here')
    args = parser.parse_args(argv)
    if not (Path(args.bag) / 'metadata.yaml').exists():
        print(f'replay: {args.bag}: not a bag directory (no metadata.yaml)', file=sys.stderr)
        return 2
    return rerun(args) if args.rerun else publish(args)


if __name__ == '__main__':
    sys.exit(main())
