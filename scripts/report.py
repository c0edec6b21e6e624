#!/usr/bin/env python3
"""Report on a recorded run: metrics JSON, a Markdown summary and PNG figures.

    report.py BAG [--out DIR] [--scenario NAME] [--no-figures]
    report.py LOG.mf4 [--dbc FILE.dbc] [...]

Steady-drift windows come from the scenario's ``metrics`` section: ``--scenario``, else the one
the bag's run metadata names; for a bag without them, from the recorded reference (where its
sideslip holds its plateau). Output goes to
``BAG_report/`` beside the bag by default: metrics.json, report.md, states.png, inputs.png,
path.png, solve_time.png. The bag is only read; one whose recorder was killed is read as far as
it is intact (``scripts/bag.py recover`` writes a repaired copy).

An MDF4 file is read as well (``drift_tools.mdf``): one ``drift bag export`` wrote (the same report
as its bag's, without the path), or a car logger's, whose CAN / CAN FD bus logging ``--dbc``
decodes into the vehicle state (or whose channels already carry the DBC's signal names); the
report then holds what the state alone gives (no reference, commands or NMPC status). Output goes
to ``LOG_report/`` beside the file by default.
"""
import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag', help='rosbag2 directory (metadata.yaml + .mcap) or MDF4 file')
    parser.add_argument('--out', help='output directory (default: BAG_report beside the bag)')
    parser.add_argument('--scenario', help='take the steady-drift windows from this scenario')
    parser.add_argument('--no-figures', action='store_true')
    parser.add_argument('--dbc', help='decode the CAN / CAN FD bus logging of an MDF4 file')
    args = parser.parse_args(argv)

    from drift_tools.bag_salvage import BagDamagedError
    from drift_tools.report import write_report
    from drift_tools.timeseries import series_from_bag

    bag = Path(args.bag)
    is_mdf = bag.is_file()
    out = Path(args.out) if args.out else bag.with_name((bag.stem if is_mdf else bag.name)
                                                        + '_report')
    if not is_mdf and not (bag / 'metadata.yaml').exists():
        print(f'report: {bag}: neither a bag directory (metadata.yaml) nor an MDF4 file',
              file=sys.stderr)
        return 2
    if args.dbc and not is_mdf:
        print(f'report: --dbc decodes the bus logging of an MDF4 file; {bag} is a bag directory',
              file=sys.stderr)
        return 2
    from drift_control.cli_args import output_problem
    problem = output_problem(out, [bag, args.dbc], directory=True)
    if problem is not None:
        print(f'report: {problem}', file=sys.stderr)
        return 2
    windows = transient_end = None
    from drift_control.params import ParamError
    from drift_control.scenario import load_scenario_spec
    from drift_tools.mdf import log_run_info, read_log
    from drift_tools.run_info import run_scenario
    try:
        scenario = load_scenario_spec(args.scenario) if args.scenario else \
            run_scenario(log_run_info(bag))     # the run's own, from the bag's metadata
    except (ParamError, BagDamagedError, ValueError) as err:
        print(f'report: {err}', file=sys.stderr)
        return 2
    if scenario is not None:
        windows = [list(w) for w in scenario.metrics.steady]
        transient_end = scenario.metrics.transient_end
    try:
        run = series_from_bag(read_log(bag, args.dbc))
        m = write_report(run, out, bag.name, windows, transient_end,
                         with_figures=not args.no_figures)
    except (BagDamagedError, ValueError, OSError) as err:
        print(f'report: {err}', file=sys.stderr)
        return 2
    print((out / 'report.md').read_text())
    return 0 if m else 1


if __name__ == '__main__':
    sys.exit(main())
