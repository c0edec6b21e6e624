"""The closed loop in one process, no DDS: plant + reference selector + NMPC on a scenario.

The same cores the nodes run, stepped like do-mpc's ``make_step`` loop: the controller at its own
period (the NMPC's control period, 20 ms) on the latest measured state, the plant every 10 ms.
``scripts/simulate.py`` is its command line; the acceptance tests call ``run_closed_loop``.
The ``feedforward`` controller applies the selected equilibrium's (delta, T_R) open loop: a
baseline to judge the NMPC against, not a substitute.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from drift_control.assembly import load_setup
from drift_control.params import config_dir
from drift_control.signals import Command, Mode
from drift_sim import metrics
from drift_sim.scenario import load_scenario
from drift_sim.simulator import Simulator


class Feedforward:
    """The reference equilibrium's steering angle and torque, applied open loop."""

    period = 0.02

    def step(self, state, ref, now):
        if ref is None:
            return None, math.nan
        eq = ref.target
        return Command(now, eq.delta, 0.0, eq.T_R, Mode.FULL), 0.0

    def prepare(self):
        """Nothing to prepare ahead of the next state."""


class NmpcController:
    """drift_control.nmpc.Nmpc behind the same small interface.

    The NMPC is told the named surface's nominal mu (config/vehicle/surfaces.yaml), not the
    scenario's actual one: a ``--set surface.mu=...`` is a friction the controller does not know.
    """

    def __init__(self, setup, supervised: bool = True, plans_at=(), stamped: bool = False):
        from drift_control.nmpc import STATE_NAMES   # imported when used: heavy
        self.nmpc = setup.build_nmpc(supervised=supervised, stamped=stamped)
        self.period = setup.nmpc.Ts
        self.trip_time: float | None = None   # when the supervisor latched the fallback [s]
        self._delta_col = STATE_NAMES.index('delta')
        self.plan_delta = math.nan
        self._plans_at = sorted(plans_at)
        self.plans: list[dict] = []   # the plans asked for by ``plans_at`` (plan_record)

    def step(self, state, ref, now):
        result = self.nmpc.step(state, ref, now)
        # the steering the NMPC plans for the end of its horizon (TORQUE_ONLY: never applied)
        plan = result.predicted_states
        self.plan_delta = float(plan[-1, self._delta_col]) if plan.size else math.nan
        if self._plans_at and now >= self._plans_at[0] - 0.5 * self.period:
            self._plans_at.pop(0)
            self.plans.append(plan_record(now, state, ref, result))
        if self.trip_time is None and 'supervisor:' in result.message:
            self.trip_time = now
        return result.command, result.solve_time_s

    def prepare(self):
        """The NMPC's work for the next cycle that needs no measurement (after the command)."""
        self.nmpc.prepare()


def plan_record(now: float, state, ref, result) -> dict:
    """One NMPC solve as plain lists (SI units): the measured state, the reference row of each
    stage as the NMPC tracked it, and the predicted states and inputs (diagnosis)."""
    from drift_control.nmpc import INPUT_NAMES, STATE_NAMES, reference_rows
    N = len(result.predicted_inputs)
    rows = reference_rows(ref, N).T.tolist() if ref is not None and N else None
    names = ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta', 'T_R')
    return {
        't': now, 'message': result.message,
        'measured': {k: getattr(state, k) for k in STATE_NAMES + ('drive_torque',)}
        if state is not None else None,
        'reference': dict(zip(names, rows)) if rows else {},
        'states': {k: result.predicted_states[:, i].tolist()
                   for i, k in enumerate(STATE_NAMES)} if result.predicted_states.size else {},
        'inputs': {k: result.predicted_inputs[:, i].tolist()
                   for i, k in enumerate(INPUT_NAMES)} if result.predicted_inputs.size else {},
    }


