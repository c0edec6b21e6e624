"""Plant: the simulated car, stepped every 10 ms by a command, returning what the car measures.

``Plant.step(command)`` integrates the double-track model of ``drift_sim.model`` over one call
(``substeps`` RK4 steps of ``dt`` in one casadi call), applying the drive torque request through
its transport delay and the steering request through the actuator (or, in TORQUE_ONLY mode, the
driver's steering passed as ``steer``). It returns the measured ``VehicleState`` (noisy, each
signal with its own delay) and keeps the ground truth in ``Plant.truth``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drift_control.signals import Command, Mode, VehicleState
from drift_sim.model import NS, NUP, NY, PP, S, UP, Y, PlantModel, n_params
from drift_sim.params import SIGNALS, PlantParams
from drift_sim.road import friction, friction_modes

# measured signal columns, and the noise/delay group (plant.measurement key) of each
_COLUMNS = ('V', 'beta', 'r', 'vx', 'vy', 'ax', 'ay', 'w_FL', 'w_FR', 'w_RL', 'w_RR', 'delta',
            'steering_torque', 'drive_torque', 'x', 'y', 'yaw')
_GROUP = {'w_FL': 'wheel_speeds', 'w_FR': 'wheel_speeds', 'w_RL': 'wheel_speeds',
          'w_RR': 'wheel_speeds', 'x': 'pose', 'y': 'pose'}
C = {name: i for i, name in enumerate(_COLUMNS)}


@dataclass(frozen=True)
class GroundTruth:
    """The plant's true state after a call.

    Attributes
    ----------
    t : float
        Simulation time [s].
    x : numpy.ndarray
        Full state, laid out as ``drift_sim.model.S``.
    y : numpy.ndarray
        Outputs (accelerations, steering torque, aligning moment, mu, per-wheel forces), ``Y``.
    state : VehicleState
        The true signals in the measured format (no noise, no delay).
    """

    t: float
    x: np.ndarray
    y: np.ndarray
    state: VehicleState

    @property
    def mu(self) -> float:
        """Friction under the CoG [-]."""
        return float(self.y[Y.MU])


# the signals copied from a state or an output, by column
_FROM_STATE = {'r': S.R, 'vx': S.VX, 'vy': S.VY, 'w_FL': S.OMEGA_FL, 'w_FR': S.OMEGA_FR,
               'w_RL': S.OMEGA_RL, 'w_RR': S.OMEGA_RR, 'delta': S.DELTA,
               'drive_torque': S.T_DRIVE, 'x': S.X, 'y': S.Y, 'yaw': S.YAW}
_FROM_OUTPUT = {'ax': Y.AX, 'ay': Y.AY, 'steering_torque': Y.STEER_TORQUE}
_STATE_COLS = [C[c] for c in _FROM_STATE]
_STATE_ROWS = list(_FROM_STATE.values())
_OUTPUT_COLS = [C[c] for c in _FROM_OUTPUT]
_OUTPUT_ROWS = list(_FROM_OUTPUT.values())


def signals(X: np.ndarray, Ys: np.ndarray) -> np.ndarray:
    """True measured signals from states (NS, n) and outputs (NY, n): array (n, len(_COLUMNS))."""
    vx, vy = X[S.VX], X[S.VY]
    out = np.empty((X.shape[1], len(_COLUMNS)))
    out[:, C['V']] = np.hypot(vx, vy)
    out[:, C['beta']] = np.arctan2(vy, vx)
    out[:, _STATE_COLS] = X[_STATE_ROWS].T
    out[:, _OUTPUT_COLS] = Ys[_OUTPUT_ROWS].T
    return out


def _state(t: float, row: np.ndarray) -> VehicleState:
    (V, beta, r, vx, vy, ax, ay, w_FL, w_FR, w_RL, w_RR, delta, steering_torque, drive_torque,
     x, y, yaw) = row.tolist()   # Python floats, in _COLUMNS order
    return VehicleState(
        stamp=t, V=V, beta=beta, r=r, vx=vx, vy=vy, ax=ax, ay=ay,
        wheel_speeds=(w_FL, w_FR, w_RL, w_RR), delta=delta, steering_torque=steering_torque,
        drive_torque=drive_torque, x=x, y=y, yaw=math.remainder(yaw, 2.0 * math.pi))


class Plant:
    """The simulated car.

    Parameters
    ----------
    params : PlantParams
        Plant parameters.
    mu : float
        Mean surface friction [-]; the road field varies around it by ``params.road.variation``.
    seed : int
        Seeds the friction field and the measurement noise; same seed, same trajectory.
    model : PlantModel, optional
        Reuse compiled Functions across plants with the same parameters.
    """

    def __init__(self, params: PlantParams, mu: float = 1.0, seed: int = 0,
                 model: PlantModel | None = None):
        self.p = params
        self.model = model or PlantModel(params)
        self.seed = int(seed)
        self.q = np.zeros(n_params(params))
        self.q[PP.MU], self.q[PP.VARIATION] = mu, params.road.variation
        self.q[PP.LOCKING] = params.lsd.locking
        self.modes = friction_modes(params.road, seed)
        self.q[len(PP):] = self.modes.ravel()
        meas = params.measurement
        self._std = np.array([meas[_GROUP.get(c, c)].std if _GROUP.get(c, c) in meas else 0.0
                              for c in _COLUMNS])
        self._lag = np.array([int(round(meas[_GROUP.get(c, c)].delay / params.dt))
                              if _GROUP.get(c, c) in meas else 0 for c in _COLUMNS])
        self._torque_lag = int(round(params.powertrain.delay / params.dt))
        self.reset()

    # --- configuration at run time ---------------------------------------------------------

    @property
    def mu(self) -> float:
        """Mean surface friction [-]."""
        return float(self.q[PP.MU])

    def set_mu(self, mu: float) -> None:
        """Change the mean surface friction (a wet patch, a fault) [-]."""
        self.q[PP.MU] = mu

    def set_locking(self, locking: float) -> None:
        """Change the LSD locking fraction [-] (0 open, 1 up to the full input torque)."""
        self.q[PP.LOCKING] = locking

    def friction_at(self, x, y):
        """The road friction at map positions ``x, y`` [m] [-]."""
        return friction(np.asarray(x, float), np.asarray(y, float), self.q[PP.MU],
                        self.q[PP.VARIATION], self.modes)

    # --- stepping --------------------------------------------------------------------------

    def reset(self, V: float = 0.0, beta: float = 0.0, r: float = 0.0, x: float = 0.0,
              y: float = 0.0, yaw: float = 0.0, delta: float = 0.0,
              drive_torque: float = 0.0, rear_slip: float = 0.0) -> VehicleState:
        """Start a run: body state as given, free-rolling wheels, relaxed slips, zero time.

        Parameters are speed [m/s], sideslip [rad], yaw rate [rad/s], pose [m, m, rad],
        road-wheel angle [rad], drive torque at the rear axle [Nm] and the rear wheels'
        longitudinal slip [-] (0: free rolling; an established drift spins them). Returns the
        first measurement.
        """
        p = self.p
        self.t = 0.0
        self._rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0xA015E]))
        s = np.zeros(NS)
        vx, vy = V * math.cos(beta), V * math.sin(beta)
        s[[S.VX, S.VY, S.R, S.X, S.Y, S.YAW]] = vx, vy, r, x, y, yaw
        s[S.DELTA] = s[S.DELTA_REF] = delta
        s[S.T_DRIVE] = drive_torque
        s[S.AY_F] = r * vx
        b = p.body.b
        geometry = {'FL': (p.body.a, 0.5 * p.body.track_F, delta, p.wheels.R_F),
                    'FR': (p.body.a, -0.5 * p.body.track_F, delta, p.wheels.R_F),
                    'RL': (-b, 0.5 * p.body.track_R, 0.0, p.wheels.R_R),
                    'RR': (-b, -0.5 * p.body.track_R, 0.0, p.wheels.R_R)}
        for name, (px, py, steer, radius) in geometry.items():
            v_x, v_y = vx - r * py, vy + r * px
            v_cx = v_x * math.cos(steer) + v_y * math.sin(steer)
            v_cy = -v_x * math.sin(steer) + v_y * math.cos(steer)
            spin = 1.0 + rear_slip if name in ('RL', 'RR') else 1.0
            s[S[f'OMEGA_{name}']] = spin * v_cx / radius
            s[S[f'ALPHA_{name}']] = -math.atan(v_cy / math.hypot(v_cx, p.wheels.v_eps))
        self.x = s
        self._torque = np.full(self._torque_lag + p.substeps, float(drive_torque))
        self._steer_hold = delta
        _, ys = self.model.f(s, self._inputs_column(delta, 0.0, drive_torque, 0.0, False), self.q)
        row = signals(s[:, None], np.asarray(ys))
        row[:, C['steering_torque']] = 0.0
        self._hist = np.repeat(row, int(self._lag.max()) + p.substeps, axis=0)
        self.truth = GroundTruth(0.0, s.copy(), np.asarray(ys).ravel(), _state(0.0, row[0]))
        return self._measure()

    def step(self, command: Command, steer: tuple[float, float] | None = None,
             brake: float = 0.0) -> VehicleState:
        """Advance one call (``params.step`` seconds) under ``command``; return the measurement.

        Parameters
        ----------
        command : Command
            Steering angle [rad] and rate [rad/s] requests and rear axle drive torque [Nm]. In
            TORQUE_ONLY mode the steering comes from ``steer``; OFF requests zero torque and
            holds the steering.
        steer : (delta [rad], delta_rate [rad/s]), optional
            The driver's steering (TORQUE_ONLY mode); the steering torque is then limited to
            ``steering.driver_torque_max`` instead of the actuator's ``torque_max``.
        brake : float
            Total brake torque [Nm].
        """
        p = self.p
        n = p.substeps
        mode = Mode(command.mode)
        torque = command.drive_torque if mode != Mode.OFF else 0.0
        human = mode == Mode.TORQUE_ONLY or mode == Mode.OFF or steer is not None
        if steer is not None:
            delta, rate = steer
        elif mode in (Mode.FULL, Mode.FALLBACK):
            delta, rate = command.delta, command.delta_rate
        else:
            delta, rate = self._steer_hold, 0.0
        self._steer_hold = delta
        if not (math.isfinite(torque) and math.isfinite(delta) and math.isfinite(rate)):
            raise ValueError(f'plant: non-finite command {command}')
        self._torque = np.concatenate([self._torque[n:], np.full(n, float(torque))])
        U = np.repeat(self._inputs_column(delta, rate, 0.0, brake, human), n, axis=1)
        U[UP.T_REQ] = self._torque[:n]
        X, Ys = self._integrate(U)
        self.x = X[:, -1].copy()
        self.t = round(self.t + p.step, 9)
        rows = signals(X, Ys)
        # the measured steering torque is the driver's (a takeover signal): none when hands-off
        rows[:, C['steering_torque']] *= self.p.steering.driver_share if human else 0.0
        self._hist = np.concatenate([self._hist[n:], rows])
        self.truth = GroundTruth(self.t, self.x.copy(), Ys[:, -1].copy(), _state(self.t, rows[-1]))
        if not np.all(np.isfinite(self.x)):
            raise FloatingPointError(f'plant: state is not finite at t={self.t:.3f} s')
        return self._measure()

    def _integrate(self, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States (NS, n) and outputs (NY, n) after each substep from ``self.x`` under ``U``."""
        fast = self.model.compiled
        if fast is None:
            X, Ys = self.model.step(self.x, U, self.q)
            return np.asarray(X), np.asarray(Ys)
        n = U.shape[1]
        fast.inputs[0][:] = self.x
        fast.inputs[1][:] = U.ravel(order='F')   # casadi's column-major nonzeros
        q = fast.inputs[2]   # mapped: one column per substep, rewritten when q changed
        if not np.array_equal(q[:len(self.q)], self.q):
            q[:] = np.tile(self.q, n)
        fast()
        return fast.outputs[0].reshape(n, NS).T.copy(), fast.outputs[1].reshape(n, NY).T.copy()

    def _inputs_column(self, delta, rate, torque, brake, human) -> np.ndarray:
        st = self.p.steering
        u = np.zeros((NUP, 1))
        u[UP.DELTA_CMD], u[UP.DELTA_RATE_CMD] = delta, rate
        u[UP.T_REQ], u[UP.BRAKE] = torque, brake
        u[UP.STEER_TORQUE_MAX] = (st.driver_torque_max if human else st.torque_max) * st.ratio
        return u

    def measure(self) -> VehicleState:
        """A new measurement of the present state (fresh noise, no time step): what a car's
        sensors send while it waits."""
        return self._measure()

    def _measure(self) -> VehicleState:
        n = len(self._hist)
        row = self._hist[n - 1 - self._lag, np.arange(len(_COLUMNS))]
        row = row + self._std * self._rng.standard_normal(len(_COLUMNS))
        return _state(self.t, row)


__all__ = ['GroundTruth', 'Plant', 'SIGNALS', 'signals']
