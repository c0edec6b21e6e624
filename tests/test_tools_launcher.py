"""Launcher and stack config in-process, with plain Python children (no ROS needed)."""
import ast
import dataclasses
import io
import json
import os
import subprocess
import sys
import threading
import time

import pytest
import yaml

from conftest import REPO
from drift_control.params import ParamError
from drift_tools.launcher import Launcher
from drift_tools.stack import (RECORDER_MODULE, NodeSpec, RunOptions, load_stack, node_command,
                               node_env, write_params_file)

CHILD = r'''
import signal, sys, time
mode, delay = sys.argv[1], float(sys.argv[2])
def stop(signum, frame):
    raise KeyboardInterrupt
signal.signal(signal.SIGTERM, stop)
if mode == "ignore":
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
if mode == "hang":   # a node process (stops.install) whose stop never comes through
    from drift_control.nodes import stops
    stops.install()
    def stuck_in_a_callback():
        time.sleep(3600)
    print("up", flush=True)
    stuck_in_a_callback()
print("up", flush=True)   # its SIGTERM handling is in place
if mode in ("crash", "finish"):
    time.sleep(delay)
    print("leaving", flush=True)
    sys.exit(7 if mode == "crash" else 0)
try:
    while True:
        time.sleep(0.02)
except KeyboardInterrupt:
    time.sleep(delay)
    print("got SIGTERM", flush=True)
'''


def child(mode, delay=0.0):
    return [sys.executable, '-c', CHILD, mode, str(delay)]


def run(children, duration=None, kill_timeout=5.0, stop_after=None, optional=()):
    out = io.StringIO()
    launcher = Launcher(out=out, colour=False, kill_timeout=kill_timeout)
    for name, argv, last in children:
        launcher.start(name, argv, env=None, stop_last=last, critical=name not in optional)
    # the timings count from when every child handles SIGTERM (a loaded machine starts Python
    # slowly: a signal before that kills it silently, and the test would judge the machine)
    deadline = time.monotonic() + 30.0
    while not all(any(line.startswith(f'[{name}]') and line.endswith(' up')
                      for line in out.getvalue().splitlines()) for name, _, _ in children):
        assert time.monotonic() < deadline, 'children did not come up'
        time.sleep(0.01)
    if stop_after is not None:
        threading.Timer(stop_after, launcher.request_stop).start()
    t0 = time.monotonic()
    outcome = launcher.wait(duration)
    return outcome, time.monotonic() - t0, out.getvalue().splitlines()


def test_duration_is_respected_and_nodes_stop_cleanly():
    outcome, elapsed, lines = run([('a', child('run'), False), ('bb', child('run'), False)],
                                  duration=1.0)
    assert outcome.reason == 'duration' and outcome.ok and outcome.exit_code == 0
    assert 1.0 <= elapsed < 4.0
    assert '[a]  got SIGTERM' in lines and '[bb] got SIGTERM' in lines   # prefixed, aligned
    assert outcome.returncodes == {'a': 0, 'bb': 0}


def test_a_crashing_node_stops_the_rest_and_fails_the_run():
    outcome, elapsed, lines = run([('ok', child('run'), False), ('bad', child('crash', 0.3), False)],
                                  duration=30.0)
    assert outcome.reason == 'node-crash' and outcome.failed_node == 'bad'
    assert not outcome.ok and outcome.exit_code == 7
    assert elapsed < 5.0 and '[ok]  got SIGTERM' in lines


def test_a_non_critical_node_dying_is_reported_and_the_rest_runs_on():
    outcome, elapsed, lines = run([('ctl', child('run'), False), ('rec', child('crash', 0.2), True)],
                                  duration=1.5, optional=('rec',))
    assert outcome.reason == 'duration' and elapsed >= 1.5, 'the run must go on'
    assert outcome.lost == ['rec'] and outcome.returncodes == {'ctl': 0, 'rec': 7}
    assert not outcome.ok and outcome.exit_code == 7          # the exit code still says so
    assert any('rec exited with code 7; it is not critical' in line for line in lines)
    assert '[ctl] got SIGTERM' in lines


