#!/usr/bin/env python3
"""Report on a recorded run: metrics JSON, a Markdown summary and PNG figures.

    report.py BAG [--out DIR] [--scenario NAME] [--no-figures]

Steady-drift windows come from the scenario's ``metrics`` section: ``--scenario``, else the one
the bag's run metadata names; for a bag without them, from the recorded reference (where its
sideslip holds its plateau). Output goes to
``BAG_report/`` beside the bag by default: metrics.json, report.md, states.png, inputs.png,
path.png, solve_time.png. The bag is only read; one whose recorder was killed is read as far as
it is intact (``scripts/bag.py recover`` writes a repaired copy).
"""
import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag', help='rosbag2 directory (metadata.yaml + .mcap)')
    parser.add_argument('--out', help='output directory (default: BAG_report beside the bag)')
    parser.add_argument('--scenario', help='take the steady-drift windows from this scenario')
    parser.add_argument('--no-figures', action='store_true')
    args = parser.parse_args(argv)

    from drift_tools.bag import read_bag
    from drift_tools.bag_salvage import BagDamagedError
    from drift_tools.report import write_report
    from drift_tools.timeseries import series_from_bag

    bag = Path(args.bag)
    out = Path(args.out) if args.out else bag.with_name(bag.name + '_report')
    if not (bag / 'metadata.yaml').exists():
        print(f'report: {bag}: not a bag directory (no metadata.yaml)', file=sys.stderr)
        return 2
    windows = transient_end = None
    from drift_control.params import ParamError
    from drift_control.scenario import load_scenario_spec
    from drift_tools.run_info import read_run_info, run_scenario
    try:
        scenario = load_scenario_spec(args.scenario) if args.scenario else \
            run_scenario(read_run_info(bag))     # the run's own, from the bag's metadata
    except (ParamError, BagDamagedError, ValueError) as err:
        print(f'report: {err}', file=sys.stderr)
        return 2
    if scenario is not None:
        windows = [list(w) for w in scenario.metrics.steady]
        transient_end = scenario.metrics.transient_end
    try:
        run = series_from_bag(read_bag(bag))
        m = write_report(run, out, bag.name, windows, transient_end,
                         with_figures=not args.no_figures)
    except (BagDamagedError, ValueError, OSError) as err:
        print(f'report: {err}', file=sys.stderr)
        return 2
    print((out / 'report.md').read_text())
    return 0 if m else 1


if __name__ == '__main__':
    sys.exit(main())
