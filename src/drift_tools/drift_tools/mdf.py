"""MDF4 (ASAM MDF 4.10) files: a bag exported channel by channel, and MDF4 logs read back as runs.

Export (:func:`export_mdf`): one channel group per topic, named by the topic, its message type as
the group comment; one channel per fixed-size field, named ``<topic>.<field path>``
(``vehicle/state.v``, ``vehicle/state.wheel_speeds[2]``, ``drift/reference.target.beta``), with
the unit and comment of its line in the message definition the bag carries (the ``.msg`` text:
``float64 v  # speed over ground [m/s]``) and, where the type has ``FIELD_*`` constants, their
names as a value-to-text table (``drift/command.mode``: OFF, FULL, ...). Values keep their ROS
type (float64 stays float64, strings UTF-8); sequences (a horizon, a path) have no fixed channel
layout and are listed as not exported. Times are the bag's log times (sim time in a lock-step
run) relative to the header's start time, which is the first log time to the nanosecond. The
bag's ``drift_run`` record goes into the header comment (common properties) and, whole, into an
embedded ``drift_run.json``.

Reading (:func:`read_mdf`) returns ``{topic: [BagMessage]}`` as ``drift_tools.bag.read_bag`` does,
from a file this export wrote, or from a car logger's file: its CAN / CAN FD bus logging decoded
with a DBC (asammdf), or channels it already holds, whose names are the DBC contract of
``drift_vehicle_bridge.codec`` (``V``, ``beta``, ``r``, ``omega_FL``...), become ``/vehicle/state``
messages on the time base of the sideslip channel. The input is only read.
"""
from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from drift_tools.bag import BagMessage
from drift_tools.msgdef import Leaf, MsgDefError, leaves, message_definition, normalize

MDF_VERSION = '4.10'
SUFFIXES = ('.mf4', '.mdf')
RUN_ATTACHMENT = 'drift_run.json'
STATE_TOPIC = '/vehicle/state'
STATE_TYPE = 'drift_msgs/msg/VehicleState'
STATE_NEEDED = ('V', 'beta', 'r')     # the drift state: nothing is judged without it
_DTYPES = {'float64': 'f8', 'float32': 'f4', 'int8': 'i1', 'uint8': 'u1', 'byte': 'u1',
           'char': 'u1', 'int16': 'i2', 'uint16': 'u2', 'int32': 'i4', 'uint32': 'u4',
           'int64': 'i8', 'uint64': 'u8', 'bool': 'bool'}
_STRINGS = ('string', 'wstring')


class MdfError(ValueError):
    """An input that is not an MDF4 file, or lacks the channels asked for."""


# --- export ------------------------------------------------------------------------------------

@dataclass
class Export:
    """What :func:`export_mdf` wrote."""

    path: Path
    groups: list = field(default_factory=list)       # (topic, channels, samples)
    not_exported: list = field(default_factory=list)  # 'topic: what (why)'

    def lines(self) -> list[str]:
        channels = sum(g[1] for g in self.groups)
        out = [f'{self.path}: {len(self.groups)} channel groups, {channels} channels, '
               f'{sum(g[2] for g in self.groups)} samples']
        width = max((len(g[0]) for g in self.groups), default=5)
        out += [f'  {t.ljust(width)}  {c:4d} channels  {n:7d} samples' for t, c, n in self.groups]
        out += [f'  not exported: {line}' for line in self.not_exported]
        return out


