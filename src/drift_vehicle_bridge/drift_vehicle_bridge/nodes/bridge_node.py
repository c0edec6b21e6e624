"""The vehicle bridge node: the car's link (CAN, CAN FD, PDUs over UDP) <-> vehicle/state, drift/command.

``sensors:=true``: the sensor units' samples on vehicle/sensors for the state estimator instead
of vehicle/state, whose estimate (on vehicle/state) the modes then judge (config/bridge.yaml
``sensors``).
"""
import sys
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from drift_msgs.msg import DriftCommand, SensorSamples, VehicleState
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_srvs.srv import SetBool

from drift_control.cycle_watch import CycleWatch
from drift_control.estimator import SensorSample
from drift_control.nodes.convert import decode, sensor_samples_to_msg, state_from_msg
from drift_control.nodes.qos import kept_qos
from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import raise_real_time
from drift_control.nodes.spin import run_node
from drift_control.ocp import load_nmpc_params
from drift_control.params import config_dir, load_vehicle, parse_overrides
from drift_control.plausibility import InputChecker
from drift_control.scenario import load_scenario_spec
from drift_vehicle_bridge.codec import Codec
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.nodes import convert
from drift_vehicle_bridge.params import description_path, load_bridge_params
from drift_vehicle_bridge.peers import HeartbeatWatch
from drift_vehicle_bridge.replay import LogReplay
from drift_vehicle_bridge.transport import open_transport


