"""Estimator node: vehicle/sensors -> the state estimator -> vehicle/state, one step per frame."""
import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from drift_msgs.msg import SensorSamples, VehicleState
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from drift_control.assembly import load_setup
from drift_control.estimator import FrameStepper, build_estimator
from drift_control.nodes import convert
from drift_control.nodes.qos import kept_qos
from drift_control.nodes.priority import raise_real_time
from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.spin import run_node
from drift_control.params import config_dir


class EstimatorNode(Node):
    """Fuses each frame of sensor samples into the state the selector and the NMPC read."""

    def __init__(self):
        super().__init__('estimator')
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        vehicle = self.declare_parameter('vehicle', '').value      # '' = the scenario's
        overrides = [o for o in self.declare_parameter('set', ['']).value if o]   # scenario's
        kind = self.declare_parameter('estimator', 'ekf').value
        estimator_set = [o for o in self.declare_parameter('estimator_set', ['']).value if o]
        setup = load_setup(cfg, scenario, vehicle or None, overrides, with_map=False)
        self._stepper = FrameStepper(build_estimator(
            kind, setup.vehicle, setup.config / 'estimator.yaml', estimator_set,
            intervals=False))   # its status reports the NIS without intervals
        self._epoch = None      # whole seconds taken off every stamp (wall-clock stamps)
        self._log = StepperLog(self.get_logger())
        reliable = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)   # every frame
        self._state_pub = self.create_publisher(VehicleState, 'vehicle/state', kept_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self.create_subscription(SensorSamples, 'vehicle/sensors', self._on_samples, reliable)
        self.create_timer(1.0, self._publish_diagnostics)
        raise_real_time(by=0)   # after start-up: at the launch's priority, as the controller
        lock_parameters(self)   # every parameter is read once, at start
        self.get_logger().info(f'{kind} for {setup.vehicle_name}')

    def _on_samples(self, msg):
        if self._epoch is None:
            self._epoch = msg.header.stamp.sec
        frame = convert.decode(lambda m: convert.sensor_samples_from_msg(m, self._epoch), msg,
                               self.get_logger())
        if frame is None:
            return
        now, samples = frame
        state = self._stepper.step(samples, now)
        self._log(self._stepper, self._epoch)
        if state is not None:   # stamped with the frame's own arrival stamp, to the nanosecond
            self._state_pub.publish(convert.state_to_msg(state, msg.header.stamp))

    def _publish_diagnostics(self):
        msg = DiagnosticArray(status=[estimator_status(self._stepper)])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)


def estimator_status(stepper: FrameStepper) -> DiagnosticStatus:
    """Cost per step and the mean NIS over the records since the last call, which it clears,
    the fault count and the last fault."""
    est = stepper.estimator
    status = DiagnosticStatus(name='estimator', hardware_id='drift_control',
                              level=DiagnosticStatus.OK)
    status.message = 'running' if stepper.state is not None else 'no state yet'
    times = np.asarray(getattr(est, 'step_times', ()), float) * 1e3
    if times.size:
        status.values.append(KeyValue(key='step_ms_p50', value=f'{np.median(times):.3f}'))
        status.values.append(KeyValue(key='step_ms_max', value=f'{times.max():.3f}'))
    for name, nis in (est.nis_summary(intervals=False) if hasattr(est, 'nis_summary')
                      else {}).items():
        status.values.append(KeyValue(key=f'nis_mean {name}', value=f'{nis["mean"]:.2f}'))
    events = getattr(est, 'events', ())
    if events:
        status.level = DiagnosticStatus.WARN
        status.values.append(KeyValue(key='faults', value=str(len(events))))
        status.message = f'last fault: {events[-1].channel} {events[-1].reason}'
    if hasattr(est, 'clear_records'):
        est.clear_records()
    return status


class StepperLog:
    """Logs the estimator's new fault events and each time it started over, once each."""

    def __init__(self, logger):
        self.logger, self.events, self.restarts = logger, 0, 0

    def __call__(self, stepper: FrameStepper, epoch: int) -> None:
        events = getattr(stepper.estimator, 'events', ())
        for e in events[self.events:]:
            self.logger.warning(f'sensor fault: {e.channel} {e.reason} (t = {e.t + epoch:.3f} s)')
        self.events = len(events)
        if stepper.restarts != self.restarts:
            self.restarts = stepper.restarts
            self.events = 0   # a new estimator: its own events
            self.logger.warning('estimator started over: '
                                + (stepper.failure or 'the clock stepped back'))


def main(args=None) -> int:
    return run_node(EstimatorNode, 'estimator', args)


if __name__ == '__main__':
    sys.exit(main())
