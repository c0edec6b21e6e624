"""Bag commands of the operator CLI: an overview from the MCAP index, a slice, a CSV export.

A finished bag is summarised from its index (statistics, channels, metadata) without reading
the messages; an unfinished or damaged one is scanned (``drift_tools.bag_salvage``). Slice and
export write new files; the bag itself is only read.
"""
from __future__ import annotations

import csv
from pathlib import Path


def bag_overview(bag_dir) -> tuple[list[str], list[str]]:
    """(lines to print, problems) of a bag."""
    from drift_tools.bag import is_finished
    from drift_tools.bag_salvage import bag_file, scan_bag
    from drift_tools.run_info import read_run_info

    bag_dir = Path(bag_dir)
    path = bag_file(bag_dir)
    problems: list[str] = []
    if is_finished(bag_dir):
        from mcap.reader import make_reader
        with open(path, 'rb') as fh:
            summary = make_reader(fh).get_summary()
        stats = summary.statistics
        counts = {summary.channels[cid].topic: n
                  for cid, n in stats.channel_message_counts.items()}
        schemas = {ch.topic: summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas
                   else '?' for ch in summary.channels.values()}
        t0, t1, n = stats.message_start_time, stats.message_end_time, stats.message_count
        head = f'{bag_dir}: {n} messages over {(t1 - t0) * 1e-9:.2f} s ' \
               f'({stats.chunk_count} chunks, from the index)'
    else:
        scan = scan_bag(bag_dir)
        counts, schemas = {}, {}
        for ch in scan.channels.values():
            schema = scan.schemas.get(ch.schema_id)
            schemas[ch.topic] = schema.name if schema else '?'
        for m in scan.messages:
            topic = scan.channels[m.channel_id].topic
            counts[topic] = counts.get(topic, 0) + 1
        times = [m.log_time for m in scan.messages]
        t0, t1 = (min(times), max(times)) if times else (0, 0)
        head = f'{bag_dir}: {len(scan.messages)} readable messages over {(t1 - t0) * 1e-9:.2f} s ' \
               f'({scan.chunks} chunks, scanned)'
        problems = scan.problems()
    lines = [head]
    width = max((len(t) for t in schemas), default=5)
    for topic in sorted(schemas):
        lines.append(f'  {topic.ljust(width)}  {counts.get(topic, 0):7d}  {schemas[topic]}')
    run = read_run_info(bag_dir)
    if run:
        dirty = ' (with uncommitted changes)' if run.get('dirty') == 'true' else ''
        lines.append(f'  run: scenario {run.get("scenario") or "?"}, vehicle '
                     f'{run.get("vehicle") or "(the scenario default)"}, seed '
                     f'{run.get("seed") or "(the scenario default)"}, overrides '
                     f'{run.get("overrides")}, commit {run.get("commit", "")[:12]}{dirty}')
        lines.append(f'  command: {run.get("command_line", "")}')
    lines += [f'  problem: {p}' for p in problems]
    if problems:
        lines.append(f'  repair: drift bag recover {bag_dir} <new directory>')
    return lines, problems


def _window(bag_dir, start: float, end: float | None, topics):
    """The raw messages of ``[start, end]`` s after the first message, and that first time."""
    from drift_tools.replay import iter_raw
    messages = list(iter_raw(bag_dir, topics))
    if not messages:
        raise ValueError(f'{bag_dir}: no messages' + (f' on {topics}' if topics else ''))
    t0 = messages[0].t_ns
    span = (messages[-1].t_ns - t0) * 1e-9
    if start < 0 or start > span or (end is not None and end < start):
        raise ValueError(f'time window {start:g}..{end if end is not None else "end"} s is '
                         f'outside the bag (0..{span:.3f} s)')
    lo, hi = t0 + round(start * 1e9), None if end is None else t0 + round(end * 1e9)
    return [m for m in messages if m.t_ns >= lo and (hi is None or m.t_ns <= hi)], t0


def slice_bag(bag_dir, out_dir, start: float = 0.0, end: float | None = None,
              topics=None) -> dict[str, int]:
    """A new bag with the messages of a time window (and only ``topics``); counts per topic."""
    from drift_tools.bag_writer import BagWriter
    from drift_tools.replay import topic_qos
    from drift_tools.run_info import RECORD_NAME, read_run_info

    window, _ = _window(bag_dir, start, end, topics)
    qos = topic_qos(bag_dir)
    with BagWriter(out_dir) as out:
        run = read_run_info(bag_dir)
        if run:
            out.add_metadata(RECORD_NAME, {**run, 'sliced_from': str(Path(bag_dir).resolve()),
                                           'slice': f'{start:g}..{end if end is not None else ""}'})
        for m in window:
            reliable, latched = qos.get(m.topic, (True, False))
            out.add_topic(m.topic, m.msgtype, reliable=reliable, latched=latched)
            out.write(m.topic, m.data, m.t_ns)
        return out.counts()


def flatten(value, prefix: str = '') -> dict:
    """A decoded message as ``{'header.stamp.sec': ..., 'wheel_speeds.0': ...}``."""
    fields = getattr(value, '__slots__', None)
    if hasattr(value, 'get_fields_and_field_types'):
        names = list(value.get_fields_and_field_types())
    elif fields is not None and not isinstance(value, (str, bytes)):
        names = [f for f in fields if not f.startswith('_')]
    elif hasattr(value, '__dataclass_fields__'):
        names = list(value.__dataclass_fields__)
    else:
        names = None
    if names is not None:
        out = {}
        for name in names:
            out.update(flatten(getattr(value, name), f'{prefix}{name}.'))
        return out
    if isinstance(value, (list, tuple)) or type(value).__name__ in ('ndarray', 'array'):
        if len(value) > 64:                         # a horizon or a path: not a CSV column
            return {prefix.rstrip('.') + '.len': len(value)}
        out = {}
        for i, item in enumerate(value):
            out.update(flatten(item, f'{prefix}{i}.'))
        return out
    if hasattr(value, 'item'):
        value = value.item()
    return {prefix.rstrip('.'): value}


def export_csv(bag_dir, out_dir, topics=None) -> list[tuple[Path, int]]:
    """One CSV per topic: log time [s] and the flattened fields; returns (file, rows)."""
    from drift_tools.bag import read_bag

    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise FileExistsError(f'{out_dir}: exists and is not empty')
    messages = read_bag(bag_dir, topics=topics, backend='mcap')
    if not any(messages.get(t) for t in (topics or messages)):
        raise ValueError(f'{bag_dir}: no messages' + (f' on {topics}' if topics else ''))
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for topic, msgs in sorted(messages.items()):
        if not msgs:
            continue
        rows = [{'log_time_s': m.t, **flatten(m.msg)} for m in msgs]
        columns = list(dict.fromkeys(k for row in rows for k in row))
        path = out_dir / (topic.strip('/').replace('/', '__') + '.csv')
        with open(path, 'w', newline='', encoding='utf-8') as fh:
            writer = csv.DictWriter(fh, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)
        written.append((path, len(rows)))
    return written
