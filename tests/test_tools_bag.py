"""Bag writer and readers in-process: what goes in comes out, through both independent readers."""
import shutil

import pytest
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

from drift_tools.bag import bag_info, read_bag
from drift_tools.bag_writer import BagExistsError, BagWriter
from drift_tools.msgdef import dependencies, message_definition

STACK_TYPES = [
    'drift_msgs/msg/VehicleState', 'drift_msgs/msg/DriftReference', 'drift_msgs/msg/DriftCommand',
    'drift_msgs/msg/NmpcStatus', 'drift_msgs/msg/Equilibrium', 'rosgraph_msgs/msg/Clock',
    'diagnostic_msgs/msg/DiagnosticArray', 'nav_msgs/msg/Path', 'std_msgs/msg/Float64',
]
T0 = 1_700_000_000 * 10**9   # [ns]


def encoder(msgtype):
    return serialize_dynamic(msgtype, message_definition(msgtype))[msgtype]


def state(i):
    return {'header': {'stamp': {'sec': i, 'nanosec': 5}, 'frame_id': 'map'}, 'v': 0.5 * i,
            'beta': -0.01 * i, 'wheel_speeds': [1.0, 2.0, 3.0, float(i)], 'validity': 2047}


def status(i):
    return {'status': i % 4, 'message': f'it {i}', 'solve_time': 1e-3 * i,
            'state_names': ['v', 'beta'], 'predicted_states': [float(i), -1.0]}


def write_run(bag_dir, n, chunk_size=1024, flush_every=0):
    enc_s, enc_n = encoder('drift_msgs/msg/VehicleState'), encoder('drift_msgs/msg/NmpcStatus')
    w = BagWriter(bag_dir, chunk_size=chunk_size)
    w.add_topic('/vehicle/state', 'drift_msgs/VehicleState')
    w.add_topic('/drift/nmpc/status', 'drift_msgs/msg/NmpcStatus')
    for i in range(n):
        w.write('/vehicle/state', enc_s(state(i)), T0 + i * 10**7)
        if i % 2 == 0:
            w.write('/drift/nmpc/status', enc_n(status(i)), T0 + i * 10**7 + 1)
        if flush_every and (i + 1) % flush_every == 0:
            w.flush()
    return w


@pytest.mark.parametrize('msgtype', STACK_TYPES)
def test_definitions_parse_with_mcap_ros2(msgtype):
    decoders = generate_dynamic(msgtype, message_definition(msgtype))
    assert msgtype in decoders


def test_dependencies_of_msg_text():
    text = ('std_msgs/Header header\nuint8 MODE_OFF = 0  # constant\nEquilibrium[] horizon\n'
            'Equilibrium target\nstring<=8 name\nfloat64[4] w\ngeometry_msgs/msg/Pose pose\n')
    assert dependencies('drift_msgs', text) == [
        'std_msgs/msg/Header', 'drift_msgs/msg/Equilibrium', 'geometry_msgs/msg/Pose']


@pytest.mark.parametrize('backend', ['rosbags', 'mcap'])
def test_written_messages_read_back(tmp_path, backend):
    write_run(tmp_path / 'bag', 50).close()
    info = bag_info(tmp_path / 'bag')
    assert info.message_count == 75
    assert info.topics['/vehicle/state'].count == 50
    assert info.duration == pytest.approx(0.49, abs=1e-6)
    out = read_bag(tmp_path / 'bag', backend=backend)
    states, stats = out['/vehicle/state'], out['/drift/nmpc/status']
    assert len(states) == 50 and len(stats) == 25
    assert [m.t for m in states] == pytest.approx([(T0 + i * 10**7) * 1e-9 for i in range(50)])
    s = states[7].msg
    assert (s.v, s.beta, s.header.stamp.sec, s.header.frame_id) == (3.5, -0.07, 7, 'map')
    assert list(s.wheel_speeds) == [1.0, 2.0, 3.0, 7.0] and s.validity == 2047
    n = stats[3].msg
    assert (n.status, n.message, list(n.state_names)) == (2, 'it 6', ['v', 'beta'])
    assert list(n.predicted_states) == [6.0, -1.0]


def test_topic_filter(tmp_path):
    write_run(tmp_path / 'bag', 10).close()
    out = read_bag(tmp_path / 'bag', topics=['/drift/nmpc/status'], backend='mcap')
    assert list(out) == ['/drift/nmpc/status'] and len(out['/drift/nmpc/status']) == 5


def test_killed_writer_keeps_flushed_chunks(tmp_path):
    """The file as a SIGKILL leaves it: flushed chunks, no summary; read as it is, unchanged."""
    w = write_run(tmp_path / 'live', 40, chunk_size=10**6, flush_every=20)   # flushed at 20, 40
    enc = encoder('drift_msgs/msg/VehicleState')
    for i in range(40, 45):                                   # in the open chunk: lost
        w.write('/vehicle/state', enc(state(i)), T0 + i * 10**7)
    shutil.copytree(tmp_path / 'live', tmp_path / 'killed')
    w.close()
    assert bag_info(tmp_path / 'killed').message_count == 60   # metadata.yaml as of the last flush
    before = (tmp_path / 'killed' / 'live_0.mcap').read_bytes()
    for backend in ('rosbags', 'mcap'):
        out = read_bag(tmp_path / 'killed', backend=backend)
        assert [m.msg.v for m in out['/vehicle/state']] == [0.5 * i for i in range(40)]
        assert len(out['/drift/nmpc/status']) == 20
    assert (tmp_path / 'killed' / 'live_0.mcap').read_bytes() == before


def test_refuses_to_overwrite_a_bag(tmp_path):
    write_run(tmp_path / 'bag', 3).close()
    with pytest.raises(BagExistsError):
        BagWriter(tmp_path / 'bag')


def test_empty_bag_is_valid(tmp_path):
    BagWriter(tmp_path / 'bag').close()
    assert bag_info(tmp_path / 'bag').message_count == 0
    assert read_bag(tmp_path / 'bag', backend='rosbags') == {}
    assert read_bag(tmp_path / 'bag', backend='mcap') == {}
