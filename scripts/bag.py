#!/usr/bin/env python3
"""Inspect a bag and repair a damaged one into a new directory; the input is never written.

    bag.py info BAG              topics, counts, and whether the file is finished and intact
    bag.py recover BAG OUT       write what is readable of BAG into the new bag OUT

A recorder killed by SIGKILL or a full disk leaves a bag without its summary; a damaged chunk in
the middle loses only that chunk's messages. Exit status: 0 intact (info) or recovered, 1 when
info finds damage, 2 on bad input.
"""
import argparse
import sys
from pathlib import Path


def info(args) -> int:
    from drift_tools.bag_salvage import scan_bag
    scan = scan_bag(args.bag)
    counts = {}
    for m in scan.messages:
        topic = scan.channels[m.channel_id].topic
        counts[topic] = counts.get(topic, 0) + 1
    times = [m.log_time for m in scan.messages]
    span = (max(times) - min(times)) * 1e-9 if times else 0.0
    print(f'{args.bag}: {len(scan.messages)} readable messages over {span:.2f} s '
          f'({scan.chunks} chunks)')
    for cid, channel in sorted(scan.channels.items()):
        schema = scan.schemas.get(channel.schema_id)
        print(f'  {channel.topic} [{schema.name if schema else "?"}]: '
              f'{counts.get(channel.topic, 0)}')
    from drift_tools.run_info import read_run_info
    run = read_run_info(args.bag)
    if run:
        dirty = ' (with uncommitted changes)' if run.get('dirty') == 'true' else ''
        vehicle = run.get('vehicle') or "(the scenario's)"
        seed = run.get('seed') or "(the scenario's)"
        print(f'  run: scenario {run.get("scenario") or "?"}, vehicle {vehicle}, seed {seed}, '
              f'overrides {run.get("overrides")}, commit {run.get("commit", "")[:12]}{dirty}')
        print(f'  command: {run.get("command_line", "")}')
    problems = scan.problems()
    for line in problems:
        print(f'  problem: {line}')
    if problems:
        print(f'  repair: scripts/bag.py recover {args.bag} <new directory>')
    return 1 if problems else 0


def recover(args) -> int:
    from drift_tools.bag_salvage import recover_bag
    result = recover_bag(args.bag, args.out)
    print('\n'.join(result.lines()))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('info', help='topics, counts and damage of a bag')
    p.add_argument('bag', type=Path)
    p.set_defaults(run=info)
    p = sub.add_parser('recover', help='write a repaired copy of a bag')
    p.add_argument('bag', type=Path)
    p.add_argument('out', type=Path, help='new bag directory (must not exist or be empty)')
    p.set_defaults(run=recover)
    args = parser.parse_args(argv)

    from drift_tools.bag_salvage import BagDamagedError
    try:
        return args.run(args)
    except (BagDamagedError, FileExistsError, OSError) as err:
        print(f'bag: {err}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
