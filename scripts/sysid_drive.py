#!/usr/bin/env python3
"""Drive an identification manoeuvre on the simulator, controller off, and record it to a bag.

    .venv/bin/python scripts/sysid_drive.py --scenario sysid_dry --bag runs/sysid_dry_0
    .venv/bin/python scripts/sysid_drive.py --scenario sysid_wet --seed 3 --vehicle gr86 --bag B

The scripted driver (``drift_sim.manoeuvre``, programme ``config/sim/manoeuvres/sysid.yaml``)
steers and sets the drive torque; the bag holds the topics the stack records: ``/vehicle/state``
(measured, noise and delays on), ``/sim/state`` (ground truth), ``/drift/command`` (the driver's
requests) and the run record (scenario, vehicle, seed, config), stamped in sim time.
``scripts/identify.py BAG --vehicle NAME`` fits the controller's model to it.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from drift_control import cli_args
from drift_control.params import ParamError, config_dir

TOPICS = (('/vehicle/state', 'drift_msgs/msg/VehicleState'),
          ('/sim/state', 'drift_msgs/msg/VehicleState'),
          ('/drift/command', 'drift_msgs/msg/DriftCommand'))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='sysid_dry', help='name under config/scenarios')
    parser.add_argument('--manoeuvre', help='config/sim/manoeuvres/<name>.yaml (default: the '
                        "scenario's driver.manoeuvre)")
    parser.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: the scenario\'s)')
    parser.add_argument('--seed', type=cli_args.seed, default=None, help='a seed >= 0')
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a scenario key (surface.mu=0.9, plant.measurement...)')
    parser.add_argument('--config-dir', default=str(config_dir()))
    parser.add_argument('--bag', required=True, help='bag directory to create')
    args = parser.parse_args(argv)

    from rclpy.serialization import serialize_message

    from drift_control.nodes.convert import command_to_msg, state_to_msg
    from drift_control.scenario import load_scenario_spec
    from drift_sim.manoeuvre import run_manoeuvre
    from drift_tools.bag_writer import BagExistsError, BagWriter
    from drift_tools.run_info import RECORD_NAME, collect

    problem = cli_args.output_problem(args.bag, directory=True)
    if problem is not None:
        print(f'sysid_drive: {problem}', file=sys.stderr)
        return 2
    try:
        spec = load_scenario_spec(args.scenario, args.set, args.config_dir, args.seed,
                                  args.vehicle)
        samples = run_manoeuvre(args.scenario, args.manoeuvre, args.seed, args.config_dir,
                                args.vehicle, args.set)
        writer = BagWriter(args.bag)
    except (ParamError, BagExistsError) as err:
        print(f'sysid_drive: {err}', file=sys.stderr)
        return 2
    wall0 = time.perf_counter()
    max_beta = 0.0
    with writer as bag:
        for topic, msgtype in TOPICS:
            bag.add_topic(topic, msgtype)
        bag.add_metadata(RECORD_NAME, collect(args.config_dir, scenario=spec.name,
                                              vehicle=spec.vehicle, seed=spec.seed,
                                              overrides=args.set, graph='sysid_drive',
                                              clock='sim', argv=sys.argv))
        t_end = 0.0
        for s in samples:
            ns = int(round(s.t * 1e9))
            bag.write('/vehicle/state', serialize_message(state_to_msg(s.measured, s.t)), ns)
            bag.write('/sim/state', serialize_message(state_to_msg(s.truth, s.t)), ns + 1)
            bag.write('/drift/command', serialize_message(command_to_msg(s.command, s.t)),
                      ns + 2)
            max_beta, t_end = max(max_beta, abs(s.truth.beta)), s.t
    print(f'sysid_drive: {spec.name} ({spec.vehicle}, seed {spec.seed}): {t_end:.0f} s '
          f'driven in {time.perf_counter() - wall0:.1f} s, max |beta| '
          f'{math.degrees(max_beta):.1f} deg -> {Path(args.bag)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
