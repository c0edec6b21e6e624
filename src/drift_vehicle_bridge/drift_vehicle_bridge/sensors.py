"""Sensor mode: the car's sensor units reassembled from their checked PDUs, for the estimator.

A unit's signals may span several PDUs (the INS over velocity, yaw and pose frames) and a PDU may
carry several units (CAN FD). A unit's sample is complete once every PDU carrying its signals has
been accepted since its last sample, the oldest of them at most ``max_spread`` before (a gateway
sends a unit's frames together; a burst may straddle two bridge cycles); it describes the newest
of those receptions minus the unit's latency. A PDU lost or rejected drops the unit's sample: a
dropout, which the estimator sees as such, not a sample patched from older values.
"""
from __future__ import annotations

from typing import NamedTuple

from drift_control.params import ParamError
from drift_vehicle_bridge.codec import Codec, Frame
from drift_vehicle_bridge.description import SENSOR_SIGNALS


class UnitSample(NamedTuple):
    """One complete sample of one unit, as received."""

    unit: str                     # a key of SENSOR_SIGNALS (drift_control.estimator.FIELDS)
    age: float                    # how long before ``now`` of ``take`` it was measured [s]
    values: tuple[float, ...]     # in the order of SENSOR_SIGNALS[unit]


class SensorAssembler:
    """Collects accepted PDUs into unit samples.

    Parameters
    ----------
    codec : Codec
        The bus description; every sensor unit's signals must be on it (ParamError naming
        what is missing).
    latency : dict
        Unit -> sample instant to reception [s].
    max_spread : float
        The longest time between the first and the last PDU of one sample [s]; older parts
        are dropped (1.5 bridge cycles by default: a burst split by one cycle boundary).
    """

    def __init__(self, codec: Codec, latency: dict[str, float], max_spread: float = 0.015):
        if codec.sensor_missing:
            unit, sigs = next(iter(codec.sensor_missing.items()))
            raise ParamError(f'{codec.description.source}: sensor mode needs the {unit} '
                             f'signal(s) {list(sigs)} on a GATEWAY PDU')
        self.codec, self.latency, self.max_spread = codec, dict(latency), max_spread
        self._got: dict[str, dict[str, tuple[dict, float]]] = {u: {} for u in SENSOR_SIGNALS}
        self.samples = {u: 0 for u in SENSOR_SIGNALS}   # complete samples so far, per unit

    def receive(self, frame: Frame, now: float) -> None:
        """An accepted PDU at time ``now`` [s]."""
        for unit in self.codec.pdu_units.get(frame.name, ()):
            self._got[unit][frame.name] = (frame.values, now)

    def take(self, now: float) -> list[UnitSample]:
        """The units complete since the last call, their age at ``now`` [s]."""
        out = []
        for unit, pdus in self.codec.sensor_frames.items():
            got = self._got[unit]
            for name in [n for n, (_, t) in got.items() if now - t > self.max_spread]:
                del got[name]   # the rest of its sample was lost
            if len(got) < len(pdus):
                continue
            values = {}
            for frame_values, _ in got.values():
                values.update(frame_values)
            newest = max(t for _, t in got.values())
            out.append(UnitSample(unit, now - newest + self.latency[unit],
                                  tuple(float(values[s]) for s in SENSOR_SIGNALS[unit])))
            got.clear()
            self.samples[unit] += 1
        return out


def sensor_timeouts(codec: Codec, rate: dict[str, float], frame_timeout: float) \
        -> dict[str, float]:
    """PDU -> its timeout in sensor mode: three periods of its slowest unit, at least
    ``frame_timeout`` [s]."""
    return {name: max(frame_timeout, 3.0 / min(rate[u] for u in units))
            for name, units in codec.pdu_units.items() if units}


__all__ = ['SensorAssembler', 'UnitSample', 'sensor_timeouts']