def export_mdf(bag_dir, out_path, topics=None) -> Export:
    """Write the bag as one MDF4 file (see the module docstring); the bag is only read.

    Raises
    ------
    FileExistsError
        If ``out_path`` exists.
    ValueError
        If the bag has no messages (on ``topics``).
    """
    from asammdf import MDF, Signal
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from drift_tools.replay import iter_raw
    out_path = Path(out_path)
    if out_path.exists():
        raise FileExistsError(f'{out_path}: exists')
    by_topic: dict[str, list] = {}
    for m in iter_raw(bag_dir, topics):
        by_topic.setdefault(m.topic, []).append(m)
    if not by_topic:
        raise ValueError(f'{bag_dir}: no messages' + (f' on {topics}' if topics else ''))
    t0_ns = min(msgs[0].t_ns for msgs in by_topic.values())
    definitions = _bag_definitions(bag_dir)
    for msgtype in {msgs[0].msgtype for msgs in by_topic.values()} - set(definitions):
        definitions[msgtype] = _definition(msgtype)          # a bag that stored none
    types = {}
    for msgtype, text in definitions.items():
        types.update(get_types_from_msg(text, msgtype))
    store = get_typestore(Stores.EMPTY)     # rosbags: the bag's own definitions, compiled
    store.register(types)
    mdf = MDF(version=MDF_VERSION)
    result = Export(out_path)
    try:
        _describe(mdf, bag_dir, t0_ns)
        for topic, msgs in sorted(by_topic.items()):
            msgtype = msgs[0].msgtype
            try:
                channels, sequences = leaves(msgtype, definitions[msgtype])
            except MsgDefError as err:
                raise MdfError(f'{topic}: {err}') from None
            kept = [m for m in msgs if m.msgtype == msgtype]
            if len(kept) < len(msgs):
                result.not_exported.append(f'{topic}: {len(msgs) - len(kept)} messages of '
                                           f'another type than {msgtype}')
            if sequences:
                result.not_exported.append(f'{topic}: ' + ', '.join(
                    _path_name(p) + '[]' for p in sequences) + ' (variable length)')
            if not channels:
                continue
            decoded = [store.deserialize_cdr(m.data, msgtype) for m in kept]
            t = (np.array([m.t_ns for m in kept], dtype=np.int64) - t0_ns) / 1e9
            prefix = topic.strip('/') + '.'
            signals = [Signal(_column(decoded, leaf), t, name=prefix + leaf.name, unit=leaf.unit,
                              comment=leaf.comment, conversion=_text_table(leaf.values),
                              encoding='utf-8' if leaf.type in _STRINGS else None)
                       for leaf in channels]
            mdf.append(signals, acq_name=topic, comment=msgtype)
            result.groups.append((topic, len(signals), len(kept)))
        mdf.save(out_path, compression=1)
    except BaseException:
        out_path.unlink(missing_ok=True)     # no half-written file that looks like an export
        raise
    finally:
        mdf.close()
    return result


def _bag_definitions(bag_dir) -> dict[str, str]:
    """``pkg/msg/Name`` -> the full message definition the bag stores for it."""
    from drift_tools.bag import bag_info, is_finished
    from drift_tools.bag_salvage import scan_bag
    if is_finished(bag_dir):
        from mcap.reader import make_reader
        found = []
        for name in bag_info(bag_dir).files:
            with open(Path(bag_dir) / name, 'rb') as fh:
                found += make_reader(fh).get_summary().schemas.values()
    else:
        found = scan_bag(bag_dir).schemas.values()
    out = {}
    for schema in found:
        try:
            if schema.data and schema.encoding == 'ros2msg':
                out[normalize(schema.name)] = bytes(schema.data).decode()
        except MsgDefError:
            pass
    return out


def _definition(msgtype: str) -> str:
    try:
        return message_definition(msgtype)
    except MsgDefError as err:
        raise MdfError(f'{msgtype}: no definition in the bag or here ({err})') from None


def _path_name(path: tuple) -> str:
    return ''.join(f'[{p}]' if isinstance(p, int) else f'.{p}' for p in path).lstrip('.')


def _column(decoded: list, leaf: Leaf) -> np.ndarray:
    values = []
    for msg in decoded:
        for step in leaf.path:
            msg = msg[step] if isinstance(step, int) else getattr(msg, step)
        values.append(msg)
    if leaf.type in _STRINGS:
        return np.array([v.encode('utf-8') for v in values], dtype=bytes)
    return np.array(values, dtype=_DTYPES[leaf.type])


