#!/usr/bin/env python3
"""Replay a recorded bag onto its topics, or re-run the controller on its recorded states.

    replay.py BAG                       publish every topic at recorded timing
    replay.py BAG --rate 4              four times faster (--rate 0: as fast as possible)
    replay.py BAG --clock --loop 0      publish /clock from the log time, loop until stopped
                                        (each pass shifted forward: time never runs backwards)
    replay.py BAG --start 20 --end 30   a window, seconds after the first message
    replay.py BAG --lockstep [--json F] drive a live selector + NMPC in sim time: publish /clock
                                        and each state, wait for that step's command, and compare
                                        the commands with the recorded ones
    replay.py BAG --rerun [--json F]    no ROS: run the NMPC core on the recorded states and
                                        references and report recorded vs recomputed commands

The ROS environment (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST by default) is taken
from the caller. Each topic is offered with the QoS it was recorded with (the latched path stays
latched). SIGINT or SIGTERM ends the replay cleanly.
"""
import argparse
import itertools
import json
import signal
import sys
import time
from pathlib import Path

from drift_control.cli_args import natural, nonnegative, output_problem, seconds, write_text

STATE_TOPIC = '/vehicle/state'
STATE_REPEAT = 0.2   # [s] as the lock-step simulator offers its first state again
COMMAND_TOPIC = '/drift/command'


