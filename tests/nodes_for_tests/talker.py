"""Test node: publishes numbered drift_msgs on stack topics; can exit or crash on cue.

Parameters: rate [Hz], count (0 = forever), wait_for (subscriptions on vehicle/state to wait
for before publishing), exit_after [s] (0 = never) with exit_code, and config_dir/scenario as
every stack node declares. Prints ``published <n>`` when it stops.
"""
import sys
import time

from drift_msgs.msg import DriftCommand, VehicleState
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import Float64


class Talker(Node):
    def __init__(self):
        super().__init__('talker')
        self.declare_parameter('config_dir', '')
        self.declare_parameter('scenario', '')
        rate = self.declare_parameter('rate', 50.0).value
        self.count = self.declare_parameter('count', 0).value
        self.wait_for = self.declare_parameter('wait_for', 0).value
        self.exit_after = self.declare_parameter('exit_after', 0.0).value
        self.exit_code = self.declare_parameter('exit_code', 0).value
        self.state_pub = self.create_publisher(VehicleState, 'vehicle/state', qos_profile_sensor_data)
        self.cmd_pub = self.create_publisher(DriftCommand, 'drift/command', 10)
        self.sim_pub = self.create_publisher(Float64, 'sim/debug', 10)
        self.sent = 0
        self.t0 = time.monotonic()
        self.create_timer(1.0 / rate, self.tick)
        self.get_logger().info(f'talker up, use_sim_time={self.get_parameter("use_sim_time").value}')

    def tick(self):
        if self.exit_after and time.monotonic() - self.t0 > self.exit_after:
            print(f'published {self.sent}; exiting with {self.exit_code}', flush=True)
            raise SystemExit(self.exit_code)
        if (self.count and self.sent >= self.count) or \
                self.cmd_pub.get_subscription_count() < self.wait_for or \
                self.state_pub.get_subscription_count() < self.wait_for or \
                self.sim_pub.get_subscription_count() < self.wait_for:
            return
        stamp = self.get_clock().now().to_msg()
        state = VehicleState(v=float(self.sent), wheel_speeds=[1.0, 2.0, 3.0, 4.0])
        state.header.stamp = stamp
        self.state_pub.publish(state)
        cmd = DriftCommand(mode=DriftCommand.MODE_FULL, delta=-0.1, drive_torque=float(self.sent))
        cmd.header.stamp = stamp
        self.cmd_pub.publish(cmd)
        self.sim_pub.publish(Float64(data=float(self.sent)))
        self.sent += 1


    def close(self):
        print(f'published {self.sent}', flush=True)


def main(args=None):
    # as every stack node: a stop signal ends the spin cleanly, also mid-callback
    from drift_control.nodes.spin import run_node
    return run_node(Talker, 'talker', args)


if __name__ == '__main__':
    sys.exit(main())