def _text_table(values: dict):
    if not values:
        return None
    table = {}
    for i, (value, text) in enumerate(sorted(values.items())):
        table[f'val_{i}'], table[f'text_{i}'] = value, text.encode()
    table['default'] = b''
    return table


def _describe(mdf, bag_dir, t0_ns: int) -> None:
    """Header (start time, comment with the run settings), file history, run record attached."""
    from asammdf.blocks import v4_constants
    from asammdf.blocks.v4_blocks import FileHistory

    from drift_tools.run_info import read_run_info
    run = read_run_info(bag_dir) or {}
    mdf.header.abs_time = t0_ns                 # exact: ns since the epoch, UTC
    mdf.header.time_flags = v4_constants.FLAG_HD_TIME_OFFSET_VALID
    mdf.header.tz_offset = mdf.header.daylight_save_time = 0
    clock = 'sim time (lock-step run)' if run.get('clock') == 'lockstep' else 'log time'
    text = (f'drift stack run, exported from bag {Path(bag_dir).resolve().name}; times are the '
            f"bag's {clock}. Scenario {run.get('scenario') or '?'}, vehicle "
            f"{run.get('vehicle') or '(scenario default)'}, seed "
            f"{run.get('seed') or '(scenario default)'}, commit {run.get('commit') or '?'}"
            + (' (with uncommitted changes)' if run.get('dirty') == 'true' else '') + '.')
    root = ET.Element('HDcomment')
    ET.SubElement(root, 'TX').text = text
    props = ET.SubElement(root, 'common_properties')
    for key, value in [('project', 'drift stack'), ('subject', run.get('scenario', '')),
                       ('bag', str(Path(bag_dir).resolve()))] + \
            [(k, v) for k, v in run.items() if k != 'config']:
        if value:
            ET.SubElement(props, 'e', name=key).text = value
    mdf.header.comment = ET.tostring(root, encoding='unicode')
    root = ET.Element('FHcomment')
    for tag, value in (('TX', text), ('tool_id', 'drift bag export'),
                       ('tool_vendor', 'drift stack'), ('tool_version', _version())):
        ET.SubElement(root, tag).text = value
    history = FileHistory()
    history.comment = ET.tostring(root, encoding='unicode')
    mdf.file_history.append(history)
    if run:
        mdf.attach(json.dumps(run, indent=1).encode(), file_name=RUN_ATTACHMENT,
                   comment="the bag's drift_run record: run settings and configuration files",
                   mime='application/json')


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version('drift_tools')
    except PackageNotFoundError:
        return ''


# --- reading -----------------------------------------------------------------------------------

def open_mdf(path):
    """Open an MDF4 file with asammdf; anything else is an :class:`MdfError` (one line)."""
    import sys

    from asammdf import MDF
    path = Path(path)
    if not path.is_file():
        raise MdfError(f'{path}: no such MDF4 file')
    with open(path, 'rb') as fh:
        ident = fh.read(16)
    if ident[:8] != b'MDF     ':
        raise MdfError(f'{path}: not an MDF4 file (no MDF identification block)')
    version = ident[8:16].decode('ascii', 'replace').strip(' \x00')
    if not version.startswith('4'):
        raise MdfError(f'{path}: MDF {version}, not MDF4 (asammdf converts it: '
                       "MDF(path).convert('4.10').save(...))")
    hook, problem = sys.unraisablehook, None
    sys.unraisablehook = lambda _: None     # a half-read file's destructor complains otherwise
    try:
        return MDF(path)
    except Exception as err:   # noqa: BLE001 - asammdf raises its own and builtin types on damage
        problem = f'{type(err).__name__}: {err}'
    finally:
        if problem is not None:   # the half-built reader sits in a cycle with its traceback
            import gc
            gc.collect()
        sys.unraisablehook = hook
    raise MdfError(f'{path}: unreadable MDF4 file ({problem})')


