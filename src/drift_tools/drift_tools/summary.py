"""Summary of a recorded run, read back from its bag: topics, counts, rates, and stack metrics.

:func:`summarize_bag` is the entry point ``make run`` prints; :func:`run_metrics` is where metrics
of the drift itself (sideslip, path error, solver health) are computed from decoded messages --
extend it there, one key per quantity, with the unit in the key name.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drift_tools.bag import BagMessage, bag_info, read_bag


@dataclass(frozen=True)
class TopicStats:
    """Arrival statistics of one topic (receive times)."""

    name: str
    msgtype: str
    count: int
    rate_hz: float     # mean rate over first..last message [Hz]; nan for fewer than 2
    max_gap_s: float   # longest interval between two messages [s]; nan for fewer than 2


@dataclass(frozen=True)
class BagSummary:
    """What a run recorded."""

    path: Path
    duration_s: float                  # first to last message of the bag [s]
    topics: dict                       # name -> TopicStats
    metrics: dict = field(default_factory=dict)   # name_with_unit -> float
    state_source: str = ''             # what the controller's state came from (the run's record)


def topic_stats(name: str, msgtype: str, messages: list[BagMessage]) -> TopicStats:
    """Count, mean rate and largest gap of one topic's receive times."""
    t = np.array([m.t for m in messages])
    if len(t) < 2:
        return TopicStats(name, msgtype, len(t), math.nan, math.nan)
    return TopicStats(name, msgtype, len(t), (len(t) - 1) / max(t[-1] - t[0], 1e-9),
                      float(np.max(np.diff(t))))


def run_metrics(messages: dict[str, list[BagMessage]]) -> dict[str, float]:
    """Stack metrics from the decoded messages of a run; topics absent give no keys.

    Parameters
    ----------
    messages : dict
        ``read_bag`` output: absolute topic name -> messages.
    """
    out = {}
    clock = messages.get('/clock', [])
    if len(clock) >= 2:     # lockstep runs: simulated time covered, vs the wall time of the bag
        first, last = clock[0].msg.clock, clock[-1].msg.clock
        out['sim_time_span_s'] = (last.sec - first.sec) + 1e-9 * (last.nanosec - first.nanosec)
    states = [m.msg for m in messages.get('/vehicle/state', [])]
    if states:
        v = np.array([s.v for s in states])
        beta = np.array([s.beta for s in states])
        out['speed_mean_mps'] = float(np.mean(v))
        out['speed_max_mps'] = float(np.max(v))
        out['sideslip_abs_max_deg'] = float(np.degrees(np.max(np.abs(beta))))
    refs = [m.msg for m in messages.get('/drift/reference', [])]
    if refs:
        e_y = np.array([r.e_y for r in refs])
        out['lateral_error_rms_m'] = float(np.sqrt(np.mean(e_y ** 2)))
        out['lateral_error_abs_max_m'] = float(np.max(np.abs(e_y)))
    status = [m.msg for m in messages.get('/drift/nmpc/status', [])]
    if status:
        solve = np.array([s.solve_time for s in status])
        out['nmpc_solve_time_mean_ms'] = float(1e3 * np.mean(solve))
        out['nmpc_solve_time_max_ms'] = float(1e3 * np.max(solve))
        out['nmpc_ok_fraction'] = float(np.mean([s.status == 0 for s in status]))
    if states and refs:   # the drift metrics of the run report (one definition of each)
        from drift_tools.report import run_metrics as drift_metrics
        from drift_tools.timeseries import series_from_bag
        m = drift_metrics(series_from_bag(messages))
        for key in ('beta_rms_error_deg', 'mean_abs_beta_steady_deg', 'max_abs_e_y_m',
                    'time_in_drift_s', 'spun'):
            value = m.get(key)
            if value is not None and (not isinstance(value, float) or math.isfinite(value)):
                out[key] = float(value)
    return out


def summarize_bag(bag_dir, backend: str = 'rosbags') -> BagSummary:
    """Read a bag back and summarise it (see :class:`BagSummary`)."""
    info = bag_info(bag_dir)
    messages = read_bag(bag_dir, backend=backend)
    topics = {name: topic_stats(name, info.topics[name].msgtype if name in info.topics else '?',
                                msgs)
              for name, msgs in sorted(messages.items())}
    return BagSummary(Path(bag_dir), info.duration, topics, run_metrics(messages),
                      state_source(bag_dir))


def state_source(bag_dir) -> str:
    """'sensors realistic -> estimator ekf', 'no estimator' or '' (no run record)."""
    from drift_tools.run_info import read_run_info
    info = read_run_info(bag_dir)
    if not info:
        return ''
    if info.get('sensors'):
        faults = info.get('sensor_faults', '[]')
        return (f'sensors {info["sensors"]} -> estimator {info.get("estimator") or "?"}'
                + (f', faults {faults}' if faults not in ('', '[]') else ''))
    return 'no estimator'


def format_summary(summary: BagSummary) -> str:
    """A plain-text table of :class:`BagSummary` for the terminal."""
    lines = [f'bag {summary.path}: {summary.duration_s:.1f} s, '
             f'{sum(t.count for t in summary.topics.values())} messages']
    if summary.state_source:
        lines.append(f'  state: {summary.state_source}')
    width = max([len(n) for n in summary.topics] + [5])
    lines.append(f'  {"topic".ljust(width)}  {"count":>7}  {"rate Hz":>8}  {"max gap s":>9}  type')
    for t in summary.topics.values():
        lines.append(f'  {t.name.ljust(width)}  {t.count:7d}  {t.rate_hz:8.1f}  '
                     f'{t.max_gap_s:9.3f}  {t.msgtype}')
    if not summary.topics:
        lines.append('  (no topics recorded)')
    for key, value in summary.metrics.items():
        lines.append(f'  {key} = {value:.4g}')
    return '\n'.join(lines)
