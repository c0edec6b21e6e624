"""Reference node: vehicle/state -> ReferenceSelector -> drift/reference at a fixed rate.

``trigger: timer`` selects on a timer for the newest state; ``trigger: state`` selects for the
first state at or after each period of state time, as it arrives (deterministic in lock-step:
the reference always belongs to the state the NMPC solves on).
"""
import os
import sys
from dataclasses import replace

from drift_msgs.msg import DriftReference, VehicleState
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from drift_control.nodes import convert
from drift_control.nodes.spin import run_node
from drift_control.params import ParamError, config_dir, load_yaml
from drift_control.path import load_scenario_path
from drift_control.ocp import load_nmpc_params
from drift_control.reference import (ReferenceSelector, check_horizon_spacing,
                                     load_reference_params)


def load_map(cfg: str, map_file: str):
    """The EquilibriumMap of ``map_file``, relative to the checkout root; never a made-up map."""
    if not map_file:
        raise ParamError('no map_file parameter (nor map_file in the scenario): no equilibria')
    map_file = os.path.join(os.path.dirname(os.path.abspath(cfg)), map_file)
    try:
        from drift_control.eqmap import load_map as load
    except ImportError as err:
        raise ParamError(f'drift_control.eqmap is not available ({err}): no equilibrium map')
    try:
        return load(map_file)
    except (OSError, ValueError) as err:   # eqmap.MapError is a ValueError
        raise ParamError(f'equilibrium map {map_file}: {err}') from None


class ReferenceNode(Node):
    """Publishes the equilibrium reference for the latest vehicle state, and the path."""

    def __init__(self):
        super().__init__('reference')
        cfg = self.declare_parameter('config_dir', str(config_dir())).value
        scenario = self.declare_parameter('scenario', '').value
        path_file = self.declare_parameter('path_file', '').value
        map_file = self.declare_parameter('map_file', '').value
        trigger = self.declare_parameter('trigger', 'timer').value
        if trigger not in ('timer', 'state'):
            raise ParamError(f"reference node: trigger {trigger!r} not in ['timer', 'state']")
        params = load_reference_params(os.path.join(cfg, 'reference.yaml'))
        check_horizon_spacing(params, load_nmpc_params(os.path.join(cfg, 'nmpc.yaml')).dt)
        scen = load_yaml(os.path.join(cfg, 'scenarios', f'{scenario}.yaml')) if scenario else {}
        path = load_scenario_path(cfg, scenario, path_file)
        eqmap = load_map(cfg, map_file or scen.get('map_file', ''))
        params = replace(params, radius_min=max(params.radius_min, float(eqmap.radius[0])),
                         radius_max=min(params.radius_max, float(eqmap.radius[-1])))
        self._selector = ReferenceSelector(eqmap.lookup, path, params)
        self._selector.reset(s_hint=(scen.get('initial') or {}).get('s'))  # where paths overlap
        self._state, self._fresh = None, False
        self._period, self._due = params.period, None   # trigger: state
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._ref_pub = self.create_publisher(DriftReference, 'drift/reference', 10)
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
        self.get_logger().info(f'path {path.name}: {path.length:.1f} m; radii {params.radius_min:g}'
                               f'..{params.radius_max:g} m')

    def _on_state(self, msg):
        self._state, self._fresh = convert.state_from_msg(msg), True

    def _on_state_event(self, msg):
        self._on_state(msg)
        stamp = self._state.stamp
        if self._due is None or stamp >= self._due - 1e-3:
            self._due = stamp + self._period
            self._on_tick()

    def _on_tick(self):
        if not self._fresh:   # publish only for new states: a stale state must look stale
            return
        self._fresh = False
        ref = self._selector.select(self._state)
        if ref is not None:
            self._ref_pub.publish(convert.reference_to_msg(ref))


def main(args=None) -> int:
    return run_node(ReferenceNode, 'reference', args)


if __name__ == '__main__':
    sys.exit(main())