def mdf_run_info(path) -> dict | None:
    """The ``drift_run`` record this export embedded, or None (a file from a logger)."""
    mdf = open_mdf(path)
    try:
        for i, attachment in enumerate(mdf.attachments):
            if Path(str(attachment.file_name)).name == RUN_ATTACHMENT:
                return json.loads(bytes(mdf.extract_attachment(i)[0]))
        return None
    finally:
        mdf.close()


def read_log(path, dbc=None) -> dict[str, list[BagMessage]]:
    """A run's messages from a bag directory (``read_bag``) or an MDF4 file (:func:`read_mdf`)."""
    from drift_tools.bag import read_bag
    return read_mdf(path, dbc) if Path(path).is_file() else read_bag(path)


def log_run_info(path) -> dict | None:
    """The ``drift_run`` record of a bag directory or of an MDF4 file this export wrote."""
    from drift_tools.run_info import read_run_info
    return mdf_run_info(path) if Path(path).is_file() else read_run_info(path)


def read_mdf(path, dbc=None) -> dict[str, list[BagMessage]]:
    """An MDF4 file as ``{topic: [BagMessage]}`` (see the module docstring).

    Parameters
    ----------
    path : path
        MDF4 file: one :func:`export_mdf` wrote, or a logger's.
    dbc : path, optional
        Decodes the CAN / CAN FD bus logging of a logger's file.

    Raises
    ------
    MdfError
        Not an MDF4 file, unreadable, or without the channels of the vehicle state
        (``STATE_NEEDED``) where it has to provide them.
    """
    mdf = open_mdf(path)
    try:
        exported = [(i, g.channel_group.acq_name) for i, g in enumerate(mdf.groups)
                    if (g.channel_group.acq_name or '').startswith('/')
                    and re.fullmatch(r'\w+/msg/\w+', g.channel_group.comment or '')]
        if exported:
            return _read_export(mdf, path, exported)
        return {STATE_TOPIC: _read_logger(mdf, path, dbc)}
    finally:
        mdf.close()


def _read_export(mdf, path, groups) -> dict[str, list[BagMessage]]:
    t0_ns, out = int(mdf.header.abs_time), {}
    for index, topic in groups:
        msgtype = mdf.groups[index].channel_group.comment
        master = mdf.masters_db.get(index)
        prefix = topic.strip('/') + '.'
        columns = {}
        for j, channel in enumerate(mdf.groups[index].channels):
            if j != master and channel.name.startswith(prefix):
                samples = mdf.get(group=index, index=j, raw=True).samples
                columns[channel.name[len(prefix):]] = _plain(samples)
        t_ns = np.round(mdf.get_master(index) * 1e9).astype(np.int64) + t0_ns
        if normalize(msgtype) == STATE_TYPE:
            _require(columns, path, 'in ' + topic)
        out[topic] = _messages(msgtype, t_ns, columns)
    return out


def _read_logger(mdf, path, dbc) -> list[BagMessage]:
    """``/vehicle/state`` from a logger's channels, or its bus logging decoded with ``dbc``."""
    from drift_vehicle_bridge.codec import WHEELS   # wheel_speeds[i]; the rest as in the msg
    source, decoded_with = mdf, ''
    if 'CAN_DataFrame' in mdf.channels_db:
        if dbc is None:
            raise MdfError(f'{path}: CAN bus logging; give the DBC that decodes it (--dbc)')
        if not Path(dbc).is_file():
            raise MdfError(f'{dbc}: no such DBC file')
        source = mdf.extract_bus_logging({'CAN': [(str(dbc), 0)]})
        decoded_with = f'; its CAN frames decoded with {Path(dbc).name}'
    try:
        state_leaves, _ = leaves(STATE_TYPE, message_definition(STATE_TYPE))
        found = {}
        for leaf in state_leaves:
            if leaf.path[0] == 'header' or leaf.type in _STRINGS:
                continue
            wanted = WHEELS[leaf.path[1]] if leaf.path[0] == 'wheel_speeds' else leaf.name
            where = _find(source, wanted)
            if where is not None:
                sig = source.get(group=where[0], index=where[1])
                if sig.samples.dtype.kind not in 'biuf':
                    sig = source.get(group=where[0], index=where[1], raw=True)
                found[leaf.name] = (sig.timestamps, sig.samples.astype(float))
        _require(found, path, f'named as in the DBC{decoded_with}')
        t_rel, _ = found['beta']
        t0_ns = int(source.header.abs_time)
    finally:
        if source is not mdf:
            source.close()
    t_ns = np.round(t_rel * 1e9).astype(np.int64) + t0_ns
    columns = {name: _hold(t, values, t_rel) for name, (t, values) in found.items()}
    secs, nanos = np.divmod(t_ns, 10**9)
    columns.update({'header.stamp.sec': secs.tolist(), 'header.stamp.nanosec': nanos.tolist()})
    return _messages(STATE_TYPE, t_ns, columns)


