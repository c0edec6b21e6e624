"""drift_msgs / diagnostic_msgs <-> the bridge's core types; the only module importing both."""
from __future__ import annotations

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from drift_msgs.msg import DriftCommand, VehicleState as VehicleStateMsg
from std_msgs.msg import Header

from drift_control.signals import Command, Mode, Validity, VehicleState
from drift_vehicle_bridge.mode import REQUIRED


def stamp_to_sec(stamp: Time) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def state_to_msg(state: VehicleState, stamp: Time, frame_id: str = 'base_link') -> VehicleStateMsg:
    """A VehicleState message stamped with ``stamp`` (the node's clock)."""
    msg = VehicleStateMsg()
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    msg.v, msg.beta, msg.r = state.V, state.beta, state.r
    msg.vx, msg.vy, msg.ax, msg.ay = state.vx, state.vy, state.ax, state.ay
    msg.wheel_speeds = [float(w) for w in state.wheel_speeds]
    msg.delta, msg.steering_torque = state.delta, state.steering_torque
    msg.drive_torque, msg.brake_pedal = state.drive_torque, bool(state.brake_pedal)
    msg.x, msg.y, msg.yaw = state.x, state.y, state.yaw
    msg.validity = int(state.validity)
    return msg


def command_from_msg(msg: DriftCommand) -> Command:
    """The core Command of a DriftCommand (an unknown mode reads as OFF)."""
    mode = Mode(msg.mode) if msg.mode in Mode._value2member_map_ else Mode.OFF
    return Command(stamp_to_sec(msg.header.stamp), msg.delta, msg.delta_rate, msg.drive_torque,
                   mode)


def stats_to_diagnostics(stats: dict, previous: dict | None, period: float, stamp: Time,
                         hardware_id: str) -> DiagnosticArray:
    """One DiagnosticStatus: mode, frame rates [Hz] over ``period`` [s], fault and tx counts."""
    status = DiagnosticStatus(name='vehicle_bridge: CAN', hardware_id=hardware_id)
    validity = int(stats['validity'])
    if (validity & int(REQUIRED)) != int(REQUIRED):
        status.level, status.message = DiagnosticStatus.ERROR, 'vehicle state missing or stale'
    elif validity != int(Validity.ALL) or stats['faults']:
        status.level, status.message = DiagnosticStatus.WARN, 'partial state or frame faults'
    else:
        status.level, status.message = DiagnosticStatus.OK, 'ok'
    status.message += f"; mode {stats['mode']}"
    if stats.get('implausible'):
        status.level = DiagnosticStatus.ERROR
        status.message = f"implausible vehicle state: {stats['implausible']}"
    values = {'mode': stats['mode'], 'drop_reason': stats['drop_reason'],
              'validity': f'0x{validity:03x}', 'foreign_frames': stats['foreign'],
              'discarded_at_start': stats.get('discarded_at_start', 0)}
    before = previous['rx'] if previous else {}
    for name, count in stats['rx'].items():
        values[f'rx_hz/{name}'] = f'{(count - before.get(name, 0)) / period:.1f}'
    values.update({f'rx_fault/{k}': v for k, v in stats['faults'].items()})
    values.update({f'e2e/{k}': v for k, v in stats.get('e2e', {}).items()})
    values.update({f'rx_rate/{k}': f'{v:.1f}' for k, v in stats.get('rx_rate', {}).items()})
    values.update({f'rx/{k}': v for k, v in stats['rx'].items()})
    values.update({f'rx_stamp/{k}': f'{v:.6f}' for k, v in stats.get('rx_stamp', {}).items()})
    values.update({f'drops/{k}': v for k, v in stats.get('drops', {}).items()})
    values.update({f'tx/{k}': v for k, v in stats['tx'].items()})
    values.update({f'error/{k}': v for k, v in stats['errors'].items()})
    values.update({f'sensor_samples/{k}': v for k, v in stats.get('sensor_samples', {}).items()})
    status.values = key_values(values)
    return DiagnosticArray(header=Header(stamp=stamp), status=[status])


def car_side_status(stats: dict, released: int, step_gap: dict[str, float],
                    hardware_id: str) -> DiagnosticStatus:
    """The simulated car's end of the link (``CarSide.stats``): what it accepted of the requests,
    and its longest gap between two steps since the last status (``CycleWatch.take``)."""
    faulty = stats['faults'] or stats['errors']
    status = DiagnosticStatus(name='car side', hardware_id=hardware_id,
                              level=DiagnosticStatus.WARN if faulty else DiagnosticStatus.OK,
                              message='request faults' if faulty else 'ok')
    values = {'sent': stats['sent'], 'released_steps': released, 'foreign': stats['foreign']}
    values.update(gap_values('step_gap', step_gap))
    values.update({f'rx/{k}': v for k, v in stats['rx'].items()})
    values.update({f'rx_rate/{k}': f'{v:.1f}' for k, v in stats['rx_rate'].items()})
    values.update({f'rx_stamp/{k}': f'{v:.6f}' for k, v in stats['rx_stamp'].items()})
    values.update({f'rx_fault/{k}': v for k, v in stats['faults'].items()})
    values.update({f'e2e/{k}': v for k, v in stats['e2e'].items()})
    values.update({f'error/{k}': v for k, v in stats['errors'].items()})
    values.update({f'sensor_samples/{k}': v for k, v in stats.get('sensor_samples', {}).items()})
    status.values = key_values(values)
    return status


def gap_values(name: str, gap: dict[str, float]) -> dict[str, str]:
    """A cycle's longest gap and its parts (``CycleWatch.take``) as diagnostic values [ms]:
    ``<name>_max_ms`` and ``<name>_ran_ms``, ``_waited_ms``, ``_stolen_ms``."""
    out = {f'{name}_max_ms': f"{1e3 * gap['gap']:.1f}"}
    out.update({f'{name}_{part}_ms': f'{1e3 * gap[part]:.1f}'
                for part in ('ran', 'waited', 'stolen')})
    return out


def key_values(values: dict) -> list[KeyValue]:
    """Diagnostic key-value pairs, the values as strings."""
    return [KeyValue(key=k, value=str(v)) for k, v in values.items()]


def peer_status(name: str, level: int, message: str) -> DiagnosticStatus:
    """One DiagnosticStatus about another node (the recorder as the bridge sees it)."""
    return DiagnosticStatus(name=name, level=bytes([level]), message=message)


def level_of(status: DiagnosticStatus) -> int:
    """A status's level as an int (rclpy gives the ``byte`` field as ``bytes``)."""
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)
