"""The node graphs of ``config/stack.yaml`` and the command line and environment of each node.

``stack.yaml`` has a ``graphs:`` section (graph name -> node name -> Python module) and, beside
it, one ``<node name>: {ros__parameters: ...}`` section per node in ROS convention. Everything but
``graphs:`` is written to one ROS parameter file that every node gets with ``--params-file``; each
node is renamed to its graph name (``-r __node:=<name>``) so its section applies.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from drift_control.params import ParamError, load_yaml
from drift_tools.dds import transport_env

CLOCK_MODES = ('realtime', 'lockstep')
DISCOVERY_RANGES = ('LOCALHOST', 'SUBNET', 'SYSTEM_DEFAULT', 'OFF')
RECORDER_MODULE = 'drift_tools.nodes.recorder_node'
SIM_MODULE = 'drift_sim.nodes.sim_node'
ESTIMATOR_MODULE = 'drift_control.nodes.estimator_node'
BRIDGE_MODULE = 'drift_vehicle_bridge.nodes.bridge_node'
CAR_SENSORS = 'car'     # --sensors on a car: its own units through the bridge's sensor mode
# nodes whose ``set`` parameter takes scenario overrides (the bridge's takes bridge.yaml keys)
SCENARIO_MODULES = (SIM_MODULE, 'drift_control.nodes.reference_node',
                    'drift_control.nodes.nmpc_node', ESTIMATOR_MODULE)


@dataclass(frozen=True)
class NodeSpec:
    """One node of a graph: its ROS name, the module run with ``python -m``, and whether the
    graph stops when it dies (a recorder on a car must not end the drive)."""

    name: str
    module: str
    critical: bool = True


@dataclass(frozen=True)
class StackConfig:
    """The parsed ``stack.yaml``: graphs, per-node ROS parameters and who owns ``/clock``."""

    graphs: dict            # graph name -> tuple of NodeSpec, in start order
    node_params: dict       # node name -> {'ros__parameters': {...}} (ROS parameter-file layout)
    clock_owner: str = 'sim'   # node that publishes /clock in lockstep mode
    defaults: dict = field(default_factory=dict)   # run_stack defaults: scenario, clock

    def graph(self, name: str, only: list[str] | None = None) -> list[NodeSpec]:
        """The nodes of graph ``name``, optionally restricted to the names in ``only``."""
        if name not in self.graphs:
            raise ParamError(f'stack.graphs: no graph {name!r}; have {sorted(self.graphs)}')
        nodes = list(self.graphs[name])
        if only:
            known = {n.name for n in nodes}
            unknown = [n for n in only if n not in known]
            if unknown:
                raise ParamError(f'stack.graphs.{name}: no node(s) {unknown}; have {sorted(known)}')
            nodes = [n for n in nodes if n.name in only]
        return nodes


def load_stack(path: str | os.PathLike) -> StackConfig:
    """Read and validate ``stack.yaml``; every error names the key."""
    raw = load_yaml(path)
    graphs_raw = raw.get('graphs')
    if not isinstance(graphs_raw, dict) or not graphs_raw:
        raise ParamError(f'{path}: needs a non-empty "graphs:" mapping')
    graphs = {}
    for gname, nodes in graphs_raw.items():
        if not isinstance(nodes, dict) or not nodes:
            raise ParamError(f'stack.graphs.{gname}: expected a mapping node name -> module')
        specs = []
        for nname, entry in nodes.items():
            specs.append(_node_spec(f'stack.graphs.{gname}.{nname}', str(nname), entry))
        graphs[str(gname)] = tuple(specs)
    clock_owner = raw.get('clock_owner', 'sim')
    if not isinstance(clock_owner, str):
        raise ParamError(f'stack.clock_owner: expected a node name, got {clock_owner!r}')
    defaults = raw.get('defaults') or {}
    if not isinstance(defaults, dict):
        raise ParamError(f'stack.defaults: expected a mapping, got {defaults!r}')
    unknown = sorted(set(defaults) - {'scenario', 'clock'})
    if unknown:
        raise ParamError(f'stack.defaults: unknown key(s) {unknown}')
    if defaults.get('clock', 'realtime') not in CLOCK_MODES:
        raise ParamError(f'stack.defaults.clock: must be one of {list(CLOCK_MODES)}')
    if not isinstance(defaults.get('scenario', ''), str):
        raise ParamError('stack.defaults.scenario: expected a scenario name')
    node_params = {}
    for key, section in raw.items():
        if key in ('graphs', 'clock_owner', 'defaults'):
            continue
        if not isinstance(section, dict) or set(section) != {'ros__parameters'} \
                or not isinstance(section['ros__parameters'], dict):
            raise ParamError(f'stack.{key}: expected exactly "ros__parameters:" with a mapping')
        node_params[str(key)] = section
    return StackConfig(graphs, node_params, clock_owner, dict(defaults))


def _node_spec(key: str, name: str, entry) -> NodeSpec:
    """``module`` or ``{module: ..., critical: false}``."""
    if isinstance(entry, dict):
        unknown = sorted(set(entry) - {'module', 'critical'})
        if unknown:
            raise ParamError(f'{key}: unknown key(s) {unknown}; have module, critical')
        module, critical = entry.get('module'), entry.get('critical', True)
        if not isinstance(critical, bool):
            raise ParamError(f'{key}.critical: expected true or false, got {critical!r}')
    else:
        module, critical = entry, True
    if not isinstance(module, str) or not module:
        raise ParamError(f'{key}: expected a module name')
    return NodeSpec(name, module, critical)


def write_params_file(cfg: StackConfig, path: str | os.PathLike) -> Path:
    """Write the ROS parameter file (all per-node sections) every node is started with."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', encoding='utf-8') as fh:
        yaml.dump(cfg.node_params or {'/**': {'ros__parameters': {}}}, fh, Dumper=_NoAliases,
                  sort_keys=False)
    return path