class SingleTrackSim:
    """The controller's own single-track model (drift_control.model_plant) as the plant.

    A diagnosis aid (``--plant single_track``): no model mismatch, no actuator dynamics, no
    friction field, no noise. If a scenario fails here too, the cause is not the simulator.
    """

    def __init__(self, loaded, vehicle):
        from drift_control.frenet import Frenet
        from drift_control.model_plant import ModelPlant
        from drift_control.vehicle import NX, X
        from drift_sim.scenario import initial_pose
        self.loaded, self.scenario = loaded, loaded.scenario
        self.plant = ModelPlant(vehicle, mu=loaded.mu, seed=self.scenario.seed)
        self.plant.seed, self.plant.model = self.scenario.seed, None
        self.dt, self.commands_lost = 0.01, 0
        start = initial_pose(self.scenario, loaded.path, vehicle.L)
        x0 = np.zeros(NX)
        x0[[X.V, X.BETA, X.R, X.DELTA]] = start['V'], start['beta'], start['r'], start['delta']
        x0[X.OMEGA_F] = start['V'] * math.cos(start['beta']) / vehicle.R_F
        x0[X.OMEGA_R] = start['V'] * math.cos(start['beta']) / vehicle.R_R
        self._x0, self._pose = x0, (start['x'], start['y'], start['yaw'])
        self._frenet = Frenet(loaded.path)
        self._frenet.reset(self.scenario.initial.s)
        self._last = Command(0.0, start['delta'], 0.0, 0.0, Mode.FULL)

    @property
    def t(self):
        return self.plant.t

    def reset(self):
        self.state = self.plant.reset(self._x0, self._pose)
        return self.state

    def step(self, command):
        if command is None:
            self.commands_lost += 1
        self._last = command or self._last
        self.state = self.plant.step(self._last, self.dt)
        return self.state

    def sample(self):
        from drift_sim.simulator import TruthSample
        st = self.state
        fp = self._frenet.project(st.x, st.y, st.yaw, st.beta)
        K = float(fp.K)
        beta_des = -math.copysign(float(self.loaded.path.beta_at(fp.s)), K) if K else 0.0
        return TruthSample(st.stamp, st, self.plant.mu, float(fp.s), float(fp.e_y), beta_des,
                           st.drive_torque, self._last.delta)


class SensedSim:
    """The simulator seen through ``drift_sim.sensors`` and a state estimator (or none: the
    newest sample of each unit); the controller gets the estimator's state."""

    def __init__(self, sim, setup, cfg: Path, sensors: str, estimator: str, sensor_set=(),
                 sensor_faults=(), estimator_set=()):
        from drift_control.estimator import Estimator, LatestSamples, load_estimator_params
        from drift_sim.sensors import Sensors, load_sensor_params, parse_fault
        self.sim = sim
        self.sensors = Sensors(load_sensor_params(sensors, cfg, sensor_set), sim.dt,
                               sim.plant.seed, [parse_fault(f) for f in sensor_faults])
        self.estimator = (Estimator(setup.vehicle, load_estimator_params(
            cfg / 'estimator.yaml', estimator_set)) if estimator == 'ekf' else LatestSamples())

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def reset(self):
        self.sim.reset()
        self.state = self.estimator.step(self.sensors.reset(self.sim.truth.state), self.sim.t)
        return self.state

    def step(self, command):
        self.sim.step(command)
        state = self.estimator.step(self.sensors.step(self.sim.truth.state), self.sim.t)
        self.state = state or self.state
        return self.state

    def summary(self) -> dict:
        """The estimator's NIS, fault events and cost per step (none without an estimator)."""
        est = self.estimator
        if not hasattr(est, 'nis_summary'):
            return {}
        times = np.asarray(est.step_times) * 1e3
        return {'nis': est.nis_summary(),
                'events': [(round(e.t, 3), e.channel, e.reason) for e in est.events],
                'step_ms_mean': float(times.mean()), 'step_ms_p50': float(np.percentile(times, 50)),
                'step_ms_p99': float(np.percentile(times, 99))}