def test_a_node_finishing_normally_ends_the_run_ok():
    outcome, _, _ = run([('ok', child('run'), False), ('done', child('finish', 0.3), False)],
                        duration=30.0)
    assert outcome.reason == 'node-exit' and outcome.ok and outcome.exit_code == 0


def test_stop_request_is_forwarded_recorder_last():
    outcome, elapsed, lines = run([('rec', child('run'), True), ('node', child('run', 0.5), False)],
                                  stop_after=0.8)
    assert outcome.reason == 'signal' and outcome.ok and elapsed < 4.0
    got = [line for line in lines if line.startswith('[') and line.endswith('got SIGTERM')]
    assert got == ['[node] got SIGTERM', '[rec]  got SIGTERM'], 'the recorder must stop after the rest'


def test_a_node_ignoring_sigterm_is_killed_and_fails_the_run():
    outcome, elapsed, lines = run([('stubborn', child('ignore'), False)], duration=0.5,
                                  kill_timeout=0.7)
    assert outcome.killed == ['stubborn'] and not outcome.ok and outcome.exit_code == 1
    assert 1.1 <= elapsed < 4.0
    assert any('SIGKILL' in line for line in lines)


def test_a_hung_node_logs_its_stacks_before_the_sigkill():
    outcome, _, lines = run([('hung', child('hang'), False)], duration=0.3, kill_timeout=0.5)
    assert outcome.killed == ['hung'] and not outcome.ok
    text = '\n'.join(lines)
    assert 'its stacks, then SIGKILL' in text
    assert 'in stuck_in_a_callback' in text, text   # the hung frame, named in the log


def test_second_interrupt_kills_without_waiting():
    import os
    import signal
    launcher = Launcher(out=io.StringIO(), colour=False, kill_timeout=30.0)
    saved = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]
    try:
        launcher.install_signal_handlers()
        launcher.start('stubborn', child('ignore'), env=None)
        for delay in (0.5, 1.0):
            threading.Timer(delay, os.kill, (os.getpid(), signal.SIGINT)).start()
        t0 = time.monotonic()
        outcome = launcher.wait()
    finally:
        signal.signal(signal.SIGINT, saved[0])
        signal.signal(signal.SIGTERM, saved[1])
    assert outcome.reason == 'signal' and outcome.killed == ['stubborn']
    assert time.monotonic() - t0 < 5.0, 'the second Ctrl-C must not wait for kill_timeout'


def test_node_output_is_logged_to_a_file(tmp_path):
    launcher = Launcher(out=io.StringIO(), colour=False)
    launcher.start('n', child('finish', 0.1), env=None, log_path=tmp_path / 'n.log')
    launcher.wait(10.0)
    assert (tmp_path / 'n.log').read_text().splitlines() == ['up', 'leaving']


ORPHAN = r'''
import sys, time
from drift_tools.launcher import Launcher
launcher = Launcher(colour=False)
proc = launcher.start('n', sys.argv[1:], env=None)
time.sleep(1.0)       # the child has printed 'up' and goes quiet: no broken pipe to end it
print('child', proc.popen.pid, flush=True)
time.sleep(60)
'''


def test_nodes_do_not_outlive_a_killed_launcher():
    import os
    import subprocess
    parent = subprocess.Popen([sys.executable, '-c', ORPHAN, *child('run')],
                              stdout=subprocess.PIPE, text=True)
    line = parent.stdout.readline()
    while not line.startswith('child'):
        line = parent.stdout.readline()
    pid = int(line.split()[1])
    parent.kill()
    parent.wait(10)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        try:
            with open(f'/proc/{pid}/stat') as fh:
                if fh.read().rsplit(')', 1)[1].split()[0] == 'Z':   # dead, not yet reaped
                    return
        except FileNotFoundError:
            return
        time.sleep(0.05)
    os.kill(pid, 9)
    raise AssertionError('the node outlived its killed launcher')