class _NoAliases(yaml.SafeDumper):
    """rcl's parameter parser refuses YAML aliases: a value shared in stack.yaml is written out."""

    def ignore_aliases(self, data):
        return True


REFERENCE_MODULE = 'drift_control.nodes.reference_node'
NMPC_MODULE = 'drift_control.nodes.nmpc_node'
ESTIMATOR_PLACES = ('nmpc', 'node')


def with_estimator(nodes: list[NodeSpec], node_params: dict, place: str = 'nmpc') \
        -> list[NodeSpec]:
    """The graph with the estimator stage: the simulator then publishes its sensor samples, or
    a simulated car on a link sends them in its frames and the bridge publishes them.

    ``place='nmpc'``: estimator and selector run inside the NMPC node (one DDS hop from the
    samples to the command), the reference node leaves the graph; ``'node'``: an estimator
    node after the samples' source publishes the state for the reference and NMPC nodes. A
    graph without a simulator (a car) gets the car's own units from its bridge. ParamError for
    a graph with neither.
    """
    def on_link(n: NodeSpec) -> bool:
        return node_params.get(n.name, {}).get('ros__parameters', {}).get('io', 'ros') == 'link'

    sims = [n for n in nodes if n.module == SIM_MODULE]
    sources = [n for n in sims if not on_link(n)]
    if not sims or any(on_link(n) for n in sims):
        sources += [n for n in nodes if n.module == BRIDGE_MODULE]
    if not sources:
        raise ParamError('--sensors: the graph has neither a simulator nor a vehicle bridge')
    if place not in ESTIMATOR_PLACES:
        raise ParamError(f'estimator place {place!r} not in {list(ESTIMATOR_PLACES)}')
    if place == 'nmpc':
        if not any(n.module == NMPC_MODULE for n in nodes):
            raise ParamError('--estimator-in nmpc: the graph has no NMPC node')
        return [n for n in nodes if n.module != REFERENCE_MODULE]
    at = max(nodes.index(n) for n in sources) + 1
    return [*nodes[:at], NodeSpec('estimator', ESTIMATOR_MODULE), *nodes[at:]]


@dataclass(frozen=True)
class RunOptions:
    """What one launch shares between all nodes."""

    params_file: Path
    config_dir: Path
    scenario: str = ''                     # '' = not passed; nodes keep their default
    clock: str = 'realtime'                # 'realtime' or 'lockstep'
    bag_dir: Path | None = None            # recorder output; None = no recorder parameter
    domain_id: int = 0
    discovery_range: str = 'LOCALHOST'
    dds_shared_memory: bool = False        # True: rmw_fastrtps's own transports (drift_tools.dds)
    python: str = sys.executable
    sim_duration: float = 0.0              # simulated seconds the simulator runs; 0: scenario's
    vehicle: str = ''                      # '' = not passed; the scenario's, else the default
    seed: int | None = None                # simulator seed; None = not passed (the scenario's)
    overrides: tuple = ()                  # scenario overrides (--set) for sim and controller
    run_info_file: Path | None = None      # the run's settings, for the recorder to keep
    node_overrides: dict = field(default_factory=dict)   # node name -> {param: value} (-p)
    extra_params: dict = field(default_factory=dict)   # name -> value, for every node
    sensors: str = ''                      # the simulator's sensor set; '': its measured state
    estimator: str = 'ekf'                 # with sensors: 'ekf' or 'none' (newest samples)
    estimator_in: str = 'nmpc'             # with sensors: in the NMPC's process, or a 'node'
    sensor_set: tuple = ()                 # sensor set overrides key=value
    sensor_faults: tuple = ()              # unit[.channel]:kind:start:end[:value]
    estimator_set: tuple = ()              # config/estimator.yaml overrides key=value
    graph_nodes: tuple = ()                # the critical nodes' names: a recorded run starts
                                           # once the simulator sees every one of them

    def __post_init__(self):
        if self.clock not in CLOCK_MODES:
            raise ParamError(f'clock: must be one of {list(CLOCK_MODES)}, got {self.clock!r}')
        if self.discovery_range not in DISCOVERY_RANGES:
            raise ParamError(f'discovery range: must be one of {list(DISCOVERY_RANGES)}, '
                             f'got {self.discovery_range!r}')
        if not (self.sim_duration >= 0.0 and self.sim_duration < float('inf')):
            raise ParamError(f'sim duration: must be >= 0 s, got {self.sim_duration}')
        if not 0 <= self.domain_id <= 232:
            raise ParamError(f'ROS_DOMAIN_ID: must be in 0..232, got {self.domain_id}')


