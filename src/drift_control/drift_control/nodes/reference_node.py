"""Reference node: vehicle/state -> ReferenceSelector -> drift/reference at a fixed rate.

``trigger: timer`` selects on a timer for the newest state; ``trigger: state`` selects for the
first state at or after each period of state time, as it arrives (deterministic in lock-step:
the reference always belongs to the state the NMPC solves on).
"""
import sys

from drift_msgs.msg import DriftReference, VehicleState
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from drift_control.assembly import load_setup
from drift_control.nodes import convert
from drift_control.nodes.qos import kept_qos
from drift_control.nodes.runtime_params import lock_parameters
from drift_control.nodes.priority import raise_real_time
from drift_control.nodes.spin import run_node
from drift_control.pacing import PeriodGate
from drift_control.params import ParamError, config_dir


class ReferenceNode(Node):
    """Publishes the equilibrium reference for the latest vehicle state, and the path."""

    def __init__(self):
        super().__init__('reference')
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        vehicle = self.declare_parameter('vehicle', '').value      # '' = the scenario's
        overrides = [o for o in self.declare_parameter('set', ['']).value if o]
        path_file = self.declare_parameter('path_file', '').value
        trigger = self.declare_parameter('trigger', 'timer').value
        if trigger not in ('timer', 'state'):
            raise ParamError(f"reference node: trigger {trigger!r} not in ['timer', 'state']")
        if not scenario and not path_file:
            raise ParamError('reference node: give a scenario (with a path) or a path_file')
        setup = load_setup(cfg, scenario, vehicle or None, overrides, path_file=path_file)
        params, path = setup.reference, setup.path
        self._selector = setup.build_selector()
        self._state, self._fresh = None, False
        self._gate = PeriodGate(params.period)   # trigger: state
        self._last_ref = None
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._ref_pub = self.create_publisher(DriftReference, 'drift/reference', kept_qos())
        self.create_publisher(PathMsg, 'drift/path', latched).publish(
            convert.path_to_msg(path, self.get_clock().now()))
        if trigger == 'state':   # every state counts: a deeper queue, and no timer
            self.create_subscription(VehicleState, 'vehicle/state', self._on_state_event,
                                     QoSProfile(depth=20,
                                                reliability=ReliabilityPolicy.BEST_EFFORT))
        else:
            self.create_subscription(VehicleState, 'vehicle/state', self._on_state,
                                     qos_profile_sensor_data)
            self.create_timer(params.period, self._on_tick)
        raise_real_time(by=0)   # after start-up: at the launch's priority, below the link
        lock_parameters(self)   # every parameter is read once, at start
        self.get_logger().info(f'{setup.vehicle_name} on {setup.surface.name}, path {path.name}: '
                               f'{path.length:.1f} m; radii {params.radius_min:g}'
                               f'..{params.radius_max:g} m')

    def _on_state(self, msg) -> bool:
        state = convert.decode(convert.state_from_msg, msg, self.get_logger())
        if state is not None:
            self._state, self._fresh = state, True
        return state is not None

    def _on_state_event(self, msg):
        if not self._on_state(msg):
            return
        stamp = self._state.stamp
        if self._gate.due(stamp, self.get_clock().now().nanoseconds * 1e-9):
            self._gate.fired(stamp)
            self._on_tick()
        elif stamp == self._gate.last and self._last_ref is not None:
            self._ref_pub.publish(self._last_ref)   # offered again: for a node that joined late

    def _on_tick(self):
        if not self._fresh:   # publish only for new states: a stale state must look stale
            return
        self._fresh = False
        ref = self._selector.select(self._state)
        if ref is not None:
            self._last_ref = convert.reference_to_msg(ref)
            self._ref_pub.publish(self._last_ref)


def main(args=None) -> int:
    return run_node(ReferenceNode, 'reference', args)


if __name__ == '__main__':
    sys.exit(main())
