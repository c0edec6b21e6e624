"""Probe a link: which PDUs arrive, how often (from their stamps) and in which E2E state.

Listens without sending: run it in the bridge's place to check what the car's gateway forwards
before the stack is attached (``drift probe``). Every PDU of the description is checked by its own
E2E receiver, the car's state PDUs and the stack's requests alike.
"""
from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass

from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import Codec
from drift_vehicle_bridge.e2e import SMConfig


@dataclass(frozen=True)
class PduReport:
    """What the probe saw of one PDU id."""

    id: int
    name: str              # the description's name, '?' for an id it does not know
    count: int             # PDUs received
    accepted: int          # of those, passed every check
    rate: float            # [Hz] from the reception stamps; nan below two PDUs
    e2e: str               # last E2E status and state, e.g. 'OK, VALID'
    faults: dict           # fault name -> count


def probe(transport, codec: Codec, duration: float, max_counter_delta: int = 2,
          sm: SMConfig | None = None, clock=time.monotonic) -> list[PduReport]:
    """Receive for ``duration`` [s]; one report per PDU id seen, the description's order first."""
    checker = FrameChecker(codec, codec.names, max_counter_delta, sm)
    stamps: dict[int, list[float]] = {}
    counts, accepted = Counter(), Counter()
    faults: dict[int, Counter] = {}
    end = clock() + duration
    while (now := clock()) < end:
        pdu = transport.recv(timeout=min(0.05, max(0.0, end - now)))
        if pdu is None:
            continue
        stamp = pdu.timestamp or now
        first_last = stamps.setdefault(pdu.id, [stamp, stamp])
        first_last[1] = stamp
        counts[pdu.id] += 1
        before = Counter(checker.faults)
        if checker.check(pdu, stamp) is not None:
            accepted[pdu.id] += 1
        else:
            faults.setdefault(pdu.id, Counter()).update(checker.faults - before)
    order = {spec.id: k for k, spec in enumerate(codec.description.pdus)}
    reports = []
    for pdu_id in sorted(counts, key=lambda i: (order.get(i, len(order)), i)):
        spec = codec.spec_of(pdu_id)
        first, last = stamps[pdu_id]
        n = counts[pdu_id]
        rate = (n - 1) / (last - first) if n > 1 and last > first else float('nan')
        rx = checker.receivers.get(spec.name) if spec else None
        reports.append(PduReport(pdu_id, spec.name if spec else '?', n, accepted[pdu_id], rate,
                                 rx.reason() if rx else '-', dict(faults.get(pdu_id, {}))))
    return reports


def format_reports(reports: list[PduReport], codec: Codec) -> str:
    """A table of the reports, with the PDUs of the description that never arrived."""
    lines = [f'{"id":>10}  {"PDU":<16} {"count":>6} {"ok":>6} {"Hz":>7}  {"E2E":<24} faults']
    for r in reports:
        faults = ', '.join(f'{k} {v}' for k, v in sorted(r.faults.items())) or '-'
        lines.append(f'0x{r.id:08x}  {r.name:<16} {r.count:>6} {r.accepted:>6} '
                     f'{r.rate:>7.1f}  {r.e2e:<24} {faults}')
    seen = {r.name for r in reports}
    missing = [spec.name for spec in codec.description.pdus if spec.name not in seen]
    if missing:
        lines.append(f'never seen: {", ".join(missing)}')
    return '\n'.join(lines)


__all__ = ['PduReport', 'format_reports', 'probe']