# --- stack.yaml -------------------------------------------------------------------------------

def test_project_stack_graphs():
    cfg = load_stack(REPO / 'config' / 'stack.yaml')
    assert [n.module for n in cfg.graph('sim')] == [
        'drift_sim.nodes.sim_node', 'drift_control.nodes.reference_node',
        'drift_control.nodes.nmpc_node', RECORDER_MODULE]
    assert [n.name for n in cfg.graph('vehicle')] == ['bridge', 'reference', 'nmpc', 'recorder']
    assert [n.name for n in cfg.graph('vehicle') if not n.critical] == ['recorder']
    assert all(n.critical for n in cfg.graph('sim'))     # a sim run without its bag is no run
    assert [n.name for n in cfg.graph('sim', ['nmpc', 'sim'])] == ['sim', 'nmpc']
    with pytest.raises(ParamError, match='graphs: no graph .car.'):
        cfg.graph('car')
    with pytest.raises(ParamError, match=r"no node\(s\) \['planner'\]"):
        cfg.graph('sim', ['planner'])


@pytest.mark.parametrize('text, key', [
    ('nodes: {}', 'graphs'),
    ('graphs: {sim: {sim: 3}}', 'stack.graphs.sim.sim'),
    ('graphs: {sim: {sim: {module: m, critical: maybe}}}', 'stack.graphs.sim.sim.critical'),
    ('graphs: {sim: {sim: {module: m, optional: true}}}', r"stack.graphs.sim.sim: unknown key\(s\) \['optional'\]"),
    ('graphs: {sim: {sim: m}}\nsim: {rate: 1}', 'stack.sim'),
    ('graphs: {sim: {sim: m}}\ndefaults: {clock: fast}', 'stack.defaults.clock'),
    ('graphs: {sim: {sim: m}}\ndefaults: {duration: 3}', 'stack.defaults'),
])
def test_stack_errors_name_the_key(tmp_path, text, key):
    (tmp_path / 'stack.yaml').write_text(text)
    with pytest.raises(ParamError, match=key):
        load_stack(tmp_path / 'stack.yaml')


def test_params_file_is_the_ros_layout_without_graphs(tmp_path):
    cfg = load_stack(REPO / 'config' / 'stack.yaml')
    raw = yaml.safe_load(write_params_file(cfg, tmp_path / 'p.yaml').read_text())
    assert 'graphs' not in raw and 'clock_owner' not in raw
    assert all(set(section) == {'ros__parameters'} for section in raw.values())


def _params(argv):
    return dict(argv[i + 1].split(':=', 1) for i, a in enumerate(argv) if a == '-p')


@pytest.mark.parametrize('clock', ['realtime', 'lockstep'])
def test_node_command_and_clock_ownership(tmp_path, clock):
    opts = RunOptions(params_file=tmp_path / 'p.yaml', config_dir=tmp_path, scenario="it's",
                      clock=clock, bag_dir=tmp_path / 'bag', python='py')
    sim = node_command(NodeSpec('sim', 'drift_sim.nodes.sim_node'), opts, clock_owner='sim')
    rec = node_command(NodeSpec('recorder', RECORDER_MODULE), opts, clock_owner='sim')
    assert sim[:5] == ['py', '-m', 'drift_sim.nodes.sim_node', '--ros-args', '-r']
    assert '__node:=sim' in sim and sim[sim.index('--params-file') + 1] == str(tmp_path / 'p.yaml')
    p_sim, p_rec = _params(sim), _params(rec)
    assert p_sim['use_sim_time'] == 'false' and p_sim['clock_mode'] == f"'{clock}'"
    assert p_rec['use_sim_time'] == ('true' if clock == 'lockstep' else 'false')
    assert yaml.safe_load(p_rec['scenario']) == "it's"
    assert yaml.safe_load(p_rec['bag_dir']) == str(tmp_path / 'bag') and 'bag_dir' not in p_sim