def _find(mdf, name: str):
    """(group, index) of the channel called ``name`` (any case) with the most samples, or None."""
    best, size = None, -1
    for key, places in mdf.channels_db.items():
        if key.lower() != name.lower():
            continue
        for group, index in places:
            if index == mdf.masters_db.get(group):
                continue
            n = mdf.groups[group].channel_group.cycles_nr
            if n > size or (n == size and key == name):
                best, size = (group, index), n
    return best


def _hold(t: np.ndarray, values: np.ndarray, at: np.ndarray) -> list:
    """Zero-order hold of ``values`` at times ``at`` (NaN before the first sample)."""
    idx = np.searchsorted(t, at, side='right') - 1
    out = values[np.clip(idx, 0, None)].astype(float)
    out[idx < 0] = np.nan
    return out.tolist()


def _require(columns: dict, path, where: str) -> None:
    names = {n.lower() for n in columns}
    missing = [n for n in STATE_NEEDED if n.lower() not in names]
    if missing:
        raise MdfError(f'{path}: no channel {", ".join(missing)} ({where}; the vehicle state '
                       f'needs {", ".join(STATE_NEEDED)})')


def _plain(samples: np.ndarray) -> list:
    if samples.dtype.kind == 'S':
        return [s.decode('utf-8', 'replace') for s in samples]
    return samples.tolist()


def _messages(msgtype: str, t_ns: np.ndarray, columns: dict) -> list[BagMessage]:
    """Messages shaped by the type's definition, fields from ``columns`` (name -> values).

    A field without a column is NaN (a string ''), a sequence empty, so that readers of
    ``read_bag`` output find every field of the type.
    """
    try:
        fields, sequences = leaves(msgtype, message_definition(msgtype))
    except MsgDefError:                      # a type unknown here: the channels alone
        fields = [Leaf(name, tuple(_split(name)), 'float64', '', '', {}) for name in columns]
        sequences = []
    tree: dict = {}
    for leaf in fields:
        _place(tree, leaf.path, leaf)
    for path in sequences:
        _place(tree, path, [])

    def build(node, i):
        if isinstance(node, Leaf):
            values = columns.get(node.name)
            if values is not None:
                return values[i]
            return '' if node.type in _STRINGS else math.nan
        if isinstance(node, list):
            return []
        if all(isinstance(k, int) for k in node):
            return [build(node[k], i) for k in sorted(node)]
        return SimpleNamespace(**{k: build(v, i) for k, v in node.items()})

    return [BagMessage(int(t) * 1e-9, build(tree, i)) for i, t in enumerate(t_ns)]


def _place(tree: dict, path: tuple, node) -> None:
    for step in path[:-1]:
        tree = tree.setdefault(step, {})
    tree[path[-1]] = node


def _split(name: str) -> list:
    """'target.v' -> ['target', 'v']; 'wheel_speeds[2]' -> ['wheel_speeds', 2]."""
    out = []
    for part in name.split('.'):
        base, *indices = part.replace(']', '').split('[')
        out += [base] + [int(i) for i in indices]
    return out