def run_closed_loop(scenario: str, overrides=(), seed: int | None = None,
                    controller: str = 'nmpc', plant: str = 'double_track',
                    config: str | Path | None = None, progress: bool = False,
                    stop_on_spin: bool = False, supervised: bool = True,
                    vehicle: str | None = None,
                    refuse_infeasible: bool = False, sensors: str | None = None,
                    estimator: str = 'none', sensor_set=(), sensor_faults=(),
                    estimator_set=(), plans_at=()) -> tuple[dict, dict]:
    """Run a scenario's closed loop in this process; returns (metrics, time series).

    Parameters
    ----------
    scenario : str
        Name under ``config/scenarios`` or a file.
    overrides : iterable of str
        ``key=value`` overrides of scenario keys (``surface.mu=0.55``, ``plant.lsd.locking=1``).
    seed : int, optional
        Overrides the scenario's seed.
    controller : {'nmpc', 'feedforward'}
    plant : {'double_track', 'single_track'}
        'single_track': the controller's own model as the plant (diagnosis of mismatch).
    supervised : bool
        Run the NMPC with its supervisor (``config/supervisor.yaml``); False shows what the
        controller does when nothing stops it (the paper's spin with a weak steering).
    vehicle : str, optional
        Overrides the scenario's vehicle (``config/vehicle/<name>.yaml``).
    refuse_infeasible : bool
        ParamError before the run when the path asks for a drift the car cannot hold.
    sensors : str, optional
        ``config/sim/sensors/<name>.yaml`` (e.g. 'realistic'): the controller sees the car
        through these sensors instead of the plant's own noise and delay model (the default).
    estimator : {'none', 'ekf'}
        With ``sensors``: 'ekf' fuses them (``drift_control.estimator``), 'none' hands the
        controller the newest sample of each unit.
    sensor_set, sensor_faults, estimator_set : iterable of str
        ``key=value`` overrides of the sensor set and of ``config/estimator.yaml``; faults as
        ``drift_sim.sensors.parse_fault`` reads them (``ins:dropout:30:31``).
    plans_at : iterable of float
        Times [s] at which the NMPC's plan is kept (the first solve within half a control
        period of each, or after it): the metrics gain ``plans``, one ``plan_record`` each.
    """
    cfg = Path(config) if config else config_dir()
    setup = load_setup(cfg, scenario, vehicle, overrides, seed)
    if refuse_infeasible:
        setup.check_reference()
    loaded = load_scenario(scenario, config=cfg, spec=setup.scenario)
    sc = loaded.scenario
    selector = setup.build_selector()
    ctrl = (Feedforward() if controller == 'feedforward' else
            NmpcController(setup, supervised, plans_at,
                           stamped=sensors is not None or plant != 'double_track'))
    sim = Simulator(loaded) if plant == 'double_track' else SingleTrackSim(loaded, setup.vehicle)
    if sensors is not None:
        sim = SensedSim(sim, setup, cfg, sensors, estimator, sensor_set, sensor_faults,
                        estimator_set)
    every = max(1, int(round(ctrl.period / sim.dt)))
    # with the estimator, as the NMPC node's in-process stages: the selector after the command,
    # its reference for the next cycle (drift_control.nodes.nmpc_node)
    ahead = sensors is not None
    n_steps = int(round(sc.duration / sim.dt))

    state = sim.reset()
    command, ref = None, None
    log = {k: [] for k in ('t', 'x', 'y', 'V', 'beta', 'r', 'delta', 'T', 'omega_F', 'omega_R',
                           'e_y', 's', 'mu', 'beta_ref',
                           'beta_des', 'delta_cmd', 'delta_plan', 'T_cmd', 'lag')}
    if sensors is not None:   # what the controller saw, next to the truth
        log.update(beta_seen=[], r_seen=[], V_seen=[])
    solve_times = []
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_steps, unit='step', file=sys.stderr, desc=sc.name)
    wall0 = time.perf_counter()
    for k in range(n_steps):
        if k % every == 0:
            if ref is None or not ahead:
                ref = selector.select(state)
            new, solve = ctrl.step(state, ref, sim.t)
            if new is not None:
                command = new
                solve_times.append(solve)
            if ahead:   # on the state the plan expects at the next control instant
                ref = selector.select(ctrl.nmpc.next_state(state) or state) or ref
            ctrl.prepare()
        state = sim.step(command)
        if sensors is not None and hasattr(ctrl, 'nmpc'):   # the lag learner's own samples
            for stamp, torque in sim.estimator.torque_samples:
                ctrl.nmpc.observe_torque(stamp, torque)
        tr = sim.sample()
        st = tr.state
        for key, value in (('t', tr.t), ('x', st.x), ('y', st.y), ('V', st.V),
                           ('beta', st.beta), ('r', st.r),
                           ('delta', st.delta), ('T', st.drive_torque),
                           ('omega_F', st.omega_F), ('omega_R', st.omega_R),
                           ('e_y', tr.e_y),
                           ('s', tr.s),
                           ('mu', tr.mu), ('beta_des', tr.beta_des),
                           ('beta_ref', ref.target.beta if ref is not None else math.nan),
                           ('delta_cmd', command.delta if command else math.nan),
                           ('delta_plan', getattr(ctrl, 'plan_delta', math.nan)),
                           ('T_cmd', command.drive_torque if command else math.nan),
                           ('lag', getattr(getattr(ctrl, 'nmpc', None), 'lag', math.nan))):
            log[key].append(value)
        if sensors is not None:
            for key, value in (('beta_seen', state.beta), ('r_seen', state.r),
                               ('V_seen', state.V)):
                log[key].append(value)
        if bar is not None:
            bar.update(1)
            if k % 100 == 0:
                bar.set_postfix(beta=f'{math.degrees(st.beta):+.1f}deg', V=f'{st.V:.1f}')
        if stop_on_spin and abs(st.beta) > metrics.SPIN_BETA:
            break
    wall = time.perf_counter() - wall0
    if bar is not None:
        bar.close()
    data = {k: np.asarray(v, dtype=float) for k, v in log.items()}
    # steady-state tracking is judged against the path's desired sideslip where no reference
    beta_ref = np.where(np.isfinite(data['beta_ref']), data['beta_ref'], data['beta_des'])
    windows, transient_end = sc.metrics.steady, sc.metrics.transient_end
    if sc.metrics.settle > 0.0:
        windows = metrics.settled_windows(data['t'], data['beta_ref'], sc.metrics.settle,
                                          math.radians(sc.metrics.drift_beta_deg))
        transient_end = max(transient_end, windows[0][0] if windows else math.inf)
    out = metrics.summary(data['t'], data['beta'], beta_ref, data['e_y'], windows,
                          transient_end, math.radians(sc.metrics.drift_beta_deg),
                          solve_times, wall, V=data['V'])
    out['laps_in_steady_drift'] = metrics.laps(data['t'], data['s'], windows,
                                               loaded.path.length) if loaded.path.closed else None
    out['supervisor_trip_s'] = getattr(ctrl, 'trip_time', None)
    out['max_abs_e_y_steady_m'] = metrics.max_abs_in_windows(data['t'], data['e_y'], windows)
    out['transition_time_s'] = metrics.transition_time(
        data['t'], data['beta'], math.radians(sc.metrics.drift_beta_deg + 10.0))
    out['exit_time_s'] = metrics.exit_time(data['t'], data['beta'], data['beta_ref'])
    # the powertrain lag the NMPC planned with at the end (learnt, or its configured one)
    lags = data['lag'][np.isfinite(data['lag'])]
    out['torque_lag_s'] = float(lags[-1]) if len(lags) else None
    if sc.control_mode == 'torque_only':   # the NMPC's steering is a proposal (paper Sec. VI-B)
        out.update(metrics.steer_proposal_diff(data['t'], data['delta_cmd'], data['delta'],
                                               windows))
        out.update(metrics.steer_proposal_diff(data['t'], data['delta_plan'], data['delta'],
                                               windows, name='steer_plan'))
    out.update(scenario=sc.name, vehicle=sc.vehicle, seed=sim.plant.seed, controller=controller,
               overrides=list(overrides), expect_spin=sc.expect_spin,
               commands_lost=sim.commands_lost, plant=plant,
               plant_jit=bool(sim.plant.model and sim.plant.model.jit))
    if plans_at:
        out['plans'] = getattr(ctrl, 'plans', [])
    if sensors is not None:
        out.update(sensors=sensors, estimator=estimator, sensor_faults=list(sensor_faults),
                   estimator_summary=sim.summary())
    return out, data
