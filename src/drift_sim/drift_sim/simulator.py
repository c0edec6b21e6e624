"""Simulator: a scenario played on the plant, stepped by commands like every other block.

``Simulator`` owns the plant, the driver (TORQUE_ONLY scenarios), the scenario's faults and the
ground-truth path errors; the sim node and ``scripts/simulate.py`` both drive it with
``reset()`` then ``step(command)`` every ``dt`` (10 ms), so they cannot disagree.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

from drift_control.frenet import Frenet
from drift_control.signals import Command, Mode, Validity, VehicleState
from drift_sim.driver import Driver, load_driver_params
from drift_sim.model import PlantModel
from drift_sim.plant import GroundTruth, Plant
from drift_sim.scenario import LoadedScenario, initial_pose


class TruthSample(NamedTuple):
    """Ground truth of one step, with the path errors of the true pose."""

    t: float
    state: VehicleState     # true signals, no noise and no delay
    mu: float               # friction under the CoG [-]
    s: float                # arc length [m]
    e_y: float              # lateral error, positive left [m]
    beta_des: float         # the path's desired sideslip, signed [rad]
    T_applied: float        # drive torque at the wheels [Nm]
    delta_request: float    # steering angle the actuator was asked for [rad]


class Simulator:
    """A scenario on the plant.

    Parameters
    ----------
    loaded : LoadedScenario
        From ``drift_sim.scenario.load_scenario``.
    seed : int, optional
        Overrides the scenario's seed (friction field and noise).
    model : PlantModel, optional
        Share compiled Functions between simulators with the same plant parameters.
    """

    def __init__(self, loaded: LoadedScenario, seed: int | None = None,
                 model: PlantModel | None = None):
        self.loaded = loaded
        self.scenario = sc = loaded.scenario
        self.mu = loaded.mu
        self.plant = Plant(loaded.plant, mu=self.mu, seed=sc.seed if seed is None else seed,
                           model=model)
        self.dt = loaded.plant.step
        self.driver = (Driver(load_driver_params(loaded.driver_raw), loaded.path, self.dt)
                       if sc.control_mode == 'torque_only' else None)
        self._frenet = Frenet(loaded.path)
        self.reset()

    @property
    def t(self) -> float:
        """Simulation time [s]."""
        return self.plant.t

    @property
    def done(self) -> bool:
        """The scenario's duration has elapsed."""
        return self.plant.t >= self.scenario.duration - 1e-9

    @property
    def truth(self) -> GroundTruth:
        return self.plant.truth

    def reset(self) -> VehicleState:
        """Put the car at the scenario's start; returns the first measurement."""
        start = initial_pose(self.scenario, self.loaded.path, self.loaded.plant.body.L)
        self.plant.set_mu(self.mu)
        self.state = self.plant.reset(**start)
        self._frenet.reset(self.scenario.initial.s)
        if self.driver is not None:
            self.driver.reset(start['delta'], self.scenario.initial.s)
        self._last = Command(0.0, start['delta'], 0.0, start['drive_torque'], Mode.FULL)
        self._delta_request = start['delta']
        self.commands_lost = 0
        return self.state

    def step(self, command: Command | None) -> VehicleState:
        """Advance ``dt`` under ``command`` (None: no command arrived, the last one is held)."""
        t = self.plant.t
        faults = [f for f in self.scenario.faults if f.active(t)]
        kinds = {f.kind for f in faults}
        if command is None or 'command_loss' in kinds:
            self.commands_lost += 1
            command = self._last
        self._last = command
        mu = self.mu
        for f in faults:
            if f.kind == 'mu_scale':
                mu *= f.value
        self.plant.set_mu(mu)
        if 'torque_cut' in kinds:
            command = dataclasses.replace(command, drive_torque=0.0)
        steer = None
        if self.driver is not None:
            steer = self.driver.steer(self.state)
        elif 'steering_freeze' in kinds:
            steer = (self._delta_request, 0.0)
        self._delta_request = steer[0] if steer is not None else command.delta
        state = self.plant.step(command, steer=steer)
        if 'signal_dropout' in kinds:
            state = dataclasses.replace(state, validity=int(Validity.ALL & ~Validity.CONTROL))
        self.state = state
        return state

    def sample(self) -> TruthSample:
        """Ground truth now, with the path errors of the true pose."""
        tr = self.plant.truth
        st = tr.state
        fp = self._frenet.project(st.x, st.y, st.yaw, st.beta)
        K = float(fp.K)
        beta_abs = float(self.loaded.path.beta_at(fp.s))
        beta_des = -math.copysign(beta_abs, K) if K != 0.0 else 0.0
        return TruthSample(tr.t, st, tr.mu, float(fp.s), float(fp.e_y), beta_des,
                           st.drive_torque, self._delta_request)