def test_the_estimator_stage_follows_the_samples_source_and_gets_the_sensors(tmp_path):
    from drift_tools.stack import ESTIMATOR_MODULE, NMPC_MODULE, with_estimator
    cfg = load_stack(REPO / 'config' / 'stack.yaml')
    # in the NMPC's process with the selector (one hop), or a node of its own (three)
    assert [n.name for n in with_estimator(cfg.graph('sim'), cfg.node_params)] == [
        'sim', 'nmpc', 'recorder']
    nodes = with_estimator(cfg.graph('sim'), cfg.node_params, 'node')
    assert [n.name for n in nodes] == ['sim', 'estimator', 'reference', 'nmpc', 'recorder']
    # a car: its own units from the bridge
    assert [n.name for n in with_estimator(cfg.graph('vehicle'), cfg.node_params)] == [
        'bridge', 'nmpc', 'recorder']
    with pytest.raises(ParamError, match='neither a simulator nor a vehicle bridge'):
        with_estimator([NodeSpec('nmpc', NMPC_MODULE)], cfg.node_params)
    # a simulated car on a link: the samples come from the bridge, the estimator after it
    assert [n.name for n in with_estimator(cfg.graph('sim_can'), cfg.node_params, 'node')] == [
        'can_car', 'can_bridge', 'estimator', 'reference', 'can_nmpc', 'recorder']
    p_bridge = _params(node_command(NodeSpec('b', 'drift_vehicle_bridge.nodes.bridge_node'),
                                    RunOptions(params_file=tmp_path, config_dir=tmp_path,
                                               sensors='realistic')))
    assert yaml.safe_load(p_bridge['sensors']) is True
    opts = RunOptions(params_file=tmp_path / 'p.yaml', config_dir=tmp_path, scenario='s',
                      overrides=('surface.mu=0.9',), sensors='realistic', estimator='none',
                      sensor_faults=('ins:dropout:1:2',), estimator_in='node')
    p_sim = _params(node_command(NodeSpec('sim', 'drift_sim.nodes.sim_node'), opts))
    p_est = _params(node_command(NodeSpec('estimator', ESTIMATOR_MODULE), opts))
    assert yaml.safe_load(p_sim['sensors']) == 'realistic'
    assert yaml.safe_load(p_sim['sensor_faults']) == ['ins:dropout:1:2']
    assert yaml.safe_load(p_est['estimator']) == 'none' and 'sensors' not in p_est
    assert yaml.safe_load(p_est['set']) == ['surface.mu=0.9']
    p_nmpc = _params(node_command(NodeSpec('nmpc', NMPC_MODULE), opts))
    assert 'state_source' not in p_nmpc
    assert yaml.safe_load(p_nmpc['stamped_states']) is True, "the estimator node's states"
    p_nmpc = _params(node_command(NodeSpec('nmpc', NMPC_MODULE),
                                  dataclasses.replace(opts, estimator_in='nmpc')))
    assert yaml.safe_load(p_nmpc['state_source']) == 'sensors'
    assert yaml.safe_load(p_nmpc['estimator']) == 'none'
    plain = _params(node_command(NodeSpec('sim', 'drift_sim.nodes.sim_node'),
                                 RunOptions(params_file=tmp_path, config_dir=tmp_path)))
    assert 'sensors' not in plain, 'the default graph: the simulator as it was'
    assert 'stamped_states' not in _params(node_command(
        NodeSpec('nmpc', NMPC_MODULE), RunOptions(params_file=tmp_path, config_dir=tmp_path)))


