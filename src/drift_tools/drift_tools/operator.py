"""``drift``: the operator's command line (PyPI has no ros2cli). One entry point, subcommands:

    drift arm | disarm | status              the vehicle bridge: arm, release, its diagnostics
    drift topic list | echo | hz | pub       live topics
    drift service call SERVICE TYPE [YAML]   any service
    drift param list | get | set NODE ...    node parameters
    drift bag info | recover | slice | export   recorded runs (read only; export: CSV or MDF4)
    drift probe                              the car's link: PDUs seen, rates, E2E states

Exit codes: 0 done, 1 refused or nothing heard (the reason on stderr), 2 bad input. Uses
ROS_DOMAIN_ID from the environment; ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

import yaml

from drift_control.cli_args import natural, output_problem, positive, seconds


class CliError(Exception):
    """A refusal with its one-line reason and exit code."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


# --- messages ---------------------------------------------------------------------------------

def interface_class(name: str, kind: str = 'msg'):
    """``pkg/msg/Name`` (or ``pkg/Name``) -> the generated class; ``kind`` msg or srv."""
    parts = name.strip('/').split('/')
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or parts[1] != kind:
        raise CliError(f'{name!r} is not a {kind} type name (pkg/{kind}/Name)', 2)
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{kind}'), parts[2])
    except (ImportError, AttributeError):
        raise CliError(f'{kind} type {name} is not installed here', 2) from None


def to_plain(msg):
    """A message as nested dicts and lists (for YAML output)."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {name: to_plain(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or type(msg).__name__ in ('ndarray', 'array'):
        return [to_plain(x) for x in msg]
    if isinstance(msg, bytes):
        return list(msg)
    if hasattr(msg, 'item'):          # numpy scalar
        return msg.item()
    return msg


def fill(msg, values: dict, where: str = ''):
    """Set ``msg``'s fields from a (nested) dict; an unknown field is a CliError naming it."""
    if not isinstance(values, dict):
        raise CliError(f'{where or "message"}: expected a mapping of fields, got {values!r}', 2)
    fields = msg.get_fields_and_field_types()
    for key, value in values.items():
        if key not in fields:
            raise CliError(f'{where}{key}: no such field; have {sorted(fields)}', 2)
        current = getattr(msg, key)
        try:
            if hasattr(current, 'get_fields_and_field_types'):
                fill(current, value, f'{where}{key}.')
            else:
                setattr(msg, key, _coerce(fields[key], value, f'{where}{key}'))
        except (TypeError, ValueError, AssertionError) as err:
            raise CliError(f'{where}{key}: {err}', 2) from None
    return msg


_INT_BITS = {'int8': 8, 'int16': 16, 'int32': 32, 'int64': 64, 'uint8': 8, 'uint16': 16,
             'uint32': 32, 'uint64': 64, 'byte': 8, 'octet': 8, 'char': 8}


def _coerce(kind: str, value, where: str):
    """``value`` checked against a field type of ``get_fields_and_field_types`` (rclpy's own
    checks are off by default: a string would silently become True in a bool field)."""
    if kind.startswith('sequence<') or kind.endswith(']'):
        inner = kind[len('sequence<'):].split('>')[0].split(',')[0] if kind.startswith(
            'sequence<') else kind[:kind.index('[')]
        if not isinstance(value, list):
            raise CliError(f'{where}: expected a list for {kind}, got {value!r}', 2)
        return [_coerce(inner, v, f'{where}[{i}]') for i, v in enumerate(value)]
    if kind == 'boolean':
        if not isinstance(value, bool):
            raise CliError(f'{where}: expected true or false, got {value!r}', 2)
        return value
    if kind in ('float', 'double'):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CliError(f'{where}: expected a number, got {value!r}', 2)
        return float(value)
    if kind in _INT_BITS:
        if isinstance(value, bool) or not isinstance(value, int):
            raise CliError(f'{where}: expected an integer, got {value!r}', 2)
        bits, signed = _INT_BITS[kind], kind.startswith('int')
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        if not lo <= value <= hi:
            raise CliError(f'{where}: {value} outside {kind} [{lo}, {hi}]', 2)
        return value
    if kind.startswith(('string', 'wstring')):
        if not isinstance(value, str):
            raise CliError(f'{where}: expected a string, got {value!r}', 2)
    return value


def parse_yaml(text: str, what: str):
    try:
        value = yaml.safe_load(text) if text else {}
    except yaml.YAMLError as err:
        raise CliError(f'{what}: not YAML ({str(err).splitlines()[0]})', 2) from None
    return {} if value is None else value


def absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


# --- bag ----------------------------------------------------------------------------------------

def bag_info(args) -> int:
    from drift_tools.bag_tools import bag_overview
    lines, problems = bag_overview(args.bag)
    print('\n'.join(lines))
    return 1 if problems else 0


