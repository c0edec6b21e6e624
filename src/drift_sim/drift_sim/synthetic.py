"""A synthetic drift through the sensor units into an estimator: a truth the estimator's model
describes exactly, to test the estimator alone (convergence, faults, consistency).

    sensors = Sensors(load_sensor_params('realistic'), 0.01, seed)
    truths, states = drive(sensors, estimator, 55.0, lambda t: circle(t, vehicle))
"""
from __future__ import annotations

import math

from drift_control.params import VehicleParams
from drift_control.signals import VehicleState


def circle(t: float, vehicle: VehicleParams, V: float = 9.0, beta: float = -0.5,
           r: float = 0.6, r_wave: float = 0.0) -> VehicleState:
    """A left drift on a circle at speed ``V``, sideslip ``beta`` and yaw rate ``r`` (plus
    ``r_wave sin(2t)``: its heading follows, its position stays on the constant-rate circle)."""
    r_t = r + r_wave * math.sin(2.0 * t)
    yaw = r * t + r_wave * (1.0 - math.cos(2.0 * t)) / 2.0
    vx, vy = V * math.cos(beta), V * math.sin(beta)
    R = V / r
    delta = -0.1
    w_F = (vx * math.cos(delta) + (vy + vehicle.a * r_t) * math.sin(delta)) / vehicle.R_F
    return VehicleState(stamp=round(t, 9), V=V, beta=beta, r=r_t, vx=vx, vy=vy, ax=-r_t * vy,
                        ay=r_t * vx, wheel_speeds=(w_F, w_F, 40.0, 40.0), delta=delta,
                        drive_torque=2000.0, x=R * math.sin(yaw + beta),
                        y=-R * math.cos(yaw + beta), yaw=math.remainder(yaw, 2.0 * math.pi))


def drive(sensors, estimator, seconds: float, truth, dt: float = 0.01):
    """Step ``truth(t)`` through ``sensors`` (a ``drift_sim.sensors.Sensors`` at ``dt``) into
    ``estimator`` for ``seconds``; returns the truths and the estimator's states."""
    truths = [truth(0.0)]
    states = [estimator.step(sensors.reset(truths[0]), 0.0)]
    for k in range(1, int(round(seconds / dt)) + 1):
        t = round(k * dt, 9)
        truths.append(truth(t))
        states.append(estimator.step(sensors.step(truths[-1]), t))
    return truths, states
