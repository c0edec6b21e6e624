"""Run report on a synthetic bag with known answers: windows, metrics, files."""
import json
import math

import numpy as np
import pytest

from drift_tools.bag import read_bag
from drift_tools.bag_writer import BagWriter
from drift_tools.report import run_metrics, steady_windows, write_report
from drift_tools.timeseries import resample, series_from_bag

ser = pytest.importorskip('rclpy.serialization')
msgs = pytest.importorskip('drift_msgs.msg')


def stamp(msg, t):
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int(round((t % 1) * 1e9))
    return msg


def synthetic_bag(path, offset_deg=1.0, e_y_peak=3.0):
    """20 s: grip for 4 s, ramp to -30 deg by 6 s, then hold with a constant sideslip offset."""
    with BagWriter(path) as bag:
        for topic, typ in (('/vehicle/state', 'drift_msgs/msg/VehicleState'),
                           ('/drift/reference', 'drift_msgs/msg/DriftReference'),
                           ('/drift/command', 'drift_msgs/msg/DriftCommand'),
                           ('/drift/nmpc/status', 'drift_msgs/msg/NmpcStatus')):
            bag.add_topic(topic, typ)
        for k in range(2000):
            t = 100.0 + k * 0.01
            tr = t - 100.0
            beta_ref = -math.radians(30.0) * min(max((tr - 4.0) / 2.0, 0.0), 1.0)
            beta = beta_ref - math.radians(offset_deg) * (tr > 6.0)
            e_y = e_y_peak * math.exp(-tr) if tr < 8.0 else 0.2 * math.sin(tr)
            st = stamp(msgs.VehicleState(v=10.0, beta=beta, r=0.7, x=tr, y=0.0), t)
            st.wheel_speeds = [30.0, 30.0, 40.0, 40.0]
            log_ns = int(t * 1e9)
            bag.write('/vehicle/state', ser.serialize_message(st), log_ns)
            if k % 2 == 0:
                ref = stamp(msgs.DriftReference(direction=1 if tr > 4.0 else 0, e_y=e_y), t)
                ref.target.beta = beta_ref
                bag.write('/drift/reference', ser.serialize_message(ref), log_ns + 1)
                cmd = stamp(msgs.DriftCommand(mode=1, delta=-0.3, drive_torque=1400.0), t)
                bag.write('/drift/command', ser.serialize_message(cmd), log_ns + 2)
                status = stamp(msgs.NmpcStatus(status=0, solve_time=0.002 + 0.001 * (k % 3)), t)
                bag.write('/drift/nmpc/status', ser.serialize_message(status), log_ns + 3)
    return path


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    bag = synthetic_bag(tmp_path_factory.mktemp('bags') / 'run')
    return bag, series_from_bag(read_bag(bag))


def test_series_are_relative_to_the_first_state_and_resample_by_hold(run):
    _, series = run
    assert series.state['t'][0] == 0.0
    assert series.duration == pytest.approx(19.99)
    t = np.array([-1.0, 0.0, 0.015, 10.0])
    held = resample(series.reference, t, 'beta')
    assert math.isnan(held[0]) and held[1] == 0.0 and held[2] == 0.0
    assert held[3] == pytest.approx(-math.radians(30.0))


def test_steady_windows_come_from_the_reference_plateau(run):
    _, series = run
    windows, transient_end = steady_windows(series, settle=3.0)
    assert len(windows) == 1
    # the plateau starts where the ramp is within 1 deg of 30 deg (5.93 s), then 3 s settle
    assert windows[0][0] == pytest.approx(4.0 + 2.0 * 29.0 / 30.0 + 3.0, abs=0.02)
    assert windows[0][1] == pytest.approx(19.98, abs=0.05)
    assert transient_end == windows[0][0]


def test_metrics_recover_the_known_errors(run):
    _, series = run
    m = run_metrics(series)
    assert m['beta_rms_error_deg'] == pytest.approx(1.0, abs=1e-6)
    assert m['mean_abs_beta_steady_deg'] == pytest.approx(31.0, abs=1e-6)
    assert m['max_abs_e_y_m'] == pytest.approx(0.2, abs=0.01)   # the 3 m peak is before 9 s
    assert not m['spun']
    assert m['solve_time_ms_p50'] == pytest.approx(3.0)
    assert m['solve_time_ms_max'] == pytest.approx(4.0)
    assert m['nmpc_cycles'] == 1000 and m['nmpc_not_ok'] == 0


def test_report_files_are_written(run, tmp_path):
    bag, series = run
    m = write_report(series, tmp_path / 'report', bag.name, windows=[[10.0, 19.0]],
                     transient_end=10.0)
    saved = json.loads((tmp_path / 'report' / 'metrics.json').read_text())
    assert saved['steady_windows_s'] == [[10.0, 19.0]]
    assert saved['beta_rms_error_deg'] == pytest.approx(m['beta_rms_error_deg'])
    for name in ('report.md', 'states.png', 'inputs.png', 'path.png', 'solve_time.png'):
        assert (tmp_path / 'report' / name).stat().st_size > 1000 or name == 'report.md'
    assert '| spun | no |' in (tmp_path / 'report' / 'report.md').read_text()


def test_a_bag_without_states_is_a_clear_error(tmp_path):
    with BagWriter(tmp_path / 'empty') as bag:
        bag.add_topic('/drift/command', 'drift_msgs/msg/DriftCommand')
    with pytest.raises(ValueError, match='no vehicle state'):
        run_metrics(series_from_bag(read_bag(tmp_path / 'empty')))