def bag_recover(args) -> int:
    from drift_tools.bag_salvage import recover_bag
    print('\n'.join(recover_bag(args.bag, args.out).lines()))
    return 0


def bag_slice(args) -> int:
    from drift_tools.bag_tools import slice_bag
    kept = slice_bag(args.bag, args.out, args.start, args.end, args.topics)
    print(f'{args.out}: {sum(kept.values())} messages ' +
          ', '.join(f'{t} {n}' for t, n in sorted(kept.items())))
    return 0


def bag_export(args) -> int:
    from drift_tools.bag_tools import export_csv
    if (args.format or export_format(args.out)) == 'mdf4':
        from drift_tools.mdf import export_mdf
        print('\n'.join(export_mdf(args.bag, args.out, args.topics).lines()))
        return 0
    for path, rows in export_csv(args.bag, args.out, args.topics):
        print(f'{path}: {rows} rows')
    return 0


def export_format(out: Path) -> str:
    """'mdf4' for an output named ``*.mf4`` or ``*.mdf``, else 'csv' (a directory)."""
    from drift_tools.mdf import SUFFIXES
    return 'mdf4' if out.suffix.lower() in SUFFIXES else 'csv'


# --- the command line ---------------------------------------------------------------------------

ROS_COMMANDS = {('topic', 'list'): 'topic_list', ('topic', 'echo'): 'topic_echo',
                ('topic', 'hz'): 'topic_hz', ('topic', 'pub'): 'topic_pub',
                ('service', 'call'): 'service_call', ('arm', None): 'bridge_arm',
                ('disarm', None): 'bridge_arm', ('status', None): 'bridge_status',
                ('param', 'list'): 'param_list', ('param', 'get'): 'param_get',
                ('param', 'set'): 'param_set'}   # functions of drift_tools.nodes.cli_ros
BAG_COMMANDS = {'info': bag_info, 'recover': bag_recover, 'slice': bag_slice,
                'export': bag_export}


def probe(args) -> int:
    """Listen on the link config/bridge.yaml names (no ROS, nothing sent) and report its PDUs."""
    import can
    from drift_control.params import ParamError, parse_overrides
    from drift_vehicle_bridge.codec import Codec
    from drift_vehicle_bridge.params import description_path, load_bridge_params
    from drift_vehicle_bridge.probe import format_reports, probe as listen
    from drift_vehicle_bridge.transport import open_transport
    if not args.duration > 0:
        raise CliError(f'--duration must be > 0 s, got {args.duration}', 2)
    try:
        params = load_bridge_params(args.config_dir, parse_overrides(args.set, 'bridge'))
        codec = Codec.load(description_path(params, args.config_dir))
    except ParamError as err:
        raise CliError(str(err), 2) from None
    try:
        with open_transport(params) as link:
            reports = listen(link, codec, args.duration, params.monitor.max_counter_delta,
                             params.monitor.e2e)
    except (OSError, can.CanError, ParamError) as err:
        raise CliError(f'cannot listen on {params.link()}: {err}') from None
    print(f'{params.link()}, {codec.description.source}, {args.duration:g} s')
    print(format_reports(reports, codec))
    seen = {r.name: r for r in reports}
    bad = [n for n in codec.state_frames
           if n not in seen or seen[n].e2e.rpartition(', ')[2] != 'VALID']
    if bad:
        raise CliError(f'state PDU(s) missing or not E2E VALID: {", ".join(bad)}')
    return 0


