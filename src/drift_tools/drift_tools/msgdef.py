"""ROS 2 message definitions from ``.msg`` files: the concatenated text bags store as schemas.

A bag's ``ros2msg`` schema is the type's own ``.msg`` text followed by every type it depends on,
each after a line of 80 ``=`` and a ``MSG: pkg/Name`` line -- the layout rosbag2 writes and
``mcap_ros2`` and ``rosbags`` parse. ``.msg`` files are looked up in ``share/<pkg>/msg/`` of the
ament prefixes and of this interpreter's prefix (where the ROS wheels and drift_msgs install), then
in ``src/<pkg>/msg/`` of this checkout. A definition is also read back field by field
(``parse_fields``, ``leaves``): each primitive value of a type with the unit its line's comment
gives (``float64 v  # speed over ground [m/s]``) and its ``FIELD_*`` constants.
"""
from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

SEPARATOR = '=' * 80
PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string', 'wstring',
})
_REPO_SRC = Path(__file__).resolve().parents[2]


class MsgDefError(LookupError):
    """No ``.msg`` file for a message type."""


def normalize(msgtype: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    parts = msgtype.strip('/').split('/')
    if len(parts) == 2:
        return f'{parts[0]}/msg/{parts[1]}'
    if len(parts) == 3 and parts[1] == 'msg':
        return '/'.join(parts)
    raise MsgDefError(f'not a message type name: {msgtype!r}')


def _search_dirs() -> list[Path]:
    prefixes = [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(Path(sys.prefix))
    return [p / 'share' for p in prefixes] + [_REPO_SRC]


@lru_cache(maxsize=None)
def msg_text(msgtype: str) -> str:
    """The ``.msg`` file text of ``msgtype`` (``pkg/msg/Name``)."""
    pkg, _, name = normalize(msgtype).split('/')
    for base in _search_dirs():
        path = base / pkg / 'msg' / f'{name}.msg'
        if path.is_file():
            return path.read_text(encoding='utf-8')
    raise MsgDefError(f'no {pkg}/msg/{name}.msg under {[str(d) for d in _search_dirs()]}')


@dataclass(frozen=True)
class Field:
    """One field or constant line of a ``.msg`` text."""

    type: str            # a primitive ('float64', 'string') or 'pkg/msg/Name'
    name: str
    array: int | None    # None: one value; n: a fixed array of n; -1: a sequence (bounded or not)
    comment: str         # the line's own comment, '#' stripped
    value: str | None    # a constant's value; None for a field

    @property
    def unit(self) -> str:
        """The last ``[...]`` of the comment (``# speed over ground [m/s]`` -> ``m/s``), or ''."""
        found = re.findall(r'\[([^\[\]]*)\]', self.comment)
        return found[-1].strip() if found else ''


_CONSTANT = re.compile(r'^(\S+)\s+([A-Za-z]\w*)\s*=\s*(.*)$')
_FIELD = re.compile(r'^(\S+)\s+(\w+)(?:\s+.*)?$')


def parse_fields(pkg: str, text: str) -> list[Field]:
    """The fields and constants of one ``.msg`` text of package ``pkg``, in file order."""
    out = []
    for line in text.splitlines():
        code, _, comment = line.partition('#')
        code = code.strip()
        if not code:
            continue
        match = _CONSTANT.match(code) or _FIELD.match(code)
        if match is None:
            continue
        type_token, name = match.group(1), match.group(2)
        value = match.group(3).strip() if match.re is _CONSTANT else None
        array = None
        shape = re.search(r'\[(<=)?(\d*)\]$', type_token)
        if shape:
            array = int(shape.group(2)) if shape.group(2) and not shape.group(1) else -1
            type_token = type_token[:shape.start()]
        base = re.sub(r'<=\d+$', '', type_token)
        if base not in PRIMITIVES:
            if '/' in base:
                base = normalize(base)
            elif base == 'Header':
                base = 'std_msgs/msg/Header'
            else:
                base = f'{pkg}/msg/{base}'
        out.append(Field(base, name, array, comment.strip(), value))
    return out


def dependencies(pkg: str, text: str) -> list[str]:
    """Non-primitive field types of one ``.msg`` text, as ``pkg/msg/Name``, in field order."""
    deps = []
    for f in parse_fields(pkg, text):
        if f.value is None and f.type not in PRIMITIVES and f.type not in deps:
            deps.append(f.type)
    return deps


def split_definition(msgtype: str, definition: str) -> dict[str, str]:
    """A full definition (the root's text, then ``MSG: pkg/Name`` sections) -> type -> text."""
    out, current, lines = {}, normalize(msgtype), []
    for line in definition.splitlines():
        if line.strip() == SEPARATOR:
            out[current], current, lines = '\n'.join(lines), None, []
        elif current is None and line.startswith('MSG:'):
            current = normalize(line[4:].strip())
        elif current is not None:
            lines.append(line)
    if current is not None:
        out[current] = '\n'.join(lines)
    return out


@dataclass(frozen=True)
class Leaf:
    """A primitive value in a message: a field, or an element of a fixed array, at any depth."""

    name: str          # 'header.stamp.sec', 'wheel_speeds[2]', 'target.v'
    path: tuple        # ('header', 'stamp', 'sec'), ('wheel_speeds', 2), ('target', 'v')
    type: str          # the primitive type
    unit: str          # from the field's line (Field.unit)
    comment: str
    values: dict       # value -> name of the field's FIELD_* constants (MODE_OFF = 0: {0: 'OFF'})


# builtin_interfaces/Time carries no unit comments; a stamp's two parts get theirs here
TIME_UNITS = {('builtin_interfaces/msg/Time', 'sec'): 's',
              ('builtin_interfaces/msg/Time', 'nanosec'): 'ns'}
_INTEGERS = frozenset({'byte', 'char', 'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32',
                       'int64', 'uint64'})


def leaves(msgtype: str, definition: str) -> tuple[list[Leaf], list[tuple]]:
    """The primitive leaves of ``msgtype`` and the paths of its sequences (no fixed layout).

    ``definition`` is the full definition (a bag's schema); a type it lacks is looked up here.
    """
    texts = split_definition(msgtype, definition)
    found, sequences = [], []

    def walk(typ, prefix, path):
        fields = parse_fields(typ.split('/')[0], texts[typ] if typ in texts else msg_text(typ))
        constants = [f for f in fields if f.value is not None]
        for f in fields:
            if f.value is not None:
                continue
            if f.array == -1:
                sequences.append(path + (f.name,))
                continue
            items = [(prefix + f.name, path + (f.name,))] if f.array is None else \
                [(f'{prefix}{f.name}[{i}]', path + (f.name, i)) for i in range(f.array)]
            for name, where in items:
                if f.type not in PRIMITIVES:
                    walk(f.type, name + '.', where)
                    continue
                table = {int(c.value): c.name[len(f.name) + 1:] for c in constants
                         if f.type in _INTEGERS and c.type == f.type
                         and c.name.startswith(f.name.upper() + '_')
                         and c.value.lstrip('-').isdigit()}
                found.append(Leaf(name, where, f.type, f.unit or TIME_UNITS.get((typ, f.name), ''),
                                  f.comment, table))

    walk(normalize(msgtype), '', ())
    return found, sequences


@lru_cache(maxsize=None)
def message_definition(msgtype: str) -> str:
    """The full ROS 2 definition of ``msgtype``: its text, then each dependency once.

    Raises
    ------
    MsgDefError
        If the ``.msg`` file of the type or of one of its dependencies is not found.
    """
    root = normalize(msgtype)
    order, stack = [], [root]
    while stack:                    # depth-first, each type once, root first
        current = stack.pop(0)
        if current in order:
            continue
        order.append(current)
        pkg = current.split('/')[0]
        stack = [d for d in dependencies(pkg, msg_text(current)) if d not in order] + stack
    parts = [msg_text(root).rstrip('\n')]
    for dep in order[1:]:
        pkg, _, name = dep.split('/')
        parts.append(f'{SEPARATOR}\nMSG: {pkg}/{name}\n{msg_text(dep).rstrip(chr(10))}')
    return '\n'.join(parts) + '\n'
