"""Run summary from a bag: counts, rates and gaps of receive times; metrics from decoded fields."""
import math

import numpy as np
import pytest
from mcap_ros2._dynamic import serialize_dynamic

from drift_tools.bag_writer import BagWriter
from drift_tools.msgdef import message_definition
from drift_tools.summary import format_summary, summarize_bag

T0 = 1_700_000_000 * 10**9   # [ns]


def enc(msgtype):
    return serialize_dynamic(msgtype, message_definition(msgtype))[msgtype]


@pytest.fixture
def bag(tmp_path):
    state, clock = enc('drift_msgs/msg/VehicleState'), enc('rosgraph_msgs/msg/Clock')
    with BagWriter(tmp_path / 'bag') as w:
        w.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
        w.add_topic('/clock', 'rosgraph_msgs/msg/Clock')
        w.add_topic('/drift/path', 'nav_msgs/msg/Path')
        for i in range(101):                       # 100 Hz for 1 s, one 50 ms hole
            t = T0 + i * 10**7 + (4 * 10**7 if i > 50 else 0)
            w.write('/vehicle/state', state({'v': 8.0 + 0.01 * i, 'beta': -np.radians(0.3 * i)}), t)
            w.write('/clock', clock({'clock': {'sec': 100 + i // 50, 'nanosec': (i % 50) * 4 * 10**7}}), t)
    return tmp_path / 'bag'


@pytest.mark.parametrize('backend', ['rosbags', 'mcap'])
def test_summary_counts_rates_gaps_and_metrics(bag, backend):
    s = summarize_bag(bag, backend=backend)
    st = s.topics['/vehicle/state']
    assert st.count == 101 and st.msgtype == 'drift_msgs/msg/VehicleState'
    assert st.rate_hz == pytest.approx(100 / 1.04)
    assert st.max_gap_s == pytest.approx(0.05, abs=1e-6)   # float s since the epoch: ~0.2 us
    assert s.duration_s == pytest.approx(1.04)
    assert s.metrics['sideslip_abs_max_deg'] == pytest.approx(30.0)
    assert s.metrics['speed_max_mps'] == pytest.approx(9.0)
    assert s.metrics['sim_time_span_s'] == pytest.approx(2.0)   # clock ran twice as fast
    assert s.topics['/drift/path'].count == 0 and math.isnan(s.topics['/drift/path'].rate_hz)
    text = format_summary(s)
    assert '/vehicle/state' in text and 'sideslip_abs_max_deg = 30' in text