def test_an_empty_scenario_is_not_passed(tmp_path):
    opts = RunOptions(params_file=tmp_path / 'p.yaml', config_dir=tmp_path)
    assert 'scenario' not in _params(node_command(NodeSpec('nmpc', 'm'), opts))
    cfg = load_stack(REPO / 'config' / 'stack.yaml')
    assert cfg.defaults['clock'] in ('realtime', 'lockstep')
    assert (REPO / 'config' / 'scenarios' / f"{cfg.defaults['scenario']}.yaml").is_file()


def test_child_env_always_sets_domain_and_discovery(tmp_path):
    opts = RunOptions(params_file=tmp_path, config_dir=tmp_path, domain_id=17)
    env = node_env(opts, base={'ROS_DOMAIN_ID': '3', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'})
    # a config without the DDS profile: rmw's own LOCALHOST
    assert env['ROS_DOMAIN_ID'] == '17' and env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in env
    with pytest.raises(ParamError, match='clock'):
        RunOptions(params_file=tmp_path, config_dir=tmp_path, clock='fast')


def test_core_modules_do_not_import_rclpy():
    core = [p for p in (REPO / 'src' / 'drift_tools' / 'drift_tools').glob('*.py')]
    assert core, 'drift_tools has no modules?'
    for path in core:
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ''] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.split('.')[0] == 'rclpy' for n in names), f'{path.name} imports rclpy'


def test_seed_overrides_and_node_parameters_reach_their_nodes(tmp_path):
    cfg = load_stack(REPO / 'config' / 'stack.yaml')
    opts = RunOptions(params_file=tmp_path / 'p.yaml', config_dir=tmp_path, scenario='s',
                      bag_dir=tmp_path / 'bag', seed=4, overrides=('surface.mu=0.9',),
                      run_info_file=tmp_path / 'bag' / 'run_info.json',
                      node_overrides={'nmpc': {'trigger': 'timer', 'max_input_age': 0.1}})
    sim, nmpc, rec, can_car = (
        _params(node_command(NodeSpec(name, module), opts, 'sim', cfg.node_params))
        for name, module in (('sim', 'drift_sim.nodes.sim_node'),
                             ('nmpc', 'drift_control.nodes.nmpc_node'),
                             ('recorder', RECORDER_MODULE),
                             ('can_car', 'drift_sim.nodes.sim_node')))
    assert sim['seed'] == '4' and 'seed' not in nmpc
    assert yaml.safe_load(sim['set']) == ['surface.mu=0.9'] == yaml.safe_load(nmpc['set'])
    # a node's own stack.yaml overrides stay, the command line's come after them
    assert yaml.safe_load(can_car['set']) == ['plant.steering.driver_share=0.0', 'surface.mu=0.9']
    assert nmpc['trigger'] == "'timer'" and nmpc['max_input_age'] == '0.1'
    assert 'trigger' not in sim and yaml.safe_load(rec['run_info_file']).endswith('run_info.json')
    assert 'set' not in rec


@pytest.mark.parametrize('argv, says', [
    (['-p', 'foo=1'], "-p 'foo=1': expected NODE.PARAM=VALUE"),
    (['-p', 'planner.x=1'], "no node 'planner' in this graph"),
    (['-p', 'nmpc.x={a: 1}'], 'VALUE must be a number, bool, string or list'),
    (['--set', 'surface.mu'], "override 'surface.mu': expected key=value"),
    (['--set', 'bogus.key=1'], "unknown key(s) ['bogus']"),
    (['--seed', '-2'], 'expected an integer >= 0'),
])
def test_run_stack_settings_errors_are_one_line(capsys, argv, says):
    from conftest import load_script
    try:
        rc = load_script('run_stack').main([*argv, '--duration', '1'])
    except SystemExit as ended:      # argparse's own refusals
        rc = ended.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and says in err[-1], err


