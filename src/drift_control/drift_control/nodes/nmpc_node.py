"""NMPC node: vehicle/state + drift/reference -> Nmpc.step -> drift/command, status, diagnostics.

``state_source: sensors``: the estimator and the reference selector run in this process as
library stages, on vehicle/sensors: one DDS hop from the sensor samples to the command instead
of three (docs/estimator.md has the measurements). The estimator runs before the NMPC, the
selector after the command (the next cycle's reference, on the state the NMPC predicts for it);
the estimated state and the reference are published after the command, for the recorder and the
view.
"""
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from drift_msgs.msg import DriftCommand, DriftReference, NmpcStatus, SensorSamples, VehicleState
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.time import Time

from drift_control.assembly import MODES, load_setup
from drift_control.estimator import FrameStepper, build_estimator
from drift_control.nmpc import LockstepTrigger
from drift_control.nmpc import NmpcStatus as Status
from drift_control.nodes import convert
from drift_control.nodes.qos import kept_qos
from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import raise_real_time
from drift_control.nodes.estimator_node import StepperLog, estimator_status
from drift_control.nodes.spin import run_node
from drift_control.pacing import PeriodGate
from drift_control.params import ParamError, config_dir
REALTIME_REFERENCE_WAIT = 0.005   # trigger: state, wall time [s]
LOCKSTEP_REFERENCE_WAIT = 1.0
LEVEL = {Status.OK: DiagnosticStatus.OK, Status.SHIFTED: DiagnosticStatus.WARN,
         Status.NO_INPUT: DiagnosticStatus.WARN, Status.FALLBACK: DiagnosticStatus.ERROR}