def publish(args) -> int:
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock

    from drift_tools.dds import use_udp_here
    from drift_tools.replay import Pacer, iter_replay, message_class, topic_qos

    topics = args.topics or None
    if args.lockstep and topics is None:
        topics = [STATE_TOPIC]     # the controller runs live; recorded outputs would clash
    try:
        recorded_qos = topic_qos(args.bag)
        # /clock: a bag that has it (a sim-time run) replays its own with --clock; lock-step
        # publishes each state's stamp before it, as the simulator did; otherwise the log time
        own_clock = args.clock and not args.lockstep and '/clock' in recorded_qos
        publish_clock = args.lockstep or (args.clock and not own_clock)
        if topics is not None:
            topics = [t for t in topics if t != '/clock'] + (['/clock'] if own_clock else [])
        messages = iter_replay(args.bag, topics, args.start, args.end, args.loop)
        first = next(messages, None)
    except (ValueError, LookupError, OSError) as err:
        print(f'replay: {err}', file=sys.stderr)
        return 2
    if first is None:
        print('replay: nothing to publish (no such topics in the bag)', file=sys.stderr)
        return 2
    use_udp_here()
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('replay')
    publishers, commands = {}, []
    clock_pub = node.create_publisher(Clock, '/clock', 10) if publish_clock else None
    recorded, answered = {}, set()       # stamps [ns] of the recorded / received commands
    command_sub = None
    if args.lockstep:
        from drift_msgs.msg import DriftCommand

        def on_command(msg):
            commands.append(msg)
            answered.add(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        command_sub = node.create_subscription(DriftCommand, COMMAND_TOPIC, on_command, 100)
        recorded = _recorded_commands(args.bag)   # stamp [ns] -> (delta, torque, mode)
    pacer = Pacer(0.0 if args.lockstep else args.rate)
    sent = waited_out = 0
    try:
        for raw in itertools.chain([first], messages):
            if raw.topic == '/clock' and publish_clock:
                continue
            if raw.topic not in publishers:
                reliable, latched = recorded_qos.get(raw.topic, (True, False))
                qos = QoSProfile(
                    depth=10, reliability=ReliabilityPolicy.RELIABLE if reliable
                    else ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                    else DurabilityPolicy.VOLATILE)
                publishers[raw.topic] = node.create_publisher(message_class(raw.msgtype),
                                                              raw.topic, qos)
                _wait_for_subscribers(node, publishers[raw.topic], args.discovery_timeout,
                                      answer=command_sub if raw.topic == STATE_TOPIC else None)
            pacer.wait_until(raw.t_ns)
            if clock_pub is not None and not args.lockstep:
                clock_pub.publish(_clock(raw.t_ns))
            elif clock_pub is not None and raw.topic == STATE_TOPIC:
                clock_pub.publish(_clock(_stamp_ns(raw)))
            before = len(commands)
            publishers[raw.topic].publish(raw.data)
            sent += 1
            stamp = _stamp_ns(raw) if args.lockstep and raw.topic == STATE_TOPIC else None
            if stamp is not None and (not recorded or stamp in recorded):
                # as the lock-step simulator: no step before this state's command is in (the
                # recorded run had one for it); until the first command, the state is offered
                # again every 0.2 s, for nodes that were still discovering us
                deadline = time.monotonic() + args.step_timeout
                offered = time.monotonic()
                while not (stamp in answered if recorded else len(commands) > before) \
                        and time.monotonic() < deadline:
                    rclpy.spin_once(node, timeout_sec=0.005)
                    if not commands and time.monotonic() - offered > STATE_REPEAT:
                        offered = time.monotonic()
                        publishers[raw.topic].publish(raw.data)
                waited_out += not (stamp in answered if recorded else len(commands) > before)
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
    if args.lockstep and recorded:
        report = _compare(commands, recorded)
        print(f'replay: {report["matched"]} of {report["recorded"]} recorded commands answered; '
              f'max |delta - recorded| {report["delta_max_abs_diff"]:.3g} rad, '
              f'max |torque - recorded| {report["torque_max_abs_diff"]:.3g} Nm, '
              f'{report["mode_mismatches"]} mode mismatches')
        if args.json:
            return _write_json(args.json, report)
    return 0


def _write_json(path, data) -> int:
    problem = write_text(path, json.dumps(data, indent=2))
    if problem is not None:
        print(f'replay: {problem}', file=sys.stderr)
        return 2
    return 0


def _stamp_ns(raw) -> int:
    """The header stamp of a raw VehicleState (its first field) [ns]."""
    import struct
    sec, nsec = struct.unpack_from('<iI' if raw.data[1] == 1 else '>iI', raw.data, 4)
    return sec * 1_000_000_000 + nsec


def _recorded_commands(bag) -> dict:
    from drift_tools.bag import read_bag
    out = {}
    for m in read_bag(bag, topics=[COMMAND_TOPIC]).get(COMMAND_TOPIC, []):
        c = m.msg
        out[c.header.stamp.sec * 1_000_000_000 + c.header.stamp.nanosec] = (
            c.delta, c.drive_torque, c.mode)
    return out


def _compare(commands, recorded: dict) -> dict:
    """Live commands against the recorded ones of the same stamps."""
    d_delta = d_torque = 0.0
    matched = modes = 0
    for c in commands:
        key = c.header.stamp.sec * 1_000_000_000 + c.header.stamp.nanosec
        if key not in recorded:
            continue
        delta, torque, mode = recorded[key]
        matched += 1
        d_delta = max(d_delta, abs(c.delta - delta))
        d_torque = max(d_torque, abs(c.drive_torque - torque))
        modes += c.mode != mode
    return {'recorded': len(recorded), 'received': len(commands), 'matched': matched,
            'delta_max_abs_diff': d_delta, 'torque_max_abs_diff': d_torque,
            'mode_mismatches': modes}


def _wait_for_subscribers(node, pub, timeout: float, answer=None) -> None:
    """Give discovery its ~2.5 s: wait until someone listens (or the timeout passes).

    With ``answer`` (the command subscription of a lock-step replay), also until the controller
    publishes, and until every subscriber the graph shows on the topic is matched: a state the
    NMPC misses would shift its solving phase against the recorded run's.
    """
    import rclpy

    def ready():
        subscribers = pub.get_subscription_count()
        if answer is None:
            return subscribers > 0
        return (subscribers > 0 and answer.get_publisher_count() > 0
                and subscribers >= node.count_subscribers(pub.topic_name))
    deadline = time.monotonic() + timeout
    while not ready() and time.monotonic() < deadline:
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
        return _write_json(args.json, result.to_dict())
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__)
    parser.add_argument('bag', help='rosbag2 directory (metadata.yaml + .mcap)')
    parser.add_argument('--rate', type=nonnegative, default=1.0,
                        help='speed-up factor; 0 = no pacing')
    parser.add_argument('--topics', nargs='*', help='only these topics (absolute names)')
    parser.add_argument('--clock', action='store_true',
                        help='publish /clock for nodes with use_sim_time: the bag\'s own if it '
                             'recorded one (a sim-time run), else from the log time')
    parser.add_argument('--loop', type=natural, default=1, metavar='N',
                        help='play N times (0: until stopped); each pass later in time, stamps '
                             'and /clock shifted, so time never runs backwards')
    parser.add_argument('--start', type=seconds, default=0.0,
                        help='from this many seconds after the first message')
    parser.add_argument('--end', type=seconds, default=None,
                        help='up to this many seconds after the first message')
    parser.add_argument('--lockstep', action='store_true',
                        help='publish /clock, wait per state for its command')
    parser.add_argument('--step-timeout', type=seconds, default=1.0, help='lockstep wait [s]')
    parser.add_argument('--discovery-timeout', type=seconds, default=5.0, help='[s]')
    parser.add_argument('--rerun', action='store_true', help='re-run the NMPC core offline')
    parser.add_argument('--control-mode', default='full', choices=('full', 'torque_only'))
    parser.add_argument('--surface', help='friction the NMPC assumes (default: the recorded '
                        'run\'s scenario, else dry)')
    parser.add_argument('--vehicle', help='the car the run drove (default: the recorded run\'s, '
                        'else config/defaults.yaml\'s)')
    parser.add_argument('--json', help='with --rerun or --lockstep: write the comparison here')
    args = parser.parse_args(argv)
    if not (Path(args.bag) / 'metadata.yaml').exists():
        print(f'replay: {args.bag}: not a bag directory (no metadata.yaml)', file=sys.stderr)
        return 2
    problem = output_problem(args.json, [args.bag]) if args.json else None
    if problem is not None:
        print(f'replay: {problem}', file=sys.stderr)
        return 2
    return rerun(args) if args.rerun else publish(args)


if __name__ == '__main__':
    sys.exit(main())
