"""Sim node: the plant as a car -- vehicle/state out every 10 ms, drift/command in (or CAN)."""
import json
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from drift_msgs.msg import DriftCommand, DriftReference, SensorSamples, VehicleState
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header, String

from drift_control.nodes import convert
from drift_control.nodes.qos import kept_qos
from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import raise_real_time
from drift_control.nodes.spin import run_node
from drift_control.pacing import Pacer
from drift_control.params import ParamError, config_dir, parse_overrides
from drift_sim.lockstep import LockstepGate
from drift_sim.scenario import load_scenario
from drift_sim.simulator import Simulator


STATE_REPEAT = 0.2   # lock-step: offer the first state again this often until a command [s]


class SimNode(Node):
    """Steps the simulator in real time, or in lock-step with the controller on sim time.

    ``io:=link`` puts the plant behind the car's end of the bridge's link instead (CAN, CAN FD
    or PDUs over UDP, as ``link_set`` makes of config/bridge.yaml: the bridge in the loop, real
    time): only the ground truth goes to ROS.
    """

    def __init__(self):
        super().__init__('sim')
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', 'steady_dry').value
        vehicle = self.declare_parameter('vehicle', '').value      # '' = the scenario's
        seed = self.declare_parameter('seed', -1).value
        self._mode = self.declare_parameter('clock_mode', 'realtime').value
        overrides = [o for o in self.declare_parameter('set', ['']).value if o]
        duration = self.declare_parameter('duration', 0.0).value   # sim time [s]; 0: scenario's
        period = self.declare_parameter('command_period', 0.02).value
        timeout = self.declare_parameter('lockstep_timeout', 1.0).value
        startup = self.declare_parameter('startup_timeout', 120.0).value
        # the run fails when the controller stops: this many lock-step waits in a row, or in
        # real time this long without a command [s]
        self._max_missed = self.declare_parameter('max_missed_commands', 3).value
        self._command_timeout = self.declare_parameter('command_timeout', 1.0).value
        self._startup = startup
        wait_reference = self.declare_parameter('wait_reference', True).value
        # lock-step: the first step waits until the ground truth has a subscriber (the recorder
        # of a run_stack --bag run, which discovers topics by polling and may join late)
        self._wait_recorder = self.declare_parameter('wait_recorder', False).value
        # ... and until every node of the launch is seen: a publisher not yet discovered here
        # would count as none when the recorder's matches are compared (its samples lost)
        self._wait_nodes = [n for n in self.declare_parameter('wait_nodes', ['']).value if n]
        io = self.declare_parameter('io', 'ros').value
        # the bridge.yaml overrides naming the link, the same ones the bridge node gets
        link_set = [o for o in self.declare_parameter('link_set', ['']).value if o]
        can_hold = self.declare_parameter('can_hold_until_engaged', False).value
        # the car's sensor units (config/sim/sensors/<name>.yaml) on vehicle/sensors for the
        # estimator, instead of the plant's measured state on vehicle/state (io link: in the
        # frames, for the bridge's sensor mode); '': the measured state
        sensors = self.declare_parameter('sensors', '').value
        sensor_set = [o for o in self.declare_parameter('sensor_set', ['']).value if o]
        sensor_faults = [o for o in self.declare_parameter('sensor_faults', ['']).value if o]
        for name, value in (('duration', duration), ('command_period', period),
                            ('lockstep_timeout', timeout), ('startup_timeout', startup),
                            ('command_timeout', self._command_timeout)):
            if not 0.0 <= value < float('inf') or (value == 0.0 and name != 'duration'):
                raise ParamError(f'sim: {name} must be a time > 0 s'
                                 + (' (0: the scenario\'s)' if name == 'duration' else '')
                                 + f', got {value!r}')
        if self._mode not in ('realtime', 'lockstep'):
            raise ParamError(f"sim: clock_mode must be 'realtime' or 'lockstep', "
                             f'got {self._mode!r}')
        if duration > 0.0:
            overrides.append(f'duration={duration!r}')
        loaded = load_scenario(scenario, overrides, cfg, seed=None if seed < 0 else seed,
                               vehicle=vehicle or None)
        self._sim = Simulator(loaded)
        self._sensors = self._frame = None
        if sensors:
            from drift_sim.sensors import Sensors, load_sensor_params, parse_fault
            self._sensors = Sensors(load_sensor_params(sensors, cfg, sensor_set), self._sim.dt,
                                    self._sim.plant.seed, [parse_fault(f) for f in sensor_faults])
            self._frame = self._sensors.reset(self._sim.truth.state)
        elif sensor_set or sensor_faults:
            raise ParamError('sim: sensor_set and sensor_faults need sensors')
        self._gate = LockstepGate(self._sim.dt, period, timeout, startup, wait_reference)
        self._command = None
        self._command_wall = self._started = time.monotonic()
        self._pacer = Pacer(self._sim.dt)    # real time: every 10 ms step runs, late or not
        self._offered = time.monotonic()
        self._reported = 0
        self._can = None
        self.finished = Future()   # done when the scenario's time is up: the run ends there
        if io == 'link':
            from drift_sim.can_vehicle import CanVehicle
            from drift_vehicle_bridge.params import load_bridge_params
            from drift_vehicle_bridge.vehicle_side import CarSide
            self._mode = 'realtime'
            link = load_bridge_params(cfg, parse_overrides(link_set, 'sim.link_set'),
                                      loaded.scenario.vehicle)
            self._can = CanVehicle(self._sim, CarSide.open(link, cfg), can_hold, self._sensors)
            self._link_name = link.link()
            self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
            self.create_timer(1.0, self._on_link_diag)
        elif io != 'ros':
            raise ParamError(f"sim: io must be 'ros' or 'link', got {io!r}")
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        kept = kept_qos()   # a recorder matched late still gets the first messages
        self._state_pub = self._sensor_pub = None   # on a link the bridge publishes them
        if self._can is None and self._sensors is None:
            self._state_pub = self.create_publisher(VehicleState, 'vehicle/state', kept)
        elif self._can is None:   # the estimator publishes the state
            self._sensor_pub = self.create_publisher(SensorSamples, 'vehicle/sensors', kept)
        self._truth_pub = self.create_publisher(VehicleState, 'sim/state', kept)
        self._clock_pub = self.create_publisher(Clock, '/clock', kept)
        self._inputs = [
            self.create_subscription(DriftCommand, 'drift/command', self._on_command, reliable),
            self.create_subscription(DriftReference, 'drift/reference', lambda m: self._gate.
                                     offer_reference(convert.time_from_msg(m.header.stamp)), 10)]
        # t = 0 waits for the recorder (lock-step and real time alike: a writer matched late
        # keeps only 1 s for it); a car on a link sends nothing before
        self._recorder_matched = None    # topic -> publishers the recorder is matched with
        if self._wait_recorder:   # t = 0 goes out once the recorder hears every publisher
            self.create_subscription(String, '/recorder/matched', self._on_recorder_matched,
                                     QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
        elif self._can is None:
            self._publish(self._sim.state)
        tick = self._sim.dt if self._mode == 'realtime' else 0.005
        self.create_timer(tick, self._on_tick)
        if self._can is not None or (self._sensors is not None and self._mode == 'realtime'):
            raise_real_time()   # it stands in for a car: its 10 ms cycle must not wait
        lock_parameters(self)   # every parameter is read once, at start
        self.get_logger().info(f'scenario {loaded.scenario.name} ({self._mode}), vehicle '
                               f'{loaded.scenario.vehicle}, seed '
                               f'{self._sim.plant.seed}, plant JIT {self._sim.plant.model.jit}')

    def close(self) -> None:
        """Release the link of the ``io: link`` mode."""
        if self._can is not None:
            self._can.car.transport.shutdown()

    def _on_link_diag(self):
        """The car's end of the link: which requests it accepted, their rates and E2E states."""
        from drift_vehicle_bridge.nodes.convert import car_side_status
        status = car_side_status(self._can.car.stats(), self._can.released,
                                 self._can.cycle.take(), self._link_name)
        self._diag_pub.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now()
                                                             .to_msg()), status=[status]))

    def _on_recorder_matched(self, msg):
        try:
            matched = json.loads(msg.data)
        except ValueError:
            return
        if isinstance(matched, dict):
            self._recorder_matched = matched

    def _recorder_ready(self) -> bool:
        """The controller is up (our inputs have publishers), the recorder is matched with
        every publisher the graph has of every topic it records, and our publishers with every
        subscriber the graph has of theirs: nothing of the run is lost, and t = 0 reaches the
        recorder when it is published, not later from the kept history (its log time would be
        late: a topic's rate in the bag read 101 Hz)."""
        if self._recorder_matched is None or \
                any(sub.get_publisher_count() == 0 for sub in self._inputs):
            return False
        if self._unmatched() or self._unseen():
            return False
        return all(self.count_publishers(topic) <= n
                   for topic, n in self._recorder_matched.items())

    def _unseen(self) -> list[str]:
        """The launch's nodes not discovered yet."""
        seen = set(self.get_node_names())
        return [n for n in self._wait_nodes if n not in seen]

    def _unmatched(self) -> list[str]:
        """Our topics with a subscriber in the graph that our publisher has not matched yet."""
        ours = (self._state_pub, self._sensor_pub, self._truth_pub, self._clock_pub)
        return [pub.topic_name for pub in ours if pub is not None
                and pub.get_subscription_count() < self.count_subscribers(pub.topic_name)]

    def _on_command(self, msg):
        command = convert.decode(convert.command_from_msg, msg, self.get_logger())
        if command is None:
            return
        self._command, self._command_wall = command, time.monotonic()
        self._gate.offer(command)
        if self._mode == 'lockstep':
            self._on_tick()     # step on at once: no timer latency in the loop

    def _on_tick(self):
        if self.finished.done():
            return
        if self._sim.done:
            if self._command is None and self._can is None:
                return self._fail('the controller never commanded in the whole run')
            if self._mode == 'lockstep' and not self._gate.ready(self._sim.t, time.monotonic()):
                return   # the answer to the last state too: every run's bag ends alike
            self.get_logger().info(f'scenario finished at t = {self._sim.t:.2f} s')
            self._end(True)
            return
        if self._wait_recorder:   # nothing of the run may go unrecorded
            if not self._recorder_ready():
                if time.monotonic() - self._started > self._startup:
                    return self._fail(f'the recorder and the graph did not match within '
                                      f'startup_timeout {self._startup:g} s (the recorder '
                                      f'reports {self._recorder_matched}; ours unmatched: '
                                      f'{self._unmatched()}; nodes not seen: '
                                      f'{self._unseen()})')
                return
            self._wait_recorder = False
            if self._can is not None:
                self._can.car.discard_backlog()
            if self._can is None:
                self._offered = self._started = time.monotonic()   # the controller's start-up
                self._publish(self._sim.state)   # t = 0 for the bag: state, truth and clock
        if self._mode == 'lockstep':
            if self._command is None and time.monotonic() - self._offered > STATE_REPEAT:
                # a node that joins late (the NMPC compiling its solver on first use) must still
                # see the first state: offer it again until the first command (state only; the
                # recorded truth and clock stay one message per step)
                self._offered = time.monotonic()
                self._publish_measured(self._sim.state, self._sim.t)
            # as many steps as the gate allows (up to the next command), then back to spin
            for _ in range(self._gate.every):
                if self._sim.done or not self._gate.ready(self._sim.t, time.monotonic()):
                    return
                if self._gate.timeouts != self._reported:
                    self._reported = self._gate.timeouts
                    if self._command is None:
                        return self._fail(f'the controller never commanded (startup_timeout '
                                          f'{self._startup:g} s)')
                    if self._gate.missed_in_row >= self._max_missed:
                        return self._fail(f'the controller stopped commanding: no command for '
                                          f'{self._gate.missed_in_row} lock-step steps in a row '
                                          f'at t = {self._sim.t:.2f} s')
                    self.get_logger().warning(f'lockstep: no command for t={self._sim.t:.2f} s '
                                              f'({self._gate.timeouts} timeouts); stepping on',
                                              throttle_duration_sec=2.0)
                self._publish(self._step())
            return
        if self._can is None:   # on CAN the bridge's heartbeat judges the commands
            wall = time.monotonic()
            if self._command is None and wall - self._started > self._startup:
                return self._fail(f'the controller never commanded (startup_timeout '
                                  f'{self._startup:g} s)')
            if self._command is not None and wall - self._command_wall > self._command_timeout:
                return self._fail(f'the controller stopped commanding: none for '
                                  f'{wall - self._command_wall:.1f} s at t = {self._sim.t:.2f} s')
        skipped = self._pacer.skipped
        n, now = self._pacer.due(time.monotonic()), self.get_clock().now()
        for i in range(n):   # a late tick runs the steps it missed, each with its own time
            if self._sim.done:
                break
            stamp = now - Duration(seconds=(n - 1 - i) * self._sim.dt)
            if self._can is not None:
                self._can.step(time.monotonic())
                self._truth_pub.publish(convert.state_to_msg(self._sim.truth.state, stamp))
            else:
                self._publish(self._step(), stamp)
        if self._pacer.skipped != skipped:
            self.get_logger().warning(f'real time: stalled, {self._pacer.skipped} steps of '
                                      f'{1e3 * self._sim.dt:g} ms dropped so far',
                                      throttle_duration_sec=2.0)

    def _fail(self, reason: str) -> None:
        """End the run with an error: a run whose controller is silent must not pass."""
        if not self.finished.done():
            self.get_logger().error(f'ending the run: {reason}')
            self._end(False)

    def _end(self, ok: bool) -> None:
        """End the run once the recorder has acknowledged the last states (reliable QoS)."""
        for pub in (self._state_pub, self._sensor_pub, self._truth_pub, self._clock_pub):
            if pub is not None:
                pub.wait_for_all_acked(Duration(seconds=1.0))
        self.finished.set_result(ok)

    def _step(self):
        """One plant step under the newest command; the sensor samples that arrive with it."""
        state = self._sim.step(self._command)
        if self._sensors is not None:
            self._frame = self._sensors.step(self._sim.truth.state)
        return state

    def _publish(self, state, stamp=None):
        """The measured and true state; lock-step: stamped in sim time, with /clock."""
        if self._mode == 'lockstep':
            stamp = self._sim.t
            self._clock_pub.publish(Clock(clock=convert.time_to_msg(stamp)))
        elif stamp is None:
            stamp = self.get_clock().now()
        self._publish_measured(state, stamp)
        self._truth_pub.publish(convert.state_to_msg(self._sim.truth.state, stamp))

    def _publish_measured(self, state, stamp):
        """The plant's measured state, or the sensor samples of this step (``sensors``)."""
        if self._sensors is None:
            self._state_pub.publish(convert.state_to_msg(state, stamp))
        else:
            self._sensor_pub.publish(convert.sensor_samples_to_msg(self._frame, stamp,
                                                                   self._sim.t))


def main(args=None) -> int:
    return run_node(SimNode, 'sim', args)


if __name__ == '__main__':
    sys.exit(main())
