"""Vehicle bridge node: state frames in -> vehicle/state out; arm service; commands -> the car."""
import math
import os
import subprocess
import sys
import time
from dataclasses import replace

import can
import pytest

from drift_control.signals import Mode, Validity, VehicleState
from drift_vehicle_bridge.vehicle_side import CarSide

pytestmark = pytest.mark.ros

CALM = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                    wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0,
                    x=5.0, y=-2.0, yaw=0.3)


@pytest.fixture
def ros_env(monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(30 + os.getpid() % 20))    # 30..49: the bridge's
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return dict(os.environ, PYTHONUNBUFFERED='1')


def _spin_until(executor, cond, timeout, each=None):
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, 'timed out'
        if each:
            each()
        executor.spin_once(timeout_sec=0.005)


def test_node_on_a_virtual_bus_publishes_state_arms_and_commands_the_car(ros_env):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from drift_msgs.msg import DriftCommand, VehicleState as VehicleStateMsg
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from std_srvs.srv import SetBool

    from drift_vehicle_bridge.nodes.bridge_node import BridgeNode

    channel = f'bridge-node-{os.getpid()}'
    rclpy.init()
    car_bus = can.Bus(channel, interface='virtual')
    bridge = BridgeNode(parameter_overrides=[Parameter('interface', value='virtual'),
                                             Parameter('channel', value=channel)])
    test = rclpy.create_node('bridge_test')
    executor = SingleThreadedExecutor()
    try:
        executor.add_node(bridge)
        executor.add_node(test)
        car = CarSide(car_bus)
        states, diags, applied = [], [], []
        test.create_subscription(VehicleStateMsg, 'vehicle/state', states.append,
                                 qos_profile_sensor_data)
        test.create_subscription(DiagnosticArray, 'diagnostics', diags.append, 10)
        cmd_pub = test.create_publisher(DriftCommand, 'drift/command', 10)
        arm = test.create_client(SetBool, 'bridge/arm')
        last_send = [0.0]

        def car_cycle():
            now = time.monotonic()
            if now - last_send[0] >= 0.01:   # V moving in its last digits, as measured
                car.send_state(replace(CALM, stamp=now, V=8.0 + 0.02 * math.sin(300.0 * now)))
                last_send[0] = now
            cmd = car.poll_command(now)
            if cmd is not None:
                applied.append(cmd)

        _spin_until(executor, lambda: any(m.validity == int(Validity.ALL) for m in states),
                    10.0, car_cycle)
        m = states[-1]
        assert m.v == pytest.approx(8.0, abs=0.025) and m.beta == pytest.approx(-0.05, abs=5e-4)
        assert list(m.wheel_speeds) == pytest.approx([24.0, 24.0, 24.5, 24.5], abs=0.005)
        assert m.yaw == pytest.approx(0.3, abs=1e-4)
        assert not applied, 'nothing is applied before arming'

        future = arm.call_async(SetBool.Request(data=True))
        _spin_until(executor, future.done, 10.0, car_cycle)
        assert future.result().success, future.result().message

        def car_and_controller():
            car_cycle()
            cmd_pub.publish(DriftCommand(mode=DriftCommand.MODE_FULL, delta=-0.2,
                                         delta_rate=-0.5, drive_torque=2500.0))
        _spin_until(executor, lambda: len(applied) >= 20, 10.0, car_and_controller)
        assert applied[-1].mode == Mode.FULL and -0.2 <= applied[-1].delta < 0.03

        def diag_values():
            return [{kv.key: kv.value for kv in d.status[0].values} for d in diags]
        _spin_until(executor, lambda: any(v['mode'] == 'ACTIVE_FULL' for v in diag_values()),
                    5.0, car_and_controller)
        values = next(v for v in diag_values() if v['mode'] == 'ACTIVE_FULL')
        assert float(values['rx_hz/DS_YAW']) > 20.0 and values['validity'] == '0x7ff', values

        future = arm.call_async(SetBool.Request(data=False))
        _spin_until(executor, future.done, 10.0, car_cycle)
        t_end = time.monotonic() + 0.05    # the bridge's next 10 ms tick says OFF
        _spin_until(executor, lambda: time.monotonic() > t_end, 1.0, car_cycle)
        n = len(applied)
        t_end = time.monotonic() + 0.1
        _spin_until(executor, lambda: time.monotonic() > t_end, 1.0, car_cycle)
        assert len(applied) == n and car.bridge_mode.name == 'OFF', 'disarmed: the car releases'
    finally:
        executor.shutdown()
        bridge.close()
        bridge.destroy_node()
        test.destroy_node()
        car_bus.shutdown()
        rclpy.try_shutdown()


def test_node_replays_a_candump_log_in_its_own_process(ros_env, tmp_path):
    import rclpy
    from drift_msgs.msg import VehicleState as VehicleStateMsg
    from rclpy.qos import qos_profile_sensor_data

    log_file = tmp_path / 'drive.log'

    class LogLink:   # CarSide's transport: each PDU a frame of the log at the drive's time
        t = 0.0

        def send(self, pdu):
            writer.on_message_received(can.Message(
                timestamp=1_700_000_000.0 + self.t, arbitration_id=pdu.id, data=pdu.data,
                is_extended_id=False))

        def flush(self):
            pass

    with can.Logger(str(log_file)) as writer:
        bus = LogLink()
        car = CarSide(bus)
        for k in range(600):                      # 6 s of a car speeding up
            bus.t = 0.01 * k
            car.send_state(replace(CALM, V=5.0 + 0.5 * bus.t, stamp=bus.t))
    proc = subprocess.Popen(
        [sys.executable, '-m', 'drift_vehicle_bridge.nodes.bridge_node', '--ros-args',
         '-p', f'log_file:={log_file}'], env=ros_env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node('bridge_replay_test')
    states = []
    try:
        node.create_subscription(VehicleStateMsg, 'vehicle/state', states.append,
                                 qos_profile_sensor_data)
        deadline = time.monotonic() + 20.0
        while len([m for m in states if m.validity == int(Validity.ALL)]) < 20:
            assert time.monotonic() < deadline and proc.poll() is None, 'no replayed state'
            rclpy.spin_once(node, timeout_sec=0.1)
        valid = [m for m in states if m.validity == int(Validity.ALL)]
        speeds = [m.v for m in valid]
        assert all(5.0 <= v <= 8.0 for v in speeds) and speeds[-1] > speeds[0], speeds
    finally:
        proc.terminate()
        out = proc.communicate(timeout=10)[0]
        node.destroy_node()
        rclpy.try_shutdown()
    assert 'vehicle bridge on' in out, out
