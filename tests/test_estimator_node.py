"""The estimator stage on ROS: sensor samples as messages, and the sim and estimator nodes in
their own processes (the simulator's samples in, the state out, a malformed frame survived)."""
import math
import os
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.ros


def test_sensor_samples_round_trip_and_keep_their_age():
    from drift_control.estimator import FIELDS, SensorSample
    from drift_control.nodes import convert
    from drift_msgs.msg import SensorSample as SampleMsg
    samples = [SensorSample('ins', 4.98, (9.0, -0.5, 0.6, 1.0, 2.0, 0.3)),
               SensorSample('imu', 4.99, (0.1, 5.0, 0.6)),
               SensorSample('torque', 4.98, (1500.0,))]
    assert [getattr(SampleMsg, f'UNIT_{u.upper()}') for u in FIELDS] == list(range(len(FIELDS)))
    # a wall-clock arrival stamp: each sample keeps its age to the nanosecond
    m = convert.sensor_samples_to_msg(samples, 1_700_000_000.5, t=5.0)
    now, back = convert.sensor_samples_from_msg(m, epoch=1_700_000_000)
    assert now == 0.5
    assert [s.stamp for s in back] == [0.48, 0.49, 0.48]
    assert [(s.unit, s.values) for s in back] == [(s.unit, s.values) for s in samples]
    now, back = convert.sensor_samples_from_msg(convert.sensor_samples_to_msg(samples, 5.0))
    assert back == samples and now == 5.0


@pytest.mark.parametrize('unit, values, reason', [
    (9, [1.0], 'out of range'), (1, [1.0, 2.0], 'needs 3'), (4, [math.nan], 'finite')])
def test_a_malformed_sample_is_refused_with_its_reason(unit, values, reason):
    from drift_control.nodes import convert
    from drift_msgs.msg import SensorSample, SensorSamples

    class Log:
        lines = []

        def warning(self, text, **_):
            self.lines.append(text)

    log = Log()
    m = SensorSamples(samples=[SensorSample(unit=unit, values=values)])
    assert convert.decode(convert.sensor_samples_from_msg, m, log) is None
    assert reason in log.lines[0]


def test_sim_with_sensors_feeds_the_estimator_node(monkeypatch):
    import rclpy
    from drift_msgs.msg import SensorSample, SensorSamples, VehicleState
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    monkeypatch.setenv('ROS_DOMAIN_ID', str(80 + os.getpid() % 10))   # 80..89: these tests
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    common = ['-p', 'scenario:=steady_dry']
    procs = [subprocess.Popen([sys.executable, '-m', module, '--ros-args', *common, *extra],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
             for module, extra in (
                 ('drift_sim.nodes.sim_node', ['-p', 'sensors:=realistic',
                                               '-p', 'startup_timeout:=120.0']),
                 ('drift_control.nodes.estimator_node', []))]
    rclpy.init()
    node = rclpy.create_node('estimator_test')
    frames, states = {}, []
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    try:
        node.create_subscription(SensorSamples, 'vehicle/sensors', lambda m: frames.setdefault(
            (m.header.stamp.sec, m.header.stamp.nanosec), m), reliable)
        node.create_subscription(VehicleState, 'vehicle/state', states.append, reliable)
        bad = node.create_publisher(SensorSamples, 'vehicle/sensors', reliable)

        def spin_until(cond, what, timeout=90.0):
            deadline = time.monotonic() + timeout
            while not cond():
                assert time.monotonic() < deadline, what
                assert all(p.poll() is None for p in procs), f'a node ended: {what}'
                rclpy.spin_once(node, timeout_sec=0.05)

        spin_until(lambda: len(states) >= 20 and len(frames) >= 20, 'no frames or states')
        # the state comes from the estimator alone, one per frame, stamped with the frame
        assert node.get_publishers_info_by_topic('/vehicle/state')[0].node_name == 'estimator'
        assert len(node.get_publishers_info_by_topic('/vehicle/state')) == 1
        last = (states[-1].header.stamp.sec, states[-1].header.stamp.nanosec)
        spin_until(lambda: last in frames, 'a state stamped unlike every frame')
        assert 8.0 < states[-1].v < 14.0 and abs(states[-1].r) > 0.3, 'a car in a drift'
        spin_until(lambda: bad.get_subscription_count() >= 2, 'the estimator never matched us')
        bad.publish(SensorSamples(samples=[SensorSample(unit=7, values=[1.0])]))
        n = len(states)
        spin_until(lambda: len(states) >= n + 20, 'no states after a malformed frame')
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        outs = []
        for p in procs:
            p.terminate()
            outs.append(p.communicate(timeout=30)[0])
    assert 'rejected a malformed SensorSamples: sensor unit 7 out of range' in outs[1], outs[1]
    assert 'ekf for m3_competition' in outs[1], outs[1]


@pytest.mark.slow
def test_the_lockstep_graph_with_sensors_is_the_one_process_loop_bit_for_bit(tmp_path):
    """run_stack --sensors (estimator and selector in the NMPC's process) against
    drift_sim.closed_loop with the same sensors and estimator: the same code, the same run."""
    import numpy as np
    from drift_sim.closed_loop import run_closed_loop
    from drift_tools.bag import read_bag
    from drift_tools.timeseries import series_from_bag
    from conftest import REPO
    proc = subprocess.run(
        [sys.executable, str(REPO / 'scripts' / 'run_stack.py'), '--scenario', 'steady_dry',
         '--clock', 'lockstep', '--sim-duration', '3', '--duration', '80', '--sensors',
         'realistic', '--bag', str(tmp_path / 'bag'), '--domain-id', '131', '--no-summary'],
        env={**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
        capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert 'state: sensors realistic -> estimator ekf in nmpc' in proc.stdout
    truth = series_from_bag(read_bag(tmp_path / 'bag')).truth
    _, trace = run_closed_loop('steady_dry', ['duration=3'], sensors='realistic', estimator='ekf')
    at = {round(t, 6): i for i, t in enumerate(trace['t'])}
    rows = [(i, at[round(t, 6)]) for i, t in enumerate(truth['t']) if round(t, 6) in at]
    assert len(rows) >= 299, f'only {len(rows)} common samples'
    for key in ('V', 'beta', 'r', 'delta', 'x', 'y'):
        np.testing.assert_array_equal([truth[key][i] for i, _ in rows],
                                      [trace[key][j] for _, j in rows], err_msg=key)