@pytest.mark.parametrize('argv, message', [
    (['--graph', 'vehicle', '--sensors', 'realistic'],
     "--sensors realistic: the graph has no simulator; the car's own sensor units are "
     "--sensors car"),
    (['--graph', 'sim', '--sensors', 'car'],
     '--sensors car: the graph simulates the car; name a sensor set'),
    (['--graph', 'vehicle', '--sensors', 'car', '--sensor-fault', 'ins:dropout:1:2'],
     '--sensor-set and --sensor-fault simulate sensors: not on a car'),
])
def test_run_stack_sensors_match_the_graph_in_one_line(argv, message, capsys):
    from conftest import load_script
    assert load_script('run_stack').main([*argv, '--duration', '1']) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f'run_stack: {message}'), err
    assert len(err.splitlines()) == 1


def test_a_recorded_run_waits_for_every_critical_node_of_the_launch(tmp_path):
    opts = RunOptions(params_file=tmp_path / 'p.yaml', config_dir=tmp_path,
                      bag_dir=tmp_path / 'bag', graph_nodes=('recorder', 'sim', 'nmpc'))
    p_sim = _params(node_command(NodeSpec('sim', 'drift_sim.nodes.sim_node'), opts))
    assert yaml.safe_load(p_sim['wait_nodes']) == ['recorder', 'nmpc']
    p_rec = _params(node_command(NodeSpec('recorder', 'drift_tools.nodes.recorder_node'), opts))
    assert 'wait_nodes' not in p_rec
    unrecorded = dataclasses.replace(opts, bag_dir=None)
    assert 'wait_nodes' not in _params(node_command(NodeSpec('sim', 'drift_sim.nodes.sim_node'),
                                                    unrecorded))


def test_nodes_talk_dds_over_udp_unless_told_otherwise(tmp_path):
    """LOCALHOST through the loopback-UDP profile, SUBNET with Fast DDS's UDP transport only; a
    profile or transport the user chose, another RMW, or --dds-shared-memory is left alone."""
    config = REPO / 'config'
    profile = (config / 'dds' / 'localhost_udp.xml').resolve()

    def env_for(base=None, **kw):
        return node_env(RunOptions(params_file=tmp_path, config_dir=config, **kw), base=base or {})

    env = env_for()
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SYSTEM_DEFAULT'
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(profile)
    env = env_for(discovery_range='SUBNET')
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    assert env['FASTDDS_BUILTIN_TRANSPORTS'] == 'UDPv4'
    for base, kw in (({'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}, {}),
                     ({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}, {}),
                     ({}, {'dds_shared_memory': True})):
        env = env_for(base, **kw)
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST', (base, kw)
        profile_var = 'FASTRTPS_DEFAULT_PROFILES_FILE'
        assert env.get(profile_var) == base.get(profile_var)
        assert 'FASTDDS_BUILTIN_TRANSPORTS' not in env


@pytest.mark.ros
def test_a_launched_node_talks_to_a_localhost_peer_over_loopback_udp_only(tmp_path,
                                                                         tools_domain_id):
    """A node with the launcher's environment is heard by a plain LOCALHOST process and maps no
    Fast DDS shared memory; its sockets are on 127.0.0.1 only."""
    plain = dict(os.environ)
    launched = node_env(RunOptions(params_file=tmp_path, config_dir=REPO / 'config',
                                   domain_id=tools_domain_id), base=plain)
    probe = [sys.executable, str(REPO / 'tests' / 'dds_probe.py')]
    reader = subprocess.Popen(probe + ['reader'], env=plain, stdout=subprocess.PIPE, text=True)
    writer = subprocess.run(probe + ['writer'], env=launched, capture_output=True, text=True,
                            timeout=30)
    out, _ = reader.communicate(timeout=30)
    assert writer.returncode == 0, writer.stderr
    said = json.loads(writer.stdout.strip().splitlines()[-1])
    assert said['matched'] == 1 and json.loads(out.strip().splitlines()[-1])['received'] >= 20
    assert said['shm'] == [], 'the launched node mapped Fast DDS shared memory'
    assert said['udp'] and set(said['udp']) == {'127.0.0.1'}, said['udp']
