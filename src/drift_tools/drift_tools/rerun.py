"""Re-running the NMPC core on a recorded drive: recorded vs recomputed commands.

For each recorded command, the NMPC is stepped on the newest recorded state and reference at or
before that command's stamp, in recorded order (so its warm start follows the live run), and the
recomputed command is compared with the recorded one. A large difference means the controller,
its parameters or its inputs changed since the recording, or the live solver ran late.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from drift_tools.bag import bag_info, is_finished, read_bag

STATE, REFERENCE, COMMAND = '/vehicle/state', '/drift/reference', '/drift/command'
SENSORS = '/vehicle/sensors'   # recorded: the states are the estimator's (stamped)


@dataclass(frozen=True)
class RerunResult:
    """Recorded vs recomputed commands of one bag."""

    commands: int             # recorded commands compared
    skipped: int              # commands with no state or reference before them
    delta_rms_deg: float      # steering difference [deg]
    delta_max_deg: float
    torque_rms_nm: float      # drive torque difference [Nm]
    torque_max_nm: float
    mode_mismatches: int      # commands whose mode differs
    recomputed_not_ok: int    # recomputed cycles that did not solve (shifted, fallback, no input)

    def summary_lines(self) -> list[str]:
        return [
            f'rerun: {self.commands} commands compared ({self.skipped} without inputs skipped)',
            f'  steering  difference: rms {self.delta_rms_deg:.3f} deg, max {self.delta_max_deg:.3f} deg',
            f'  torque    difference: rms {self.torque_rms_nm:.1f} Nm, max {self.torque_max_nm:.1f} Nm',
            f'  mode mismatches: {self.mode_mismatches}; recomputed cycles not solved: '
            f'{self.recomputed_not_ok}',
        ]

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def rerun_controller(bag_dir: Path, control_mode: str = 'full', surface: str | None = None,
                     config=None, nmpc=None, vehicle: str | None = None,
                     stamped: bool | None = None) -> RerunResult:
    """Step the NMPC on the bag's states and references at its command times.

    Parameters
    ----------
    bag_dir : Path
        Recorded run with /vehicle/state, /drift/reference and /drift/command.
    control_mode : {'full', 'torque_only'}
    surface : str, optional
        Surface whose friction the NMPC assumes (default: the scenario's, else 'dry').
    config : Path, optional
        Config directory (default: the checkout's).
    vehicle : str, optional
        The car the run drove (default: ``config/defaults.yaml``'s).
    nmpc : drift_control.nmpc.Nmpc, optional
        A ready controller (tests); built from the config otherwise.
    stamped : bool, optional
        The recorded states are what their stamps say (an estimator's: ``nmpc.state_age`` is
        not applied to them). Default: when the bag holds the raw sensor samples.
    """
    # the message converter lives with the nodes; bags decode to objects with the same fields
    from drift_control.nodes import convert
    from drift_control.signals import Mode

    messages = read_bag(bag_dir, topics=[STATE, REFERENCE, COMMAND])
    missing = [t for t in (STATE, REFERENCE, COMMAND) if not messages.get(t)]
    if missing:
        raise ValueError(f'{bag_dir}: nothing recorded on {missing}: cannot re-run the controller')
    if nmpc is None:
        stamped = _has_sensors(bag_dir) if stamped is None else stamped
        nmpc = _build_nmpc(control_mode, surface, config, vehicle, stamped)
    states = sorted((_stamp(m.msg), m.msg) for m in messages[STATE])
    refs = sorted((_stamp(m.msg), m.msg) for m in messages[REFERENCE])
    state_t = np.array([t for t, _ in states])
    ref_t = np.array([t for t, _ in refs])
    d_delta, d_torque = [], []
    skipped = mode_mismatches = not_ok = 0
    for m in messages[COMMAND]:
        t = _stamp(m.msg)
        i = int(np.searchsorted(state_t, t, side='right')) - 1
        j = int(np.searchsorted(ref_t, t, side='right')) - 1
        if i < 0 or j < 0:
            skipped += 1
            continue
        recorded = convert.command_from_msg(m.msg)
        result = nmpc.step(convert.state_from_msg(states[i][1]),
                           convert.reference_from_msg(refs[j][1]), t)
        not_ok += int(result.status != 0)
        mode_mismatches += int(Mode(result.command.mode) != Mode(recorded.mode))
        d_delta.append(result.command.delta - recorded.delta)
        d_torque.append(result.command.drive_torque - recorded.drive_torque)
    d_delta, d_torque = np.degrees(np.array(d_delta)), np.array(d_torque)

    def rms(v):
        return float(np.sqrt(np.mean(v ** 2))) if v.size else math.nan

    def peak(v):
        return float(np.max(np.abs(v))) if v.size else math.nan

    return RerunResult(len(d_delta), skipped, rms(d_delta), peak(d_delta), rms(d_torque),
                       peak(d_torque), mode_mismatches, not_ok)


def _has_sensors(bag_dir: Path) -> bool:
    """Whether the bag holds sensor samples: its ``metadata.yaml`` says, else (a salvaged bag)
    its messages on that topic."""
    if is_finished(bag_dir):
        try:
            topic = bag_info(bag_dir).topics.get(SENSORS)
            return topic is not None and topic.count > 0
        except (OSError, ValueError):   # no readable metadata: the messages tell
            pass
    return bool(read_bag(bag_dir, topics=[SENSORS]).get(SENSORS))


def _build_nmpc(control_mode: str, surface: str | None, config, vehicle: str | None,
                stamped: bool):
    from drift_control.assembly import MODES, load_setup
    if control_mode not in MODES:
        raise ValueError(f'control_mode must be one of {list(MODES)}, got {control_mode!r}')
    setup = load_setup(config, vehicle=vehicle, surface=surface or 'dry', with_map=False)
    return setup.build_nmpc(MODES[control_mode], stamped=stamped)
