"""Replay core: recorded order, topic filter, pacing, a truncated bag read without changing it."""
import pytest

from drift_tools.bag_writer import BagWriter
from drift_tools.replay import Pacer, iter_raw, message_class

rclpy_serialization = pytest.importorskip('rclpy.serialization')
drift_msgs = pytest.importorskip('drift_msgs.msg')


def make_bag(path, n=20):
    from std_msgs.msg import String
    with BagWriter(path) as bag:
        bag.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
        bag.add_topic('/note', 'std_msgs/msg/String')
        for i in range(n):
            state = drift_msgs.VehicleState(v=float(i))
            bag.write('/vehicle/state', rclpy_serialization.serialize_message(state),
                      log_time_ns=1_000_000_000 + i * 10_000_000)
            if i % 5 == 0:
                bag.write('/note', rclpy_serialization.serialize_message(String(data=f'n{i}')),
                          log_time_ns=1_000_000_000 + i * 10_000_000 + 1)
    return path


def test_messages_come_back_in_recorded_order_and_decode(tmp_path):
    raws = list(iter_raw(make_bag(tmp_path / 'bag')))
    assert len(raws) == 24
    assert [r.t_ns for r in raws] == sorted(r.t_ns for r in raws)
    states = [r for r in raws if r.topic == '/vehicle/state']
    cls = message_class(states[0].msgtype)
    assert [rclpy_serialization.deserialize_message(r.data, cls).v for r in states] == \
        [float(i) for i in range(20)]


def test_topic_filter(tmp_path):
    raws = list(iter_raw(make_bag(tmp_path / 'bag'), topics=['/note']))
    assert {r.topic for r in raws} == {'/note'} and len(raws) == 4


def test_truncated_bag_replays_what_it_holds_and_is_not_changed(tmp_path):
    bag = make_bag(tmp_path / 'bag', n=200)
    mcap = next(bag.glob('*.mcap'))
    whole = list(iter_raw(bag))
    mcap.write_bytes(mcap.read_bytes()[:-200])            # the summary and footer gone
    cut = mcap.read_bytes()
    assert [(r.topic, r.t_ns, r.data) for r in iter_raw(bag)] == \
        [(r.topic, r.t_ns, r.data) for r in whole]
    assert mcap.read_bytes() == cut


def test_unknown_message_type_is_a_lookup_error():
    with pytest.raises(LookupError, match='not installed'):
        message_class('no_such_pkg/msg/Thing')


def test_pacer_keeps_recorded_spacing_scaled_by_rate():
    now = [100.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    pacer = Pacer(rate=2.0, clock=lambda: now[0], sleep=sleep)
    for t_ns in (0, 1_000_000_000, 3_000_000_000):
        pacer.wait_until(t_ns)
    assert slept == pytest.approx([0.5, 1.0])
    fast = Pacer(rate=0.0, clock=lambda: now[0], sleep=sleep)
    fast.wait_until(0)
    fast.wait_until(10**12)
    assert len(slept) == 2


def test_a_window_and_loops_shift_time_forward(tmp_path):
    from drift_tools.replay import iter_replay, restamp
    bag = make_bag(tmp_path / 'bag', n=20)          # states every 10 ms from 1 s
    one = list(iter_replay(bag, ['/vehicle/state'], start=0.05, end=0.1))
    assert [r.t_ns for r in one] == [1_050_000_000 + i * 10_000_000 for i in range(6)]
    two = list(iter_replay(bag, ['/vehicle/state'], start=0.05, end=0.1, loops=2))
    times = [r.t_ns for r in two]
    assert times == sorted(times) and len(two) == 12 and times[6] == times[5] + 10_000_000
    cls = message_class('drift_msgs/msg/VehicleState')
    msg = rclpy_serialization.deserialize_message(two[6].data, cls)
    first = rclpy_serialization.deserialize_message(two[0].data, cls)
    shift = (msg.header.stamp.sec - first.header.stamp.sec) * 10**9 + \
        msg.header.stamp.nanosec - first.header.stamp.nanosec
    assert shift == two[6].t_ns - two[0].t_ns, 'the stamp moves with the log time'
    assert restamp(b'\x00\x01\x00\x00abcdefgh', 'std_msgs/msg/String', 5) == \
        b'\x00\x01\x00\x00abcdefgh', 'no leading stamp: unchanged'
    with pytest.raises(ValueError, match='outside the bag'):
        list(iter_replay(bag, start=5.0))


def test_topics_keep_their_recorded_qos(tmp_path):
    from drift_tools.replay import topic_qos
    with BagWriter(tmp_path / 'bag') as bag:
        bag.add_topic('/drift/path', 'nav_msgs/msg/Path', latched=True)
        bag.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState', reliable=False)
        bag.write('/drift/path', rclpy_serialization.serialize_message(
            pytest.importorskip('nav_msgs.msg').Path()), 1)
        bag.write('/vehicle/state', rclpy_serialization.serialize_message(
            drift_msgs.VehicleState()), 2)
    assert topic_qos(tmp_path / 'bag') == {'/drift/path': (True, True),
                                           '/vehicle/state': (False, False)}
