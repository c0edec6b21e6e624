"""CAN vehicle mode: the simulator as the car on a CAN bus, for bridge-in-the-loop runs.

The car's end of the DBC is ``drift_vehicle_bridge.vehicle_side.CarSide``: every 10 ms this
steps the simulator with the command the car side accepted (checked counters, CRCs, timeouts)
and writes the measured state frames. A released request (None) is what a real car does without
a valid request: no drive torque, steering held (the bridge's fallback and takeover logic is then
exercised against a plant, not against a mock).
"""
from __future__ import annotations

import dataclasses

from drift_control.cycle_watch import CycleWatch
from drift_control.signals import Command, Mode, VehicleState
from drift_sim.simulator import Simulator


class CanVehicle:
    """Steps a ``Simulator`` on commands from a ``CarSide`` and answers with state frames.

    Parameters
    ----------
    sim : Simulator
        The scenario on the plant.
    car : drift_vehicle_bridge.vehicle_side.CarSide
        The car's end of the bus (the caller owns and closes its bus).
    hold_until_engaged : bool
        Keep the plant at its initial state, still sending state frames, until the first
        accepted request: a scenario that starts mid-drift then begins when the stack has armed
        and engaged, not when process start-up and discovery happen to finish.
    sensors : drift_sim.sensors.Sensors, optional
        The car's sensor units: their samples go out in the frames (each unit at its rate,
        latency and noise) instead of the plant's measured state.
    """

    def __init__(self, sim: Simulator, car, hold_until_engaged: bool = False, sensors=None):
        self.sim, self.car = sim, car
        self.sensors = sensors
        if sensors is not None:
            sensors.reset(sim.truth.state)
        self.hold = hold_until_engaged
        self.engaged = False   # a request has been accepted since the start
        self.released = 0      # steps without an accepted request
        self.command: Command | None = None
        self.cycle = CycleWatch()   # the longest time between two steps: the car's stall

    def step(self, now: float) -> VehicleState:
        """One 10 ms cycle at ``now`` [s] (the bus side's clock): poll, step, send."""
        self.cycle.tick(now)
        command = self.car.poll_command(now)
        self.engaged = self.engaged or command is not None
        if self.hold and not self.engaged:   # sensors still measure (noise): never frozen
            state = self.sim.plant.measure()
            self._send(state, now)
            return state
        if command is None:
            self.released += 1
            command = Command(now, self.sim.state.delta, 0.0, 0.0, Mode.OFF)
        self.command = command
        state = self.sim.step(command)
        self._send(state, now)
        return state

    def _send(self, state: VehicleState, now: float) -> None:
        if self.sensors is None:
            self.car.send_state(dataclasses.replace(state, stamp=now))
        else:
            self.car.send_samples(self.sensors.step(self.sim.truth.state), state.brake_pedal)
