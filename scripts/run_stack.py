#!/usr/bin/env python3
"""Run a node graph of config/stack.yaml, each node its own process; optionally record a bag.

    .venv/bin/python scripts/run_stack.py --graph sim --duration 20 --bag runs/now
    .venv/bin/python scripts/run_stack.py --graph vehicle --nodes bridge,recorder --bag runs/car

The run ends at --duration (wall clock), on Ctrl-C or SIGTERM, or when the simulator's scenario
(or --sim-duration of sim time) is over; every node is then stopped cleanly. Exits non-zero if a
node crashes or must be killed.
With --bag, a summary read back from the bag is printed at the end.
"""
import argparse
import importlib.util
import json
import os
import sys
import tempfile
from pathlib import Path

from drift_control import cli_args
from drift_control.assembly import load_setup
from drift_control.params import ParamError, config_dir, parse_yaml, split_override, vehicle_file
from drift_tools.launcher import Launcher
from drift_control.estimator import ESTIMATORS
from drift_tools.stack import (CAR_SENSORS, CLOCK_MODES, DISCOVERY_RANGES, RECORDER_MODULE,
                               SIM_MODULE, ESTIMATOR_PLACES, RunOptions, load_stack, node_command, node_env,
                               with_estimator, write_params_file)




def node_overrides(items, nodes) -> dict:
    """``['nmpc.trigger=timer', ...]`` -> ``{'nmpc': {'trigger': 'timer'}}`` (values as YAML)."""
    import yaml
    names = {n.name for n in nodes}
    out = {}
    for item in items:
        key, sep, text = item.partition('=')
        node, dot, param = key.partition('.')
        if not sep or not dot or not node or not param:
            raise ParamError(f'-p {item!r}: expected NODE.PARAM=VALUE')
        if node not in names:
            raise ParamError(f'-p {item!r}: no node {node!r} in this graph; have {sorted(names)}')
        try:
            value = parse_yaml(text) if text else ''
        except yaml.YAMLError:
            raise ParamError(f'-p {item!r}: VALUE is not YAML') from None
        if value is None or isinstance(value, dict):
            raise ParamError(f'-p {item!r}: VALUE must be a number, bool, string or list')
        out.setdefault(node, {})[param] = value
    return out


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--graph', default='sim', help='graph of stack.yaml (default: sim)')
    p.add_argument('--nodes', default='', help='comma-separated subset of the graph\'s nodes')
    p.add_argument('--duration', type=cli_args.seconds, default=0.0,
                   help='stop after this many wall-clock seconds (0: until Ctrl-C or the '
                        'scenario\'s end)')
    p.add_argument('--sim-duration', type=cli_args.seconds, default=0.0,
                   help='simulated seconds the simulator runs before it ends the run '
                        '(default: the scenario\'s duration)')
    p.add_argument('--bag', type=Path, help='record to this rosbag2 (MCAP) directory')
    p.add_argument('--scenario', default=None,
                   help='scenario passed to every node (default: stack.yaml defaults.scenario)')
    p.add_argument('--vehicle', default=None,
                   help='vehicle passed to every node (default: the scenario\'s, else '
                        'config/defaults.yaml\'s)')
    p.add_argument('--seed', type=cli_args.seed, default=None,
                   help='simulator seed (friction field, noise, driver); default: the scenario\'s')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='scenario override for the simulator and the controller, as '
                        'simulate.py --set (repeatable)')
    p.add_argument('-p', '--param', action='append', default=[], metavar='NODE.PARAM=VALUE',
                   help='a ROS parameter of one node of the graph, VALUE in YAML (repeatable)')
    p.add_argument('--clock', choices=CLOCK_MODES, default=None,
                   help='lockstep: nodes use /clock, published by the clock owner (the sim); '
                        'default: stack.yaml defaults.clock, else realtime')
    p.add_argument('--config-dir', type=Path, default=None,
                   help='config directory (default: the checkout\'s config/)')
    p.add_argument('--stack', type=Path, default=None, help='stack file (default: CONFIG_DIR/stack.yaml)')
    p.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '0') or 0))
    p.add_argument('--discovery-range', choices=DISCOVERY_RANGES,
                   default=os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST'))
    p.add_argument('--dds-shared-memory', action='store_true',
                   help='let Fast DDS use shared memory (rmw default); without it the nodes talk '
                        'UDP, whose writes never wait on a reader (docs/dds.md)')
    p.add_argument('--kill-timeout', type=float, default=8.0,
                   help='seconds a node gets after SIGINT before SIGKILL')
    p.add_argument('--log-dir', type=Path, help='also write each node\'s output to DIR/<node>.log')
    p.add_argument('--no-summary', action='store_true', help='do not summarise the bag at the end')
    p.add_argument('--allow-infeasible', action='store_true',
                   help='start even if the path asks for a drift the car cannot hold')
    p.add_argument('--sensors', metavar='NAME', default='',
                   help='the simulator publishes the car\'s sensor units '
                        '(config/sim/sensors/NAME.yaml, e.g. realistic; on a link graph in the '
                        'frames, through the bridge) and an estimator between them and the '
                        'controller publishes the state (default: the plant\'s measured state, '
                        f'no estimator); {CAR_SENSORS!r}: on a car (--graph vehicle), its own '
                        'units through the bridge\'s sensor mode')
    p.add_argument('--estimator', choices=ESTIMATORS, default='ekf',
                   help='with --sensors: fuse them (ekf) or pass the newest samples (none)')
    p.add_argument('--estimator-in', choices=ESTIMATOR_PLACES, default='nmpc',
                   help='with --sensors: estimator and selector inside the NMPC node (one DDS '
                        'hop from the samples to the command; default), or an estimator node '
                        'before the reference and NMPC nodes (three hops)')
    p.add_argument('--sensor-set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a sensor key (ins.channels.beta.std=0.003)')
    p.add_argument('--sensor-fault', action='append', default=[], metavar='FAULT',
                   help='unit[.channel]:kind:start:end[:value], e.g. ins:dropout:30:31')
    p.add_argument('--estimator-set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a key of config/estimator.yaml')
    return p.parse_args(argv)


def check_sensors(args, cfg_dir: Path, simulated: bool) -> None:
    """The sensor set, its faults and the estimator's parameters, before any node starts;
    ``simulated``: the graph has a simulator (else the car's own sensors, ``--sensors car``)."""
    if not args.sensors:
        if args.sensor_set or args.sensor_fault or args.estimator_set:
            raise ParamError('--sensor-set, --sensor-fault and --estimator-set need --sensors')
        return
    from drift_control.estimator import load_estimator_params
    if not simulated:
        if args.sensors != CAR_SENSORS:
            raise ParamError(f'--sensors {args.sensors}: the graph has no simulator; the car\'s '
                             f'own sensor units are --sensors {CAR_SENSORS}')
        if args.sensor_set or args.sensor_fault:
            raise ParamError('--sensor-set and --sensor-fault simulate sensors: not on a car')
    elif args.sensors == CAR_SENSORS:
        raise ParamError(f'--sensors {CAR_SENSORS}: the graph simulates the car; name a sensor '
                         'set of config/sim/sensors (e.g. realistic)')
    else:
        from drift_sim.sensors import load_sensor_params, parse_fault
        load_sensor_params(args.sensors, cfg_dir, args.sensor_set)
        for fault in args.sensor_fault:
            parse_fault(fault)
    if args.estimator == 'ekf':
        load_estimator_params(cfg_dir / 'estimator.yaml', args.estimator_set)


def _importable(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ImportError:          # a parent package is missing
        return False


def main(argv=None) -> int:
    args = parse_args(argv)
    cfg_dir = (args.config_dir or config_dir()).resolve()
    try:
        if args.vehicle:
            vehicle_file(args.vehicle, cfg_dir)   # an unknown vehicle: one line, before any node
        stack = load_stack(args.stack or cfg_dir / 'stack.yaml')
        nodes = stack.graph(args.graph, [n for n in args.nodes.split(',') if n])
        check_sensors(args, cfg_dir, any(n.module == SIM_MODULE for n in nodes))
        if args.sensors:   # the estimator stage between the simulator and the controller
            nodes = with_estimator(nodes, stack.node_params, args.estimator_in)
        clock = args.clock or stack.defaults.get('clock', 'realtime')
        if clock == 'lockstep' and stack.clock_owner not in {n.name for n in nodes}:
            if args.clock == 'lockstep':   # nobody would publish /clock: no timer ever fires
                raise ParamError(f'--clock lockstep: graph {args.graph!r} has no clock owner '
                                 f'{stack.clock_owner!r} (stack.yaml clock_owner) to publish '
                                 '/clock; use --clock realtime')
            clock = 'realtime'
            print(f'[launch] graph {args.graph!r} has no clock owner: real time', file=sys.stderr)
        if args.bag is not None:
            args.bag = args.bag.resolve()
            if (args.bag / 'metadata.yaml').exists():
                raise ParamError(f'--bag {args.bag}: a bag is already there')
            try:
                args.bag.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise ParamError(f'--bag {args.bag}: cannot create it ({err.strerror})') from None
            if not os.access(args.bag, os.W_OK):
                raise ParamError(f'--bag {args.bag}: not writable')
        elif any(n.module == RECORDER_MODULE for n in nodes):
            print('[launch] no --bag given: not starting the recorder', file=sys.stderr)
            nodes = [n for n in nodes if n.module != RECORDER_MODULE]
        params_dir = args.bag or Path(tempfile.mkdtemp(prefix='drift_stack_'))
        for item in args.set:
            split_override(item)                      # KEY=VALUE, else one line
        per_node = node_overrides(args.param, nodes)
        scenario = stack.defaults.get('scenario', '') if args.scenario is None else args.scenario
        run_info = None
        if args.bag is not None:
            from drift_tools.run_info import collect
            run_info = params_dir / 'run_info.json'
            run_info.write_text(json.dumps(collect(
                cfg_dir, scenario=scenario, vehicle=args.vehicle or '', seed=args.seed,
                overrides=args.set, graph=args.graph, clock=clock,
                sensors=args.sensors,
                estimator=f'{args.estimator} in {args.estimator_in}' if args.sensors else '',
                sensor_faults=args.sensor_fault,
                argv=[sys.executable, *sys.argv] if argv is None else ['run_stack.py', *argv])))
        opts = RunOptions(params_file=write_params_file(stack, params_dir / 'stack_params.yaml'),
                          config_dir=cfg_dir,
                          scenario=scenario, seed=args.seed, overrides=tuple(args.set),
                          run_info_file=run_info, node_overrides=per_node,
                          clock=clock,
                          bag_dir=args.bag, domain_id=args.domain_id,
                          sim_duration=args.sim_duration,
                          vehicle=args.vehicle or '',
                          discovery_range=args.discovery_range,
                          dds_shared_memory=args.dds_shared_memory,
                          sensors=args.sensors, estimator=args.estimator,
                          estimator_in=args.estimator_in,
                          sensor_set=tuple(args.sensor_set),
                          sensor_faults=tuple(args.sensor_fault),
                          estimator_set=tuple(args.estimator_set),
                          graph_nodes=tuple(n.name for n in nodes if n.critical))
        if args.sim_duration and not any(n.module == SIM_MODULE for n in nodes):
            raise ParamError(f'--sim-duration: graph {args.graph!r} has no simulator to end it')
        if opts.scenario:   # the controller's configuration and map, checked before any node
            setup = load_setup(cfg_dir, opts.scenario, opts.vehicle or None, opts.overrides)
            if not args.allow_infeasible:
                setup.check_reference()
            if any(n.module == SIM_MODULE for n in nodes):   # and the simulator's car
                from drift_sim.scenario import load_scenario
                load_scenario(opts.scenario, list(opts.overrides), config=cfg_dir,
                              spec=setup.scenario)
        elif args.set:
            raise ParamError('--set: needs a scenario (--scenario or stack.yaml defaults)')
    except ParamError as err:
        print(f'run_stack: {err}', file=sys.stderr)
        return 2
    if not nodes:
        print('run_stack: no nodes to start', file=sys.stderr)
        return 2
    missing = [f'{n.name} ({n.module})' for n in nodes if not _importable(n.module)]
    if missing:
        print(f'run_stack: node module(s) not found: {", ".join(missing)}', file=sys.stderr)
        return 2

    if any(n.module == SIM_MODULE for n in nodes):
        print('[launch] state: ' + (f'sensors {args.sensors} -> estimator {args.estimator} '
                                    f'in {args.estimator_in}' if args.sensors
                                    else 'the plant\'s measured state'))
    launcher = Launcher(kill_timeout=args.kill_timeout)
    launcher.install_signal_handlers()
    env = node_env(opts)
    if args.log_dir:
        args.log_dir.mkdir(parents=True, exist_ok=True)
    # The recorder first, so it is subscribed before the others publish; and stopped last.
    for spec in sorted(nodes, key=lambda n: n.module != RECORDER_MODULE):
        launcher.start(spec.name, node_command(spec, opts, stack.clock_owner, stack.node_params),
                       env,
                       stop_last=spec.module == RECORDER_MODULE,
                       log_path=args.log_dir / f'{spec.name}.log' if args.log_dir else None,
                       critical=spec.critical)
    outcome = launcher.wait(args.duration or None)
    codes = ', '.join(f'{name}={rc}' for name, rc in outcome.returncodes.items())
    print(f'[launch] stopped ({outcome.reason}); exit codes: {codes}'
          + (f'; killed: {outcome.killed}' if outcome.killed else '')
          + (f'; died during the run: {outcome.lost}' if outcome.lost else ''))
    if args.bag is not None and not args.no_summary and (args.bag / 'metadata.yaml').exists():
        from drift_tools.summary import format_summary, summarize_bag
        print(format_summary(summarize_bag(args.bag)))
    return outcome.exit_code


if __name__ == '__main__':
    sys.exit(main())
