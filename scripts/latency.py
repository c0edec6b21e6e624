#!/usr/bin/env python3
"""State -> command latency of a recorded real-time run (recorder log times).

    latency.py BAG [--skip 1.0] [--json]

Each command is matched to the newest state recorded before it (with the estimator stage: the
newest frame of sensor samples); prints p50, p99 and max over the commands after the first
``--skip`` seconds, then the same hop by hop along each command's stamp (sensors -> state ->
reference -> command). ``--publish-times``: the same from the publish times the recorder keeps
(each message's DDS source timestamp), without the recorder's own delays. A lock-step bag (log
times in sim time) is refused. The bag is only read; an MDF4 export is read as well.
"""
import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory or MDF4 export')
    parser.add_argument('--skip', type=float, default=1.0, help='start-up left out [s]')
    parser.add_argument('--json', action='store_true', help='print the numbers as JSON')
    parser.add_argument('--publish-times', action='store_true',
                        help='from the publishers\' clocks at publish, not the recorder\'s '
                             'log times (bags only)')
    args = parser.parse_args(argv)

    from drift_tools.bag_salvage import BagDamagedError
    from drift_tools.latency import latency, stages
    from drift_tools.mdf import log_run_info, read_log
    if not args.bag.exists():
        print(f'latency: {args.bag}: no such bag', file=sys.stderr)
        return 2
    try:
        info = log_run_info(args.bag) or {}
        if info.get('clock') == 'lockstep':
            print(f'latency: {args.bag} is a lock-step run: its log times are sim time, so '
                  f'it has no latency to measure (record one with --clock realtime)',
                  file=sys.stderr)
            return 2
        when = 't'
        if args.publish_times:
            if args.bag.is_file():
                raise ValueError('--publish-times: an MDF4 export has no publish times')
            from drift_tools.bag import read_bag
            messages, when = read_bag(args.bag, backend='mcap'), 'pt'
        else:
            messages = read_log(args.bag)
        result = latency(messages, args.skip, when)
        hops = stages(messages, args.skip, when) if not args.bag.is_file() else {}
    except (BagDamagedError, OSError, ValueError) as err:
        named = str(err).startswith(str(args.bag))   # the readers' errors name the file
        print(f'latency: {err}' if named else f'latency: {args.bag}: {err}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({**result.as_dict(),
                          'stages': {k: v.as_dict() for k, v in hops.items()}}))
        return 0
    start = 'sensors' if result.source.endswith('sensors') else 'state'
    print(f'{start} -> command over {result.n} commands: p50 {1e3 * result.p50:.1f} ms, '
          f'p99 {1e3 * result.p99:.1f} ms, max {1e3 * result.max:.1f} ms')
    for name, hop in hops.items():
        print(f'  {name} ({hop.n}): p50 {1e3 * hop.p50:.2f} ms, p99 {1e3 * hop.p99:.2f} ms, '
              f'max {1e3 * hop.max:.2f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(main())