def _window(text: str) -> int:
    """A rate window: at least two messages."""
    value = natural(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f'expected an integer >= 2, got {text!r}')
    return value


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='drift', description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest='command', required=True)
    for name, helptext in (('arm', 'arm the vehicle bridge'), ('disarm', 'release the car')):
        s = sub.add_parser(name, help=helptext)
        s.add_argument('--timeout', type=seconds, default=10.0)
    s = sub.add_parser('status', help='the bridge\'s diagnostics (mode, rates, recording)')
    s.add_argument('--name', default='vehicle_bridge', help='status name prefix')
    s.add_argument('--timeout', type=seconds, default=5.0)

    topic = sub.add_parser('topic', help='live topics').add_subparsers(dest='sub', required=True)
    s = topic.add_parser('list', help='topics in the graph')
    s.add_argument('-t', '--types', action='store_true', help='show the message types')
    s.add_argument('--wait', type=seconds, default=2.5, help='discovery time before listing [s]')
    s = topic.add_parser('echo', help='print messages of a topic')
    s.add_argument('topic', type=absolute)
    s.add_argument('-n', '--count', type=natural, default=0,
                   help='stop after N messages (0: never)')
    s.add_argument('--timeout', type=seconds, default=10.0, help='give up after this long [s]')
    s = topic.add_parser('hz', help='receive rate of a topic, printed every second')
    s.add_argument('topic', type=absolute)
    s.add_argument('--window', type=_window, default=100, help='messages averaged over (>= 2)')
    s.add_argument('--duration', type=seconds, default=0.0, help='stop after [s] (0: never)')
    s.add_argument('--timeout', type=seconds, default=10.0, help='wait for a publisher [s]')
    s = topic.add_parser('pub', help='publish a message (fields in YAML)')
    s.add_argument('topic', type=absolute)
    s.add_argument('type', help='pkg/msg/Name')
    s.add_argument('values', nargs='?', default='', help="e.g. '{data: 1.5}'")
    s.add_argument('-n', '--count', type=natural, default=1, help='messages (0: until stopped)')
    s.add_argument('-r', '--rate', type=positive, default=10.0, help='[Hz]')
    s.add_argument('--stamp', action='store_true', help='stamp the header with the node clock')
    s.add_argument('--timeout', type=seconds, default=10.0, help='wait for a subscriber [s]')

    service = sub.add_parser('service', help='services').add_subparsers(dest='sub', required=True)
    s = service.add_parser('call', help='call a service (request fields in YAML)')
    s.add_argument('service', type=absolute)
    s.add_argument('type', nargs='?', default=None, help='pkg/srv/Name (default: the graph\'s)')
    s.add_argument('values', nargs='?', default='', help="e.g. '{data: true}'")
    s.add_argument('--timeout', type=seconds, default=10.0)

    param = sub.add_parser('param', help='node parameters').add_subparsers(dest='sub',
                                                                            required=True)
    for name in ('list', 'get', 'set'):
        s = param.add_parser(name, help=f'{name} parameters of a node')
        s.add_argument('node')
        if name in ('get', 'set'):
            s.add_argument('name')
        if name == 'set':
            s.add_argument('value', help='YAML value')
        s.add_argument('--timeout', type=seconds, default=10.0)

    bag = sub.add_parser('bag', help='recorded runs (read only)').add_subparsers(dest='sub',
                                                                                required=True)
    s = bag.add_parser('info', help='topics, counts, time span, run settings, damage')
    s.add_argument('bag', type=Path)
    s = bag.add_parser('recover', help='a repaired copy of a damaged or unfinished bag')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path)
    s = bag.add_parser('slice', help='a new bag with a time window and/or some topics')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path)
    s.add_argument('--start', type=seconds, default=0.0, help='[s] after the first message')
    s.add_argument('--end', type=seconds, default=None, help='[s] after the first message')
    s.add_argument('--topics', nargs='*', default=None)
    s = bag.add_parser('export', help='one CSV per topic, or one MDF4 file (a channel per field)')
    s.add_argument('bag', type=Path)
    s.add_argument('out', type=Path, help='directory for the CSV files, or the .mf4 file')
    s.add_argument('--format', choices=('csv', 'mdf4'), default=None,
                   help='default: mdf4 when OUT ends in .mf4 or .mdf, else csv')
    s.add_argument('--topics', nargs='*', default=None)

    s = sub.add_parser('probe', help='listen on the car\'s link (instead of the bridge): PDUs '
                                     'seen, rates from their stamps, E2E states')
    s.add_argument('--duration', type=seconds, default=2.0, help='[s]')
    s.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='config/bridge.yaml override, e.g. transport=udp (repeatable)')
    s.add_argument('--config-dir', type=Path, default=None)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == 'bag':
            if getattr(args, 'out', None) is not None:   # a bag is evidence: never written to
                fmt = args.format or export_format(args.out) if args.sub == 'export' else None
                directory = fmt != 'mdf4'   # a bag, or a directory of CSV files
                problem = output_problem(args.out, [args.bag], directory=directory)
                if problem is not None:
                    raise CliError(problem, 2)
            return BAG_COMMANDS[args.sub](args)
        if args.command == 'probe':
            return probe(args)
        from drift_tools.nodes import cli_ros
        command = getattr(cli_ros, ROS_COMMANDS[(args.command, getattr(args, 'sub', None))])
        ros = cli_ros.Ros()
        try:
            return command(ros, args)
        finally:
            ros.close()
    except CliError as err:
        print(f'drift: {err}', file=sys.stderr)
        return err.code
    except BrokenPipeError:          # `drift ... | head`: the reader has what it wanted
        sys.stdout = open(os.devnull, 'w', encoding='utf-8')
        return 0
    except (OSError, ValueError, LookupError) as err:
        print(f'drift: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0


if __name__ == '__main__':   # python -m: run the importable module (one CliError class)
    from drift_tools.operator import main as module_main
    sys.exit(module_main())
