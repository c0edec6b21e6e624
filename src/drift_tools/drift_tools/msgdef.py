"""ROS 2 message definitions from ``.msg`` files: the concatenated text bags store as schemas.

A bag's ``ros2msg`` schema is the type's own ``.msg`` text followed by every type it depends on,
each after a line of 80 ``=`` and a ``MSG: pkg/Name`` line -- the layout rosbag2 writes and
``mcap_ros2`` and ``rosbags`` parse. ``.msg`` files are looked up in ``share/<pkg>/msg/`` of the
ament prefixes and of this interpreter's prefix (where the ROS wheels and drift_msgs install), then
in ``src/<pkg>/msg/`` of this checkout.
"""
from __future__ import annotations

import os
import re
import sys
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


def dependencies(pkg: str, text: str) -> list[str]:
    """Non-primitive field types of one ``.msg`` text, as ``pkg/msg/Name``, in field order."""
    deps = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        type_token, _, rest = line.partition(' ')
        if re.match(r'^\s*\w+\s*=', rest):       # a constant: always a primitive
            continue
        base = re.sub(r'\[.*\]$', '', type_token)
        base = re.sub(r'<=\d+$', '', base)
        if base in PRIMITIVES:
            continue
        if '/' in base:
            dep = normalize(base)
        elif base == 'Header':
            dep = 'std_msgs/msg/Header'
        else:
            dep = f'{pkg}/msg/{base}'
        if dep not in deps:
            deps.append(dep)
    return deps


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