class BridgeNode(Node):
    """Runs the gateway cycle on a timer; a ``log_file`` replays a drive instead (read-only)."""

    def __init__(self, **kwargs):
        super().__init__('vehicle_bridge', **kwargs)
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        vehicle = self.declare_parameter('vehicle', '').value   # limits: '' = the scenario's car
        if not vehicle and scenario:
            vehicle = load_scenario_spec(scenario, config=cfg).vehicle
        bus = {'interface': self.declare_parameter('interface', '').value,
               'channel': self.declare_parameter('channel', '').value,
               'bitrate': self.declare_parameter('bitrate', 0).value}
        bus = {k: v for k, v in bus.items() if v}    # '' / 0: keep config/bridge.yaml's
        log_file = self.declare_parameter('log_file', '').value
        auto_arm = self.declare_parameter('auto_arm', False).value   # virtual/udp_multicast only
        sensors = self.declare_parameter('sensors', False).value
        # link_set: the overrides naming the link (shared with a simulated car), then set
        link_set = [o for o in self.declare_parameter('link_set', ['']).value if o]
        overrides = parse_overrides(link_set + [o for o in self.declare_parameter(
            'set', ['']).value if o], 'bridge')
        overrides.setdefault('bus', {}).update(bus)
        if auto_arm:
            overrides['auto_arm'] = True
        if sensors:
            overrides.setdefault('sensors', {})['enabled'] = True
        params = load_bridge_params(cfg, overrides, vehicle or None)
        codec = Codec.load(description_path(params, cfg))
        nmpc = load_nmpc_params(Path(cfg) / 'nmpc.yaml')   # the controller's input limits
        checker = InputChecker(load_vehicle(vehicle or None, cfg),
                               nmpc.inputs.for_period(params.cycle_time, nmpc.Ts))
        self._gw = Gateway(None if log_file else open_transport(params), codec, params, checker)
        self._replay = LogReplay(log_file) if log_file else None
        self._hw = log_file or params.link()
        self._stats, self._diag_period = None, 1.0
        self._ticked = False
        self._cycle = CycleWatch()   # the longest gap between two cycles, for the diagnostics
        if params.sensors.enabled:   # the estimator publishes the state; the modes judge it
            self._sensor_pub = self.create_publisher(SensorSamples, 'vehicle/sensors', kept_qos())
            self.create_subscription(VehicleState, 'vehicle/state', self._on_estimate, QoSProfile(
                depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        else:
            self._state_pub = self.create_publisher(VehicleState, 'vehicle/state', kept_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self.create_subscription(DriftCommand, 'drift/command', self._on_command, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._recorder = HeartbeatWatch('recorder')    # not critical: reported, not needed
        self._recorder_lost = False
        self.create_subscription(DiagnosticArray, 'diagnostics', self._on_peer_diag, 10)
        self.create_service(SetBool, 'bridge/arm', self._on_arm)
        self.create_timer(params.cycle_time, self._on_tick)
        self.create_timer(self._diag_period, self._on_diag)
        raise_real_time()   # its 10 ms cycle before the controller's bursts (a launch under chrt)
        lock_parameters(self)   # every parameter is read once, at start
        self.get_logger().info(f'vehicle bridge on {self._hw}, mode {self._gw.mode.name}'
                               + (', auto-arm (simulation)' if params.auto_arm else ''))

    def _on_command(self, msg):
        self._gw.set_command(convert.command_from_msg(msg), time.monotonic())

    def _on_estimate(self, msg):
        state = decode(state_from_msg, msg, self.get_logger())
        if state is not None:
            self._gw.set_estimate(state, time.monotonic())

    def _on_arm(self, request, response):
        if request.data:
            response.success, response.message = self._gw.request_arm(time.monotonic())
        else:
            self._gw.disarm(time.monotonic())
            response.success, response.message = True, 'disarmed'
        self.get_logger().info(f'arm request {request.data}: {response.message}')
        return response

    def _on_peer_diag(self, msg):
        for status in msg.status:
            if status.name == self._recorder.name:
                self._recorder.report(convert.level_of(status), status.message, time.monotonic())

    def _on_tick(self):
        # one bus cycle per tick, never a catch-up burst: several command frames within a
        # millisecond would move the actuators at a multiple of the limited rate
        if not self._ticked:   # what queued up while the node started is not the car now
            self._ticked = True
            self._gw.discard_backlog()
        now = time.monotonic()
        self._cycle.tick(now)
        for msg in self._replay.due(now) if self._replay else ():
            self._gw.receive(msg, now)
        state = self._gw.step(now)
        if self._gw.sensors is not None:
            samples = self._gw.take_samples(now)
            if samples:   # stamped on this node's clock: now minus each sample's age
                self._sensor_pub.publish(sensor_samples_to_msg(
                    [SensorSample(s.unit, -s.age, s.values) for s in samples],
                    self.get_clock().now(), 0.0))
        elif state is not None:
            self._state_pub.publish(convert.state_to_msg(state, self.get_clock().now().to_msg()))

    def _on_diag(self):
        stats = self._gw.stats()
        diag = convert.stats_to_diagnostics(stats, self._stats, self._diag_period,
                                            self.get_clock().now().to_msg(), self._hw)
        diag.status[0].values.extend(convert.key_values(convert.gap_values(
            'cycle_gap', self._cycle.take())))
        if stats['dropped_at'] is not None:   # the last drop on the ROS clock, as the stamps
            ago = time.monotonic() - stats['dropped_at']
            diag.status[0].values.extend(convert.key_values(
                {'drop_stamp': f'{self.get_clock().now().nanoseconds * 1e-9 - ago:.6f}'}))
        recording = self._recorder.status(time.monotonic())
        if recording is not None:
            diag.status.append(convert.peer_status('vehicle_bridge: recording', *recording))
            if recording[0] >= 2 and not self._recorder_lost:
                self.get_logger().error(f'recording lost: {recording[1]}')
            self._recorder_lost = recording[0] >= 2
        self._diag_pub.publish(diag)
        self._stats = stats

    def close(self):
        self._gw.shutdown()
        if self._gw.transport is not None:
            self._gw.transport.shutdown()


def main(args=None) -> int:
    return run_node(BridgeNode, 'bridge', args)


if __name__ == '__main__':
    sys.exit(main())