def _param_value(value) -> str:
    """A ``-p name:=value`` value as YAML, so strings stay strings (``''``, ``'1'``)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_param_value(v) for v in value) + ']'
    return "'" + str(value).replace("'", "''") + "'"


def node_command(spec: NodeSpec, opts: RunOptions, clock_owner: str = 'sim',
                 node_params: dict | None = None) -> list[str]:
    """The argv that starts ``spec`` as its own process.

    In lockstep mode every node but the clock owner runs on ``/clock`` (use_sim_time); the owner
    publishes it and is told so with ``clock_mode``.
    """
    owns_clock = spec.name == clock_owner
    params = {
        'use_sim_time': opts.clock == 'lockstep' and not owns_clock,
        'config_dir': str(opts.config_dir),
    }
    if opts.scenario:                # else each node keeps its own default
        params['scenario'] = opts.scenario
    if opts.vehicle:
        params['vehicle'] = opts.vehicle
    if owns_clock:
        params['clock_mode'] = opts.clock
    if spec.module == SIM_MODULE and opts.sim_duration:
        params['duration'] = float(opts.sim_duration)
    if spec.module == SIM_MODULE and opts.bag_dir is not None:
        params['wait_recorder'] = True   # no step before the bag records the truth
        others = [n for n in opts.graph_nodes if n != spec.name]
        if others:   # nor before the publishers of every node are known (and so compared)
            params['wait_nodes'] = others
    if spec.module == RECORDER_MODULE and opts.bag_dir is not None:
        params['bag_dir'] = str(opts.bag_dir)
        if opts.run_info_file is not None:
            params['run_info_file'] = str(opts.run_info_file)
    if spec.module == SIM_MODULE and opts.seed is not None:
        params['seed'] = int(opts.seed)
    if opts.overrides and spec.module in SCENARIO_MODULES:   # after the node's own stack.yaml set
        own = (node_params.get(spec.name, {}).get('ros__parameters', {}).get('set') or []) \
            if node_params else []
        params['set'] = [*own, *opts.overrides]
    if spec.module == SIM_MODULE and opts.sensors and opts.sensors != CAR_SENSORS:
        params['sensors'] = opts.sensors
        for name in ('sensor_set', 'sensor_faults'):
            if getattr(opts, name):
                params[name] = list(getattr(opts, name))
    if spec.module == BRIDGE_MODULE and opts.sensors:
        params['sensors'] = True
    in_nmpc = spec.module == NMPC_MODULE and opts.sensors and opts.estimator_in == 'nmpc'
    if in_nmpc:
        params['state_source'] = 'sensors'
    elif spec.module == NMPC_MODULE and opts.sensors:   # the estimator node's states
        params['stamped_states'] = True
    if spec.module == ESTIMATOR_MODULE or in_nmpc:
        params['estimator'] = opts.estimator
        if opts.estimator_set:
            params['estimator_set'] = list(opts.estimator_set)
    params.update(opts.extra_params)
    params.update(opts.node_overrides.get(spec.name, {}))
    argv = [opts.python, '-m', spec.module, '--ros-args', '-r', f'__node:={spec.name}',
            '--params-file', str(opts.params_file)]
    for name, value in params.items():
        argv += ['-p', f'{name}:={_param_value(value)}']
    return argv


def node_env(opts: RunOptions, base: dict | None = None) -> dict:
    """The child environment: ROS domain and discovery range always set, DDS over UDP
    (drift_tools.dds), output unbuffered."""
    env = dict(os.environ if base is None else base)
    env['ROS_DOMAIN_ID'] = str(opts.domain_id)
    transport_env(env, opts.discovery_range, opts.config_dir, opts.dds_shared_memory)
    env['PYTHONUNBUFFERED'] = '1'
    env['RCUTILS_LOGGING_BUFFERED_STREAM'] = '0'
    # The launcher prefixes the node name; keep ROS's own line short.
    env.setdefault('RCUTILS_CONSOLE_OUTPUT_FORMAT', '[{severity}] [{time}]: {message}')
    return env
