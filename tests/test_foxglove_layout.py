"""The committed Foxglove layout: its panels, and every message path it plots exists in our schemas.

The app is not available here, so the layout is checked against what it reads: each Plot and
State Transitions path must name a topic the stack or the view publishes and a chain of fields
that ends in a number or string of that topic's ``.msg`` definition (the schema live and in bags).
"""
import json
import re
from pathlib import Path

import pytest

from drift_tools.car_scene import MAP_FRAME, MARKERS_TOPIC, VIEW_TOPICS
from drift_tools.msgdef import PRIMITIVES, msg_text, normalize
from drift_tools.recording import STACK_TOPICS

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / 'config' / 'foxglove' / 'drift_layout.json'
TOPICS = {('/' + t.lstrip('/')): msgtype
          for t, msgtype in [*((t, m) for t, (m, _) in STACK_TOPICS.items()),
                             *VIEW_TOPICS.items()]}


@pytest.fixture(scope='module')
def layout():
    return json.loads(LAYOUT.read_text())


def panel_ids(tree):
    if isinstance(tree, str):
        return [tree]
    return panel_ids(tree['first']) + panel_ids(tree['second'])


def fields(msgtype: str) -> dict:
    """Field name -> type (``pkg/msg/Name`` or a primitive) of one ``.msg`` definition."""
    pkg, out = msgtype.split('/')[0], {}
    for line in msg_text(msgtype).splitlines():
        line = line.split('#', 1)[0].strip()
        if not line or '=' in line:            # blank, or a constant
            continue
        type_token, name = line.split()[:2]
        base = re.sub(r'(<=\d+)?(\[.*\])?$', '', type_token)
        if base in PRIMITIVES:
            out[name] = base
        elif '/' in base:
            out[name] = normalize(base)
        else:
            out[name] = 'std_msgs/msg/Header' if base == 'Header' else f'{pkg}/msg/{base}'
    return out


def resolve(path: str) -> str:
    """The type a message path ends in: ``/topic.field[:]{filter}.field`` -> a primitive."""
    plain = re.sub(r'\{[^}]*\}|\[[^\]]*\]', '', path)
    topic, *chain = plain.split('.')
    assert topic in TOPICS, f'{path}: no topic {topic} in the stack'
    current = normalize(TOPICS[topic])
    for name in chain:
        known = fields(current)
        assert name in known, f'{path}: {current} has no field {name!r}'
        current = known[name]
    return current


def series(layout):
    for panel_id, config in layout['configById'].items():
        if panel_id.split('!')[0] in ('Plot', 'StateTransitions'):
            for s in config['paths']:
                yield panel_id, s['value']


def test_every_panel_is_placed_and_every_placed_panel_configured(layout):
    placed = panel_ids(layout['layout'])
    assert sorted(placed) == sorted(layout['configById'])
    kinds = [p.split('!')[0] for p in placed]
    assert kinds.count('Plot') == 6
    assert {'3D', 'StateTransitions', 'DiagnosticSummary'} <= set(kinds)


def test_every_plotted_path_ends_in_a_field_of_the_topics_schema(layout):
    paths = list(series(layout))
    assert len(paths) >= 14
    for panel_id, path in paths:
        assert resolve(path) in PRIMITIVES - {'bool'} or panel_id.startswith('State'), path


@pytest.mark.parametrize('wanted', [
    '/vehicle/state.beta', '/drift/reference.target.beta',       # sideslip vs reference
    '/vehicle/state.r', '/drift/reference.target.r',             # yaw rate vs reference
    '/drift/reference.e_y',                                      # lateral error
    '/drift/command.delta', '/vehicle/state.delta',              # steering commanded, measured
    '/drift/command.drive_torque',                               # torque
    '/drift/nmpc/status.solve_time', '/drift/nmpc/status.status',
])
def test_the_layout_shows(layout, wanted):
    assert wanted in {path for _, path in series(layout)}


def test_bridge_mode_is_read_from_the_bridges_own_diagnostic_status(layout):
    convert = (REPO / 'src/drift_vehicle_bridge/drift_vehicle_bridge/nodes/convert.py').read_text()
    name = re.search(r"DiagnosticStatus\(name='([^']+)'", convert).group(1)
    assert "'mode': stats['mode']" in convert
    modes = [path for _, path in series(layout) if path.startswith('/diagnostics')]
    assert modes == [f'/diagnostics.status[:]{{name=="{name}"}}.values[:]{{key=="mode"}}.value']


def test_the_3d_panel_shows_the_path_and_the_car_in_the_map_frame(layout):
    three_d = layout['configById']['3D!drift']
    assert three_d['followTf'] == MAP_FRAME
    for topic in ('/drift/path', '/' + MARKERS_TOPIC):
        assert three_d['topics'][topic]['visible'] is True