class NmpcNode(Node):
    """Runs the NMPC every period (``trigger: timer``) or on each new state (``trigger: state``)."""

    def __init__(self):
        super().__init__('nmpc')
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        vehicle = self.declare_parameter('vehicle', '').value      # '' = the scenario's
        overrides = [o for o in self.declare_parameter('set', ['']).value if o]
        mode = self.declare_parameter('control_mode', '').value   # '' = the scenario's, else full
        trigger = self.declare_parameter('trigger', 'timer').value
        source = self.declare_parameter('state_source', 'topics').value
        kind = self.declare_parameter('estimator', 'ekf').value
        estimator_set = [o for o in self.declare_parameter('estimator_set', ['']).value if o]
        if mode not in ('', *MODES) or trigger not in ('timer', 'state') \
                or source not in ('topics', 'sensors'):
            raise ParamError(f'nmpc node: control_mode {mode!r} not in {list(MODES)}, trigger '
                             f"{trigger!r} not in ['timer', 'state'] or state_source {source!r} "
                             "not in ['topics', 'sensors']")
        setup = load_setup(cfg, scenario, vehicle or None, overrides,
                           with_map=source == 'sensors')
        params, surface = setup.nmpc, setup.surface
        mode = mode or (setup.scenario.control_mode if setup.scenario else 'full')
        # states an estimator made are what their stamps say: no state_age to predict on
        stamped = self.declare_parameter('stamped_states', False).value or source == 'sensors'
        self._nmpc = setup.build_nmpc(MODES[mode], stamped=bool(stamped))
        self._state = self._ref = self._last = None
        self._cmd_pub = self.create_publisher(DriftCommand, 'drift/command', kept_qos())
        self._status_pub = self.create_publisher(NmpcStatus, 'drift/nmpc/status', kept_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self._stepper = None
        if source == 'sensors':
            self._in_process(setup, build_estimator(kind, setup.vehicle,
                                                    setup.config / 'estimator.yaml',
                                                    estimator_set, intervals=False))
            trigger = 'sensors'
        # under sim time the simulator waits for us: wait for the reference of this very state
        # (deterministic); in real time at most a few ms, so a late reference never stalls us
        sim_time = self._sim_time = self.get_parameter('use_sim_time').value
        wait = LOCKSTEP_REFERENCE_WAIT if sim_time else REALTIME_REFERENCE_WAIT
        self._trigger = LockstepTrigger(params.Ts, wait, first_reference=sim_time) \
            if trigger == 'state' else None
        # best effort matches every publisher; the deeper queue keeps each state of a step
        state_qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.BEST_EFFORT) \
            if trigger == 'state' else qos_profile_sensor_data
        if trigger != 'sensors':   # else vehicle/sensors drive it (_on_samples)
            self.create_subscription(VehicleState, 'vehicle/state', self._on_state, state_qos)
            self.create_subscription(DriftReference, 'drift/reference', self._on_ref, 10)
        if trigger == 'sensors':
            pass
        elif self._trigger is None:
            self.create_timer(params.Ts, self._on_tick)   # node clock: honours use_sim_time
        else:   # wall clock: sim time stands still while the simulator waits for us; started
            # by a state that waits for its reference (a polling timer costs the node ~10 % CPU)
            self._wait = self.create_timer(wait, self._poll,
                                           clock=Clock(clock_type=ClockType.STEADY_TIME))
            self._wait.cancel()
        self.create_timer(1.0, self._publish_diagnostics)
        raise_real_time(by=0)   # after start-up: at the launch's priority, below the link
        lock_parameters(self)   # every parameter is read once, at start
        self.get_logger().info(f'{setup.vehicle_name}, {mode} on {surface.name} '
                               f'(mu {surface.mu:g}), trigger {trigger}, '
                               f'solver {params.solver.method}/{params.solver.qp_solver}')

    def _in_process(self, setup, estimator):
        """Estimator and selector in this process: vehicle/sensors in; the estimated state, the
        reference and the path out, as their own nodes would publish them."""
        self._stepper = FrameStepper(estimator)
        self._selector = setup.build_selector()
        self._gate = PeriodGate(setup.nmpc.Ts)   # once per control period of state time
        self._epoch = None
        self._log = StepperLog(self.get_logger())
        self._answer = None   # the command and reference of the last solved frame
        self._state_pub = self.create_publisher(VehicleState, 'vehicle/state', kept_qos())
        self._ref_pub = self.create_publisher(DriftReference, 'drift/reference', kept_qos())
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_publisher(PathMsg, 'drift/path', latched).publish(
            convert.path_to_msg(setup.path, self.get_clock().now()))
        self.create_subscription(SensorSamples, 'vehicle/sensors', self._on_samples,
                                 QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))

    def _on_samples(self, msg):
        """One frame: the estimator's step; once per period the selector and the NMPC on its
        state, the command out first."""
        if self._epoch is None:
            self._epoch = msg.header.stamp.sec
        frame = convert.decode(lambda m: convert.sensor_samples_from_msg(m, self._epoch), msg,
                               self.get_logger())
        if frame is None:
            return
        t, samples = frame
        repeated = t == self._stepper.last_now
        state = self._stepper.step(samples, t)
        self._log(self._stepper, self._epoch)
        for stamp, torque in self._stepper.estimator.torque_samples:   # the lag's learner's
            self._nmpc.observe_torque(stamp, torque)
        if state is None:
            return
        if repeated:   # offered again (a lock-step start): answer again, for a late joiner
            if self._answer is not None and self._gate.last == t:
                command, ref = self._answer
                if ref is not None:
                    self._ref_pub.publish(ref)
                self._cmd_pub.publish(command)
            return
        now = max(round(self._clock_s() - self._epoch, 9), t)   # to the ns, as the stamps
        if not self._gate.due(t, now):
            self._state_pub.publish(convert.state_to_msg(state, msg.header.stamp))
            return
        self._gate.fired(t)
        self._state = state
        if self._ref is None:   # the first cycle; then the selector runs after the command
            self._ref = self._selector.select(state)
        result = self._nmpc.step(state, self._ref, now)
        stamp = convert.time_to_msg(now + self._epoch) if now > t else msg.header.stamp
        command = convert.command_to_msg(result.command, stamp)
        if not self._sim_time:   # real time: the command out before anything else is built
            self._cmd_pub.publish(command)
        # the next cycle's reference, off the state -> command path: on the state the plan
        # expects then (this state without a plan; the NMPC moves an older one on: Reference.at)
        self._ref = self._selector.select(self._nmpc.next_state(state) or state) or self._ref
        ref = convert.reference_to_msg(self._ref, msg.header.stamp) if self._ref else None
        if ref is not None:
            self._ref_pub.publish(ref)
        if self._sim_time:   # lock-step: the simulator steps once it has both, reference first
            self._cmd_pub.publish(command)
        self._answer = (command, ref)
        self._state_pub.publish(convert.state_to_msg(state, msg.header.stamp))
        self._status_pub.publish(convert.status_to_msg(result, stamp))
        self._last = result
        self._nmpc.prepare()   # the next cycle's linearisation, while no frame waits

    def _on_state(self, msg):
        state = convert.decode(convert.state_from_msg, msg, self.get_logger())
        if state is None:
            return
        self._state = state
        if self._trigger and self._trigger.on_state(state.stamp, time.monotonic(),
                                                    self._clock_s()):
            self._on_tick()
        elif self._trigger and self._trigger.pending and self._wait.is_canceled():
            self._wait.reset()

    def _on_ref(self, msg):
        ref = convert.decode(convert.reference_from_msg, msg, self.get_logger())
        if ref is None:
            return
        self._ref = ref
        if self._trigger and self._trigger.on_reference(ref.stamp):
            self._on_tick()

    def _clock_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _poll(self):
        if self._trigger.poll(time.monotonic()):
            self._on_tick()
        if not self._trigger.pending:
            self._wait.cancel()

    def _on_tick(self):
        now = self.get_clock().now()
        if self._trigger:   # stamp with the state's time: /clock may not be in yet (the trigger
            stamp = self._trigger.fired()   # refuses states further ahead of the clock)
            if stamp > now.nanoseconds * 1e-9:
                now = Time(nanoseconds=int(round(stamp * 1e9)), clock_type=now.clock_type)
            self._wait.cancel()
        result = self._nmpc.step(self._state, self._ref, now.nanoseconds * 1e-9)
        self._cmd_pub.publish(convert.command_to_msg(result.command, now))
        self._status_pub.publish(convert.status_to_msg(result, now))
        self._last = result
        self._nmpc.prepare()   # the next cycle's linearisation, while no state waits

    def _publish_diagnostics(self):
        if self._stepper is not None:
            msg = DiagnosticArray(status=[estimator_status(self._stepper)])
            msg.header.stamp = self.get_clock().now().to_msg()
            self._diag_pub.publish(msg)
        r = self._last
        status = DiagnosticStatus(name='nmpc', hardware_id='drift_control')
        status.level = LEVEL[r.status] if r else DiagnosticStatus.STALE
        status.message = f'{r.status.name}: {r.message}'[:200] if r else 'not run yet'
        if r:
            status.values = [KeyValue(key='solve_time_ms', value=f'{1e3 * r.solve_time_s:.3f}'),
                             KeyValue(key='iterations', value=str(r.iterations)),
                             KeyValue(key='consecutive_failures',
                                      value=str(r.consecutive_failures))]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)


def main(args=None) -> int:
    return run_node(NmpcNode, 'nmpc', args)


if __name__ == '__main__':
    sys.exit(main())
