"""State estimator: the car's sensors fused into the ``VehicleState`` the controller consumes.

An EKF on a kinematic model driven by the IMU (states: body velocity vx, vy at the CoG, heading
psi, map position X, Y, the IMU biases of ax, ay and yaw rate, and the scale error of the front
wheels' rolling radius), aided by the INS/GNSS unit
(speed, sideslip, yaw rate, pose) and the front axle's wheel speeds. Not the single-track model:
its tyre forces need mu and tyre coefficients that differ from the car's (the plant is not the
controller's model by design), and a model error in the estimate is what the NMPC's offset-free
disturbance already learns; the IMU measures the forces instead (``docs/estimator.md`` gives
the measured comparison). Wheel speeds, steering angle and drive torque get one small
constant-rate Kalman filter each.

Latency: the EKF runs at a fusion horizon ``horizon_delay`` behind now, where every sensor's
samples have arrived, in stamp order; an output predictor carries it to the control instant
with the IMU samples since (as PX4's EKF2 does). Each scalar innovation is tested: a sample
beyond ``gate`` is rejected, a persistent or biased innovation is an IMU bias step (its bias
uncertainty is reset), a signal repeating itself is frozen, a wheel reading zero under a
moving car is stuck; each is named in ``events`` and the channel is left out until it recovers.
An accelerometer sample that jumps opens the hypothesis of an offset step, which the INS and
wheel innovations after it confirm or dismiss (a sequential test on the error such a step would
leave the filter), so a step is named as soon as the aiding sensors can tell it from the car.

Who owns what: this estimator owns the measured state (sensor noise, latency, sensor biases,
sensor faults) and never uses the controller's model; the NMPC's disturbance ``d``
(``drift_control.nmpc``) owns the model error of the single-track prediction.
"""
from __future__ import annotations

import bisect
import functools
import math
import time
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

import numpy as np

from drift_control.params import VehicleParams, from_dict, load_yaml, require, set_key, \
    split_override
from drift_control.signals import Validity, VehicleState

# what each sensor unit sends, in order (the frames of config/can/drift_vehicle.dbc)
FIELDS = {
    'ins': ('V', 'beta', 'r', 'x', 'y', 'yaw'),
    'imu': ('ax', 'ay', 'r'),
    'wheels': ('FL', 'FR', 'RL', 'RR'),
    'steering': ('delta', 'steering_torque'),
    'torque': ('drive_torque',),
}

E = IntEnum('E', 'VX VY PSI X Y B_AX B_AY B_R S_F', start=0)   # EKF state layout
NE = len(E)


class SensorSample(NamedTuple):
    """One message of one sensor unit."""

    unit: str                    # a key of FIELDS
    stamp: float                 # the time the values describe [s] (arrival minus latency)
    values: tuple[float, ...]    # in the order of FIELDS[unit], SI units


class FaultEvent(NamedTuple):
    """A sensor fault the estimator saw."""

    t: float          # when it was detected [s]
    channel: str      # 'ins.beta', 'imu.r', 'wheels.FL', ...
    reason: str       # 'frozen', 'jump', 'bias step', 'stuck at zero', 'dropout'


@dataclass(frozen=True)
class EstimatorParams:
    """Noise the filter assumes and its fault tests (``config/estimator.yaml``)."""

    horizon_delay: float        # fusion horizon behind now [s]: >= every sensor's latency
    accel_std: float            # IMU acceleration noise + unmodelled (roll, lever arm) [m/s^2]
    gyro_std: float             # IMU yaw rate noise [rad/s]
    yaw_jerk: float             # the yaw rate filter's process noise [rad/s^3 / sqrt(s)]
    accel_bias_walk: float      # [m/s^2 / sqrt(s)]
    gyro_bias_walk: float       # [rad/s / sqrt(s)]
    accel_bias_std0: float      # prior and reset std of the accelerometer biases [m/s^2]
    gyro_bias_std0: float       # prior and reset std of the gyro bias [rad/s]
    ins_std: dict[str, float]   # weight of each INS channel (V, beta, r, x, y, yaw) as a std
    ins_test_std: dict[str, float]  # the INS's own noise: its fault tests and NIS use this
    front_wheel_std: float      # the front axle's rim speed as a measure of its speed [m/s]
    wheel_std: float            # wheel speed noise incl. quantisation [rad/s]
    wheel_jerk: float           # wheel filters' process noise [rad/s^2 / sqrt(s)]
    steering_std: float         # [rad]
    steering_jerk: float        # [rad/s / sqrt(s)]
    torque_std: float           # [Nm]
    torque_jerk: float          # [Nm/s / sqrt(s)]
    gate: float                 # NIS beyond this: sample rejected (chi^2, 1 dof) [-]
    jump_gate: float            # NIS beyond this: named a jump [-]
    persist: int                # rejections in a row that mean a step, not an outlier [-]
    bias_window: int            # innovations in the bias test's window [-]
    bias_threshold: float       # |mean normalised innovation| sqrt(window) beyond: biased [-]
    frozen_false_rate: float    # chance per sample that a live INS channel or turning wheel, at
                                # its white noise, repeats long enough to be named frozen [-]
    ins_resolution: dict[str, float]    # the INS frames' LSB per channel (0: unquantised)
    wheel_resolution: float     # the wheel speed frames' LSB (0: unquantised) [rad/s]
    stuck_min_speed: float      # a wheel reading ~0 while its filter says more: stuck [rad/s]
    stuck_samples: int          # such readings in a row [-]
    max_coast: float            # without velocity aiding longer than this: V, beta invalid [s]
    timeout: float              # a unit silent this long has dropped out [s]
    ins_noise_std: dict[str, float] | None = None   # the INS's white noise, and the IMU's ...
    accel_noise_std: float = 0.0    # [m/s^2] and ...
    gyro_noise_std: float = 0.0     # [rad/s]: the NIS on the filter's actual covariance (None,
                                    # 0: the test noise and the weights)
    ins_slow_std: dict[str, float] = field(default_factory=dict)   # INS channels' slow
    ins_slow_tau: dict[str, float] = field(default_factory=dict)   # (Gauss-Markov) error: its
                                    # std and correlation time [s], in the actual covariance
    front_radius_std0: float = 0.01     # the front rolling radius's scale error: prior [-] ...
    front_radius_walk: float = 1e-4     # ... and its drift (pressure, temperature) [1/sqrt(s)]
    front_wheel_noise_std: float = 0.0  # the rim speed's own noise: the NIS (0: the weight) [m/s]
    accel_bias_walk_noise: float = 0.0  # the IMU's own offset drift: the NIS (0: the weight's)
    roll_gradient: float = 0.0  # the body's roll per lateral acceleration: the IMU's lateral
                                # channel reads a_y + g sin(roll) [rad s^2/m] (0: not modelled)
    accel_jump: float = 0.0     # an IMU acceleration moving this much in one sample opens a
                                # bias-step hypothesis for the INS to confirm (0: off) [m/s^2]
    step_accept: float = 9.2    # ... its log-likelihood ratio accepting it (Wald's SPRT) [-]
    step_dismiss: float = 4.6   # ... and the negative one dismissing it [-]
    step_span: float = 0.3      # ... undecided this long after the jump: dismissed [s]
    noise_learning_time: float = 0.0    # the fault tests learn how much noisier than its
                                # figures each channel is over this long (0: never) [s]
    imu_input: str = 'hold'     # between IMU samples: 'hold' each until the next, or 'linear'

    def __post_init__(self):
        for name in ('horizon_delay', 'accel_std', 'gyro_std', 'yaw_jerk', 'accel_bias_std0',
                     'gyro_bias_std0', 'front_wheel_std', 'wheel_std', 'wheel_jerk',
                     'steering_std', 'steering_jerk', 'torque_std', 'torque_jerk', 'gate',
                     'max_coast', 'stuck_min_speed', 'timeout'):
            require(getattr(self, name) > 0, f'estimator.{name}', 'must be positive')
        require(self.accel_bias_walk >= 0 and self.gyro_bias_walk >= 0, 'estimator',
                'bias walks must be >= 0')
        require(0 < self.front_radius_std0 < 0.2, 'estimator.front_radius_std0',
                'must be in (0, 0.2)')
        require(self.front_radius_walk >= 0, 'estimator.front_radius_walk', 'must be >= 0')
        require(self.accel_bias_walk_noise >= 0, 'estimator.accel_bias_walk_noise',
                'must be >= 0 (0: accel_bias_walk)')
        require(self.front_wheel_noise_std >= 0, 'estimator.front_wheel_noise_std',
                'must be >= 0 (0: front_wheel_std)')
        require(self.jump_gate > self.gate, 'estimator.jump_gate', 'must exceed gate')
        for name in ('roll_gradient', 'accel_jump', 'step_accept', 'step_dismiss', 'step_span',
                     'noise_learning_time'):
            require(getattr(self, name) >= 0, f'estimator.{name}', 'must be >= 0')
        require(0 < self.frozen_false_rate < 0.01, 'estimator.frozen_false_rate',
                'must be in (0, 0.01)')
        require(self.imu_input in ('hold', 'linear'), 'estimator.imu_input',
                f"{self.imu_input!r} is not 'hold' or 'linear'")
        require(self.wheel_resolution >= 0, 'estimator.wheel_resolution',
                'must be >= 0 (0: unquantised)')
        for name in ('persist', 'bias_window', 'stuck_samples'):
            require(getattr(self, name) >= 2, f'estimator.{name}', 'must be >= 2')
        require(self.accel_noise_std >= 0 and self.gyro_noise_std >= 0, 'estimator',
                'accel_noise_std and gyro_noise_std must be >= 0 (0: the weights)')
        require(set(self.ins_slow_std) == set(self.ins_slow_tau)
                and set(self.ins_slow_std) <= set(FIELDS['ins']), 'estimator.ins_slow_std',
                f'and ins_slow_tau need the same channels, of {list(FIELDS["ins"])}')
        for key in ('ins_slow_std', 'ins_slow_tau'):
            for k, v in getattr(self, key).items():
                require(v > 0, f'estimator.{key}.{k}', 'must be positive')
        for key in ('ins_std', 'ins_test_std', 'ins_noise_std', 'ins_resolution'):
            given = getattr(self, key)
            if given is None:
                continue
            missing = sorted(set(FIELDS['ins']) - set(given))
            unknown = sorted(set(given) - set(FIELDS['ins']))
            require(not missing and not unknown, f'estimator.{key}',
                    f'needs exactly {list(FIELDS["ins"])} (missing {missing}, unknown {unknown})')
            for k, v in given.items():
                if key == 'ins_resolution':
                    require(v >= 0, f'estimator.{key}.{k}', 'must be >= 0 (0: unquantised)')
                else:
                    require(v > 0, f'estimator.{key}.{k}', 'must be positive')


def load_estimator_params(path, overrides=()) -> EstimatorParams:
    """``config/estimator.yaml`` after ``key=value`` overrides; every error names the key."""
    raw = load_yaml(path)
    for item in overrides:
        set_key(raw, *split_override(item), where='estimator')
    return from_dict(EstimatorParams, raw, 'estimator')


def _bin_probabilities(noise: float) -> np.ndarray:
    """Chance of each quantisation bin (rows) for a still signal with white noise ``noise`` (in
    quantisation steps), at 64 offsets of the grid to the signal (columns)."""
    offset = np.linspace(0.0, 1.0, 64, endpoint=False)
    edges = np.arange(-math.ceil(8 * noise) - 1, math.ceil(8 * noise) + 2)[:, None] - offset
    cdf = 0.5 * (1.0 + np.vectorize(math.erf)(edges / (noise * math.sqrt(2.0))))
    return np.diff(cdf, axis=0)


def repeat_probability(noise: float, n: int) -> float:
    """Chance that ``n`` samples in a row of a still signal with white noise ``noise`` (in
    quantisation steps) read the same value; the grid's offset to the signal uniform."""
    return float(np.mean(np.sum(_bin_probabilities(noise) ** n, axis=0)))


@functools.lru_cache(maxsize=256)
def repeat_count(noise: float, false_rate: float, most: int = 100) -> int | None:
    """Identical values in a row that name a channel frozen: the fewest a live channel (white
    noise ``noise`` in quantisation steps) repeats with at most ``false_rate`` per sample.
    None when not even ``most`` would do: its noise is too far below the step for a repeat
    to say anything."""
    bins = _bin_probabilities(noise)
    power = bins * bins
    for n in range(2, most + 1):
        if np.mean(np.sum(power, axis=0)) <= false_rate:
            return n
        power *= bins
    return None


@functools.lru_cache(maxsize=64)
def _repeat_table(noise: float, false_rate: float) -> tuple[list[float], list[int | None]]:
    """For a unit quieter than its figure ``noise`` (down to an eighth of it): the chance of
    one repeat (ascending) and the repeat count that noise needs, for looking up the count
    from the repeats seen."""
    levels = noise * np.geomspace(1.0, 0.125, 25)
    return ([repeat_probability(float(x), 2) for x in levels],
            [repeat_count(float(x), false_rate) for x in levels])


class _RepeatTest:
    """'Frozen': the same raw value ``count`` times in a row, ``count`` from the channel's white
    noise and its frame's resolution for a false name at most ``false_rate`` per sample. A unit
    quieter than its figures repeats more: the share of repeats is learnt (the mean of all
    samples at first, then over ``learning_time``) and lengthens the count (never shortens it: a
    moving signal repeats less than noise alone)."""

    def __init__(self, noise_std: float, resolution: float, false_rate: float,
                 learning_time: float = 0.0):
        self.last, self.same = None, 0
        white = noise_std ** 2 - resolution ** 2 / 12.0   # the figure includes the rounding
        if resolution <= 0.0:
            self._p2, self._counts = [0.0], [2]        # unquantised noise never repeats
        elif white <= 0.0:
            self._p2, self._counts = [0.0], [None]
        else:
            self._p2, self._counts = _repeat_table(math.sqrt(white) / resolution, false_rate)
        self.repeats = self._p2[0]   # the learnt share of samples equal to the one before
        self._tau, self._stamp, self._seen = learning_time, None, 0

    @property
    def count(self) -> int | None:
        """Identical values in a row that mean frozen now (None: never)."""
        return self._counts[max(0, bisect.bisect_right(self._p2, self.repeats) - 1)]

    def feed(self, value: float, stamp: float, learn: bool = True) -> bool:
        """The raw value; True while it has repeated ``count`` times."""
        repeat = value == self.last
        self.same = self.same + 1 if repeat else 1
        self.last = value
        if learn and self._tau:   # the mean of all samples at first, then over the time
            self._seen += 1
            dt = stamp - self._stamp if self._stamp is not None else 0.0
            a = max(1.0 / self._seen, min(1.0, max(dt, 0.0) / self._tau))
            self.repeats += a * (float(repeat) - self.repeats)
        self._stamp = stamp
        count = self.count
        return count is not None and self.same >= count


class _Monitor:
    """Fault tests of one scalar channel, and its NIS record."""

    def __init__(self, name: str, p: EstimatorParams, repeats: _RepeatTest | None = None):
        self.name, self.p = name, p
        self.repeats = repeats   # the frozen test (None: not judged)
        self.rejected = 0
        self.window = deque(maxlen=p.bias_window)
        self.stamps = deque(maxlen=p.bias_window)
        self.span = 0.0   # the time a step or bias took to be seen [s]
        self.excluded: str | None = None    # the reason it is left out, or None
        self.nis: list[float] = []
        self.nis_var = 0.0   # the variance of the NIS record's sum a consistent filter has
        # the innovations' mean square against what the tests assume (a unit noisier than its
        # figures: > 1), learnt over ``noise_learning_time``; its running count and last stamp
        self.noise_ratio, self.noise_ratio_act, self._seen, self._stamp = 1.0, 1.0, 0, None

    def frozen(self, value: float, stamp: float) -> bool:
        """Feed the raw value; True while it has repeated itself long enough to be frozen (the
        share of repeats is not learnt while the channel is left out as frozen)."""
        if self.repeats is None:
            return False
        return self.repeats.feed(value, stamp, learn=self.excluded != 'frozen')

    def judge(self, nis: float, normalised: float, stamp: float,
              consistency: float | None = None) -> str:
        """'accept', 'reject', 'jump', 'step' or 'bias' for one innovation of a sample
        stamped ``stamp``; ``consistency`` is the NIS recorded (default ``nis``).

        The tests take the channel's noise as at least what its figures say, and more where its
        innovations have shown more (``noise_scale``): a unit twice as noisy as its data sheet
        would otherwise have its every tenth window named a bias."""
        consistency = nis if consistency is None else consistency
        self.nis.append(consistency)
        scale = self.noise_scale
        self._learn(nis, consistency, stamp)
        nis, normalised = nis / scale, normalised / math.sqrt(scale)
        self.window.append(normalised)   # a rejected sample is evidence of a bias too
        self.stamps.append(stamp)
        if nis > self.p.gate:
            self.rejected += 1
            if self.rejected >= self.p.persist:
                self.span = stamp - self.stamps[-min(self.rejected, len(self.stamps))]
                self.rejected = 0
                self.window.clear()
                return 'step'
            return 'jump' if nis > self.p.jump_gate and self.rejected == 1 else 'reject'
        self.rejected = 0
        if (len(self.window) == self.window.maxlen
                and abs(sum(self.window)) / math.sqrt(len(self.window)) > self.p.bias_threshold):
            self.span = stamp - self.stamps[0]
            self.window.clear()
            return 'bias'
        return 'accept'

    @property
    def noise_scale(self) -> float:
        """What the tests multiply the channel's innovation variance by: >= 1."""
        return max(1.0, self.noise_ratio)

    @property
    def noise_scale_act(self) -> float:
        """The same for the innovation variance of the actual covariance (the NIS's)."""
        return max(1.0, self.noise_ratio_act)

    def _learn(self, nis: float, consistency: float, stamp: float) -> None:
        """Running mean of the NIS (each sample's capped at the gate: an outlier or a fault
        moves it little), over all samples at first, then over ``noise_learning_time``."""
        tau = self.p.noise_learning_time
        if not tau:
            return
        self._seen += 1
        dt = stamp - self._stamp if self._stamp is not None else 0.0
        self._stamp = stamp
        a = max(1.0 / self._seen, min(1.0, max(dt, 0.0) / tau))
        gate = self.p.gate
        self.noise_ratio += a * (min(nis, gate) - self.noise_ratio)
        self.noise_ratio_act += a * (min(consistency, gate) - self.noise_ratio_act)


class _StepHypothesis:
    """'The accelerometer's offset stepped by ``delta`` at ``onset``': the IMU sample jumped
    that much, which the car can do too. Tested on the INS and wheel innovations after it by a
    sequential probability ratio test (Wald): a bias step leaves the filter an error that grows
    as its signature ``s`` (the filter's error per unit of step, carried through its own
    prediction and updates: Willsky and Jones' jump detection); the car's own motion leaves
    none."""

    def __init__(self, index: int, onset: float, delta: float):
        self.index, self.onset, self.delta = index, onset, delta
        self.s: np.ndarray | None = None   # None until the EKF has passed the onset
        self.llr = 0.0

    def start(self) -> None:
        self.s = np.zeros(NE)
        self.s[self.index] = -1.0   # the filter's offset is now the step short of the IMU's

    def evidence(self, nu: float, H: np.ndarray, S: float) -> None:
        """One innovation ``nu`` of variance ``S`` on measurement row ``H``."""
        rho = -float(H @ self.s) * self.delta   # its mean, were the step there
        self.llr += rho * (nu - 0.5 * rho) / S


class _RateFilter:
    """Constant-rate Kalman filter of one scalar signal: state (value, rate), plain floats
    (numpy costs more than the arithmetic at 2 x 2)."""

    def __init__(self, std: float, jerk: float):
        self.R, self.q = std * std, jerk * jerk
        self.x = None
        self.t = 0.0

    def _predicted(self, t):
        """(value, rate) and the covariance (p00, p01, p11) at ``t``."""
        h = max(0.0, t - self.t)
        x0, x1 = self.x
        p00, p01, p11 = self.P
        q = self.q
        return ((x0 + h * x1, x1),
                (p00 + 2.0 * h * p01 + h * h * p11 + q * h ** 3 / 3.0,
                 p01 + h * p11 + q * h * h / 2.0, p11 + q * h))

    def innovation(self, t: float, z: float) -> tuple[float, float]:
        """Innovation and its variance of a sample ``z`` stamped ``t``."""
        x, P = self._predicted(t)
        return z - x[0], P[0] + self.R

    def update(self, t: float, z: float) -> None:
        if self.x is None:
            self.reset(t, z)
            return
        (x0, x1), (p00, p01, p11) = self._predicted(t)
        S = p00 + self.R
        k0, k1 = p00 / S, p01 / S
        nu = z - x0
        self.x = (x0 + k0 * nu, x1 + k1 * nu)
        self.P = (p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01)
        self.t = t

    def reset(self, t: float, z: float) -> None:
        self.x, self.t = (z, 0.0), t
        self.P = (self.R, 0.0, 1e4 * self.R)

    def at(self, t: float) -> float:
        """The value extrapolated to ``t`` [signal unit]."""
        return float(self.x[0] + self.x[1] * max(0.0, t - self.t))


class _InnovationPairs:
    """How the aiding channels' innovations correlate, as the actual covariance implies it.

    For Gaussian innovations ``Var(NIS) = 2`` and ``Cov(NIS_i, NIS_j) = 2 Cov(nu_i, nu_j)^2 /
    (S_i S_j)``, so these give the spread of a run's mean NIS (``Estimator.nis_summary``). Per
    channel ``M = sum_i D_i D_i' / S_i`` over its past innovations, ``D_i`` the actual error's
    covariance with innovation ``i``, carried forward as the error is. A step's transitions are
    multiplied into one matrix and applied to the ``M``'s once, when the step ends.
    """

    def __init__(self, channels, n: int):
        self.index = {c: i for i, c in enumerate(channels)}
        self.n = n
        self.clear()

    def clear(self) -> None:
        self.M = np.zeros((len(self.index), self.n, self.n))
        self._start_step()

    def _start_step(self) -> None:
        self.phi = np.eye(self.n)          # the error's transition since the step began
        self.D = np.zeros((self.n, 16))    # this step's innovations' D, carried to now
        self.owner = np.zeros(16, dtype=int)
        self.S = np.ones(16)
        self.k = 0

    def transition(self, A: np.ndarray) -> None:
        """The error goes to ``A e``."""
        self.phi = A @ self.phi
        if self.k:
            self.D[:, :self.k] = A @ self.D[:, :self.k]

    def update(self, K: np.ndarray, H: np.ndarray) -> None:
        """The error goes to ``(I - K H) e`` (plus the update's own noise, independent)."""
        self.phi -= K[:, None] * (H @ self.phi)
        if self.k:
            self.D[:, :self.k] -= K[:, None] * (H @ self.D[:, :self.k])

    def past(self, channel: int, H: np.ndarray) -> float:
        """``sum_i Cov(nu, nu_i)^2 / S_i`` over the channel's earlier innovations, for a new
        innovation ``nu = H e + noise``."""
        g = H @ self.phi
        q = float(g @ self.M[channel] @ g)
        for j in range(self.k):
            if self.owner[j] == channel:
                q += float(H @ self.D[:, j]) ** 2 / self.S[j]
        return q

    def add(self, channel: int, D: np.ndarray, S: float) -> None:
        if self.k == self.D.shape[1]:
            self.end_step()
        self.D[:, self.k], self.owner[self.k], self.S[self.k] = D, channel, S
        self.k += 1

    def end_step(self) -> None:
        self.M = self.phi @ self.M @ self.phi.T
        for j in range(self.k):
            D = self.D[:, j]
            self.M[self.owner[j]] += D[:, None] * (D / self.S[j])
        self._start_step()


class _NoPairs:
    """Stands in for ``_InnovationPairs`` where no interval is wanted (a node's status)."""
    index: dict = {}

    def transition(self, A) -> None:
        pass

    def update(self, K, H) -> None:
        pass

    def end_step(self) -> None:
        pass

    def clear(self) -> None:
        pass


class Estimator:
    """EKF of the body velocity, pose and IMU biases, plus one filter per wheel and actuator.

    Parameters
    ----------
    vehicle : VehicleParams
        Front rolling radius ``R_F`` and CoG to front axle ``a`` (the front wheels' speed).
    params : EstimatorParams
    intervals : bool
        Keep what ``nis_summary`` needs for its intervals of the aiding channels (~0.17 ms a
        step, ~45 %); a node reporting the NIS without them need not.
    """

    def __init__(self, vehicle: VehicleParams, params: EstimatorParams, intervals: bool = True):
        self.vehicle, self.p, self.intervals = vehicle, params, intervals
        self.reset()

    def reset(self) -> None:
        p = self.p
        self.x: np.ndarray | None = None
        self.P = np.diag([0.1, 0.1, 1e-4, 0.1, 0.1, p.accel_bias_std0 ** 2,
                          p.accel_bias_std0 ** 2, p.gyro_bias_std0 ** 2,
                          p.front_radius_std0 ** 2])
        # the error covariance the filter actually has: its gains, the sensors' own white noise,
        # and after the EKF's states the INS channels' slow errors, which it does not estimate
        slow = list(p.ins_slow_std)
        self._slow = {f'ins.{name}': NE + i for i, name in enumerate(slow)}
        self._slow_var = np.array([p.ins_slow_std[name] ** 2 for name in slow])
        self._slow_tau = np.array([p.ins_slow_tau[name] for name in slow])
        self.P_act = np.zeros((NE + len(self._slow),) * 2)
        self.P_act[:NE, :NE] = self.P
        self.P_act[NE:, NE:] = np.diag(self._slow_var)
        self._pairs = (_InnovationPairs([f'ins.{f}' for f in FIELDS['ins']]
                                        + ['wheels.front_speed'], len(self.P_act))
                       if self.intervals else _NoPairs())
        self._q_act = np.diag([(p.accel_noise_std or p.accel_std) ** 2] * 2
                              + [(p.gyro_noise_std or p.gyro_std) ** 2])
        self.t = -math.inf                 # the EKF's time (the fusion horizon) [s]
        self._imu: deque = deque(maxlen=64)   # (stamp, ax, ay, r), newest last
        self._u = None                     # IMU input held since the EKF's time
        self._pending: list[SensorSample] = []
        self._steer: deque = deque(maxlen=16)  # (stamp, delta) for the wheel model
        self.wheels = [_RateFilter(p.wheel_std, p.wheel_jerk) for _ in FIELDS['wheels']]
        self.steering = _RateFilter(p.steering_std, p.steering_jerk)
        self.torque = _RateFilter(p.torque_std, p.torque_jerk)
        self.torque_samples: list[tuple[float, float]] = []   # the last step's taken (stamp, Nm)
        self.yaw_rate = _RateFilter(p.gyro_std, p.yaw_jerk)
        self._steering_torque = 0.0
        noise = p.ins_noise_std or p.ins_test_std
        repeats = {'ins': lambda f: _RepeatTest(noise[f], p.ins_resolution[f],
                                                p.frozen_false_rate, p.noise_learning_time),
                   'wheels': lambda f: _RepeatTest(p.wheel_std, p.wheel_resolution,
                                                   p.frozen_false_rate, p.noise_learning_time)}
        self.monitors = {f'{u}.{f}': _Monitor(f'{u}.{f}', p, repeats[u](f) if u in repeats
                                              else None) for u in FIELDS for f in FIELDS[u]}
        self.monitors['wheels.front_speed'] = _Monitor('wheels.front_speed', p)
        self._stuck = [0] * 4
        self._steps: list[_StepHypothesis] = []
        self.events: list[FaultEvent] = []
        self._now = 0.0
        self._last_aided = -math.inf
        self._arrived: dict[str, float] = {}   # unit -> when its last sample arrived [s]
        self._silent: set[str] = set()
        self.step_times: list[float] = []

    # --- the step ----------------------------------------------------------------------------

    def step(self, samples, now: float) -> VehicleState | None:
        """Take the samples that arrived since the last call; return the state at ``now``.

        None until the first INS and IMU samples have arrived.
        """
        t0 = time.perf_counter()
        self._now = now
        self.torque_samples = []
        for s in sorted(samples, key=lambda s: s.unit != 'imu'):   # the IMU first: it drives
            self._arrived[s.unit] = now
            if s.unit == 'imu':
                self._open_steps(s)
                self._imu.append((s.stamp, *s.values))
                if self.x is not None:   # bias-corrected with the newest gyro bias
                    self._scalar(self.yaw_rate, 'imu.r', s.stamp, s.values[2] - self.x[E.B_R])
            elif s.unit == 'wheels':
                self._wheel_sample(s)
                self._pending.append(s)
            elif s.unit == 'steering':
                self._steer.append((s.stamp, s.values[0]))
                self._scalar(self.steering, 'steering.delta', s.stamp, s.values[0])
                self._steering_torque = s.values[1]
            elif s.unit == 'torque':
                if self._scalar(self.torque, 'torque.drive_torque', s.stamp, s.values[0]):
                    self.torque_samples.append((s.stamp, s.values[0]))
            elif s.unit == 'ins':
                self._pending.append(s)
                if self.x is None and self._imu:
                    self._initialise(s)
        self._check_silence(now)
        if self.x is None:
            return None
        horizon = now - self.p.horizon_delay
        self._pending.sort(key=lambda s: s.stamp)
        while self._pending and self._pending[0].stamp <= horizon + 1e-9:
            s = self._pending.pop(0)
            if s.stamp < self.t - 1e-9:
                continue   # older than the horizon already fused: too late to use
            self._predict_to(s.stamp)
            (self._ins_update if s.unit == 'ins' else self._front_wheel_update)(s)
        self._predict_to(horizon)
        self._pairs.end_step()
        state = self._output(now)
        self.step_times.append(time.perf_counter() - t0)
        return state

    # --- EKF -----------------------------------------------------------------------------------

    def _initialise(self, s: SensorSample) -> None:
        V, beta, _, X, Y, yaw = s.values
        self.x = np.array([V * math.cos(beta), V * math.sin(beta), yaw, X, Y, 0.0, 0.0, 0.0,
                           0.0])
        self.t = self._last_aided = s.stamp
        self._u = self._imu_at(s.stamp)

    def _imu_at(self, t: float):
        """The newest IMU sample stamped at or before ``t`` (the oldest one if none)."""
        best = self._imu[0]
        for sample in self._imu:
            if sample[0] <= t + 1e-9:
                best = sample
        return best

    def _lateral(self, reading: float) -> tuple[float, float]:
        """The lateral acceleration a_y behind an offset-free lateral reading
        ``a_y + g sin(k a_y)`` (the rolled body's sensor sees gravity; k the roll gradient), and
        d a_y / d reading. Two Newton steps from ``reading / (1 + g k)``: ~1e-9 m/s^2 at 1 g."""
        g = self.vehicle.g
        gk = g * self.p.roll_gradient
        if not gk:
            return reading, 1.0
        k = self.p.roll_gradient
        a = reading / (1.0 + gk)
        for _ in range(2):
            a -= (a + g * math.sin(k * a) - reading) / (1.0 + gk * math.cos(k * a))
        return a, 1.0 / (1.0 + gk * math.cos(k * a))

    def _f(self, x, u, h):
        """Kinematic model over ``h`` seconds: the IMU's accelerations and yaw rate drive it."""
        _, ax, ay, r_m = u
        r = r_m - x[E.B_R]
        out = x.copy()
        out[E.VX] += h * (ax - x[E.B_AX] + r * x[E.VY])
        out[E.VY] += h * (self._lateral(ay - x[E.B_AY])[0] - r * x[E.VX])
        out[E.PSI] += h * r
        # the pose on the mean of the step's start and end velocities in the world (trapezoid):
        # Euler's start-of-step heading puts a drifting car ~h^2 V r / 2 inside its arc per step
        c0, s0 = math.cos(x[E.PSI]), math.sin(x[E.PSI])
        c1, s1 = math.cos(out[E.PSI]), math.sin(out[E.PSI])
        out[E.X] += 0.5 * h * (x[E.VX] * c0 - x[E.VY] * s0 + out[E.VX] * c1 - out[E.VY] * s1)
        out[E.Y] += 0.5 * h * (x[E.VX] * s0 + x[E.VY] * c0 + out[E.VX] * s1 + out[E.VY] * c1)
        return out

    def _input(self, t0: float, t1: float, held, following):
        """The IMU input over ``[t0, t1]``: ``held``, or with ``imu_input: linear`` the mean of
        the straight line between the samples ``held`` and ``following`` (``held`` itself past
        the newest sample). For a unit that samples the car at an instant, holding lags the
        heading by h/2 of every change of the yaw rate (5 mrad over an entry from 0 to 1 rad/s
        at 100 Hz, before the INS corrects it), the velocity likewise; a unit that averages
        over its interval is nearer the hold."""
        if self.p.imu_input == 'hold' or following is None or following[0] <= held[0]:
            return held
        w = 0.5 * (t0 + t1 - 2.0 * held[0]) / (following[0] - held[0])
        return tuple(a + w * (b - a) for a, b in zip(held, following))

    def _propagate(self, h: float, u=None) -> None:
        if h <= 0.0:
            return
        p, x = self.p, self.x
        u = self._u if u is None else u
        r = u[3] - x[E.B_R]
        c, s = math.cos(x[E.PSI]), math.sin(x[E.PSI])
        F = np.eye(NE)
        F[E.VX, E.VY], F[E.VX, E.B_AX], F[E.VX, E.B_R] = h * r, -h, -h * x[E.VY]
        gain = self._lateral(u[2] - x[E.B_AY])[1]
        F[E.VY, E.VX], F[E.VY, E.B_AY], F[E.VY, E.B_R] = -h * r, -h * gain, h * x[E.VX]
        F[E.PSI, E.B_R] = -h
        F[E.X, E.VX], F[E.X, E.VY], F[E.X, E.PSI] = h * c, -h * s, -h * (x[E.VX] * s + x[E.VY] * c)
        F[E.Y, E.VX], F[E.Y, E.VY], F[E.Y, E.PSI] = h * s, h * c, h * (x[E.VX] * c - x[E.VY] * s)
        # IMU noise drives the states its biases drive, not the biases themselves
        G = F[:, [E.B_AX, E.B_AY, E.B_R]].copy()
        G[E.B_AX:E.B_R + 1] = 0.0
        q = np.diag([p.accel_std ** 2, p.accel_std ** 2, p.gyro_std ** 2])
        Q, Q_act = G @ q @ G.T, G @ self._q_act @ G.T
        for M, accel_walk in ((Q, p.accel_bias_walk),
                              (Q_act, p.accel_bias_walk_noise or p.accel_bias_walk)):
            M[E.B_AX, E.B_AX] += accel_walk ** 2 * h
            M[E.B_AY, E.B_AY] += accel_walk ** 2 * h
            M[E.B_R, E.B_R] += p.gyro_bias_walk ** 2 * h
            M[E.S_F, E.S_F] += p.front_radius_walk ** 2 * h
        self.x = self._f(x, u, h)
        self.P = F @ self.P @ F.T + Q
        for hyp in self._steps:
            if hyp.s is not None:
                hyp.s = F @ hyp.s
        P_act = self.P_act
        A = np.zeros(P_act.shape)   # the actual error's transition
        A[:NE, :NE] = F
        if self._slow:   # the slow errors decay as first-order Gauss-Markov processes
            phi = np.exp(-h / self._slow_tau)
            A[NE:, NE:] = np.diag(phi)
            P_act[:NE, NE:] = F @ P_act[:NE, NE:] * phi
            P_act[NE:, :NE] = P_act[:NE, NE:].T
            P_act[NE:, NE:] *= np.outer(phi, phi)
            P_act[NE:, NE:] += np.diag(self._slow_var * (1.0 - phi * phi))
        P_act[:NE, :NE] = F @ P_act[:NE, :NE] @ F.T + Q_act
        self._pairs.transition(A)

    def _predict_to(self, t: float) -> None:
        """Advance the EKF to ``t`` on the IMU samples in between (linear between them)."""
        samples = list(self._imu)
        for sample in samples:
            if self.t + 1e-9 < sample[0] <= t + 1e-9:
                self._propagate(sample[0] - self.t, self._input(self.t, sample[0], self._u, sample))
                self.t, self._u = sample[0], sample
                for hyp in self._steps:
                    if hyp.s is None and abs(hyp.onset - sample[0]) < 1e-9:
                        hyp.start()
        following = next((s for s in samples if s[0] > self.t + 1e-9), None)
        self._propagate(t - self.t, self._input(self.t, t, self._u, following))
        self.t = max(self.t, t)

    def _scalar_update(self, name: str, z: float, h: float, H: np.ndarray, R: float,
                       wrap: bool = False, R_test: float | None = None,
                       R_noise: float | None = None) -> str:
        """One scalar EKF update weighted by ``R``; returns the monitor's verdict.

        The fault test judges the innovation on ``R_test`` (the sensor's noise with its slow
        errors; default ``R``) and the filter's ``P``: conservative, for few false alarms. The
        NIS is the innovation's consistency: on the sensor's white noise ``R_noise`` (default
        ``R_test``) and the covariance the filter actually has, ``P_act`` -- its ``P``
        overstates its error where the weights trust the IMU more than the sensor's noise does.
        """
        mon = self.monitors[name]
        nu = z - h
        if wrap:
            nu = math.remainder(nu, 2.0 * math.pi)
        R_test = R if R_test is None else R_test
        R_noise = R_test if R_noise is None else R_noise
        H_act = np.zeros(len(self.P_act))   # the slow error, if the channel has one, is in z
        H_act[:NE] = H
        if name in self._slow:
            H_act[self._slow[name]] = 1.0
        PH, PH_act = self.P @ H, self.P_act @ H_act
        HPH = float(H @ PH)
        S, S_test, S_act = HPH + R, HPH + R_test, float(H_act @ PH_act) + R_noise
        steps = [hyp for hyp in self._steps if hyp.s is not None]
        for hyp in steps:
            hyp.evidence(nu, H, S_act * mon.noise_scale_act)
        pair = self._pairs.index.get(name)
        if pair is not None:   # Var(NIS) = 2, Cov(NIS_i, NIS_j) = 2 Cov(nu_i, nu_j)^2 / S_i S_j
            mon.nis_var += 2.0 + 4.0 * self._pairs.past(pair, H_act) / S_act
        verdict = mon.judge(nu * nu / S_test, nu / math.sqrt(S_test), self.t, nu * nu / S_act)
        if verdict in ('reject', 'jump'):
            if verdict == 'jump':
                self._event(name, 'jump')
            if pair is not None:   # not used: its covariance with the error is P_act H'
                self._pairs.add(pair, PH_act, S_act)
            self._decide_steps()
            return verdict
        pose = name in ('ins.x', 'ins.y', 'ins.yaw')   # a GNSS error is slow: no bias test
        if verdict == 'step' or (verdict == 'bias' and not pose):
            self._blame(name, verdict)
            PH, PH_act = self.P @ H, self.P_act @ H_act
            S, S_act = float(H @ PH) + R, float(H_act @ PH_act) + R_noise
        K = PH / S
        self.x = self.x + K * nu
        self.P = self.P - np.outer(K, PH)
        self.P = 0.5 * (self.P + self.P.T)
        # (I - K H) P_act (I - K H)' + K R_noise K': the filter's gain on the actual covariance
        # (K is zero on the slow errors: they are the sensor's, no update moves them)
        K_act = np.zeros(len(self.P_act))
        K_act[:NE] = K
        KPH = np.outer(K_act, PH_act)
        self.P_act = self.P_act - KPH - KPH.T + S_act * np.outer(K_act, K_act)
        self._pairs.update(K_act, H_act)
        if pair is not None:   # this innovation's covariance with the error: Cov(e+, nu)
            self._pairs.add(pair, PH_act - K_act * S_act, S_act)
        for hyp in steps:   # the update corrects part of the error a step would have left
            hyp.s = hyp.s - K * float(H @ hyp.s)
        self._decide_steps()
        return verdict

    def _open_steps(self, s: SensorSample) -> None:
        """An accelerometer sample ``accel_jump`` or more from the one before opens a bias-step
        hypothesis (the car rarely moves its acceleration that far in 10 ms; a step does it at
        once)."""
        if not self.p.accel_jump or not self._imu or self.x is None:
            return
        last = self._imu[-1]
        if not 0.0 < s.stamp - last[0] <= 0.02 + 1e-9:   # next sample, or one lost between
            return
        for index, new, old in ((E.B_AX, s.values[0], last[1]), (E.B_AY, s.values[1], last[2])):
            if abs(new - old) >= self.p.accel_jump:
                self._steps.append(_StepHypothesis(index, s.stamp, new - old))

    def _decide_steps(self) -> None:
        """Accept a bias-step hypothesis whose evidence is enough (the state corrected by the
        error its signature says it left), dismiss one the innovations contradict or that stays
        undecided past ``step_span``."""
        p, keep = self.p, []
        for hyp in self._steps:
            if hyp.s is not None and hyp.llr >= p.step_accept:
                self._accept_step(hyp)
                return   # the others were tested on the errors this one explains
            if hyp.llr > -p.step_dismiss and self.t - hyp.onset < p.step_span:
                keep.append(hyp)
        self._steps = keep

    def _accept_step(self, hyp: _StepHypothesis) -> None:
        """The accelerometer offset stepped: take the error it left out of the state, and give
        the offset the uncertainty of a measured jump (the sample's noise, twice)."""
        self.x = self.x - hyp.delta * hyp.s
        var = 2.0 * (self.p.accel_noise_std or self.p.accel_std) ** 2
        for P in (self.P, self.P_act):
            P[hyp.index, :] = 0.0
            P[:, hyp.index] = 0.0
            P[hyp.index, hyp.index] = var
        for name in ('ins.V', 'ins.beta', 'wheels.front_speed'):   # their windows hold it
            self.monitors[name].window.clear()
        self._steps = []
        self._name_once('imu.ax/ay', 'bias step')

    def _blame(self, name: str, verdict: str) -> None:
        """A persistent or biased innovation: the IMU bias behind it changed (a step), or, for
        the pose, the GNSS solution jumped; that part's uncertainty is reset."""
        p = self.p
        if name == 'ins.r':
            idx, channel, var = [E.B_R], 'imu.r', p.gyro_bias_std0 ** 2
        elif name in ('ins.V', 'ins.beta', 'wheels.front_speed'):
            idx, channel, var = [E.B_AX, E.B_AY], 'imu.ax/ay', p.accel_bias_std0 ** 2
        else:
            idx, channel, var = [E[name.split('.')[1].upper().replace('YAW', 'PSI')]], name, 1.0
        if name == 'ins.r':
            self.yaw_rate.x = None   # it filtered the old bias's correction: starts again
        span = self.monitors[name].span
        for P in (self.P, self.P_act):
            for i in idx:
                P[i, :] = 0.0
                P[:, i] = 0.0
                P[i, i] = var
            if channel == 'imu.ax/ay':   # the velocity integrated the step until it was seen
                for i in (E.VX, E.VY):
                    P[i, i] += var * span * span
        self._name_once(channel,
                        'bias step' if channel.startswith('imu') else f'{verdict} accepted')

    def _name_once(self, channel: str, reason: str) -> None:
        """One fault, one name: not once per window or test."""
        if not any(e.channel == channel and e.reason == reason and self._now - e.t < 1.0
                   for e in self.events[-8:]):
            self._event(channel, reason)

    def _ins_update(self, s: SensorSample) -> None:
        std = self.p.ins_std
        aided = False
        for name, z in zip(FIELDS['ins'], s.values):
            if self._frozen_check(f'ins.{name}', z, s.stamp):
                continue
            H = np.zeros(NE)
            x = self.x
            vx, vy = x[E.VX], x[E.VY]
            V2 = max(vx * vx + vy * vy, 1e-2)
            if name == 'V':
                V = math.sqrt(V2)
                H[E.VX], H[E.VY] = vx / V, vy / V
                h, wrap = V, False
            elif name == 'beta':
                H[E.VX], H[E.VY] = -vy / V2, vx / V2
                h, wrap = math.atan2(vy, vx), True
            elif name == 'r':
                u = self._imu_at(s.stamp)
                H[E.B_R] = -1.0
                h, wrap = u[3] - x[E.B_R], False
            else:
                i = {'x': E.X, 'y': E.Y, 'yaw': E.PSI}[name]
                H[i] = 1.0
                h, wrap = x[i], name == 'yaw'
            gyro = self.p.gyro_std ** 2 if name == 'r' else 0.0   # the IMU's r is in h
            noise = self.p.ins_noise_std or self.p.ins_test_std
            verdict = self._scalar_update(
                f'ins.{name}', z, h, H, std[name] ** 2 + gyro, wrap,
                self.p.ins_test_std[name] ** 2 + gyro,
                noise[name] ** 2 + (self._q_act[2, 2] if name == 'r' else 0.0))
            aided |= name in ('V', 'beta') and verdict not in ('reject', 'jump')
        if aided:
            self._last_aided = s.stamp

    def _front_wheel_update(self, s: SensorSample) -> None:
        """The front wheels' mean rim speed: the front axle's speed along the wheel (rolling),
        scaled by the error of the rolling radius the car's data gives (``E.S_F``: 0.3 % is
        3 cm/s at 10 m/s, a bias the INS speed would otherwise fight; learnt while the INS aids,
        kept through a dropout)."""
        healthy = [i for i in (0, 1) if self.monitors[f'wheels.{FIELDS["wheels"][i]}'].excluded
                   is None]
        if len(healthy) < 2:
            return   # one front wheel alone misses the yaw term of the track: not used
        omega = 0.5 * (s.values[0] + s.values[1])
        delta = self._steer_at(s.stamp)
        u = self._imu_at(s.stamp)
        x, a = self.x, self.vehicle.a
        r = u[3] - x[E.B_R]
        c, sn = math.cos(delta), math.sin(delta)
        along = x[E.VX] * c + (x[E.VY] + a * r) * sn
        scale = 1.0 + x[E.S_F]
        h = along * scale
        H = np.zeros(NE)
        H[E.VX], H[E.VY], H[E.B_R], H[E.S_F] = c * scale, sn * scale, -a * sn * scale, along
        self._scalar_update('wheels.front_speed', omega * self.vehicle.R_F, h, H,
                            self.p.front_wheel_std ** 2,
                            R_noise=self.p.front_wheel_noise_std ** 2 or None)

    def _steer_at(self, t: float) -> float:
        best = self._steer[0][1] if self._steer else 0.0
        for stamp, delta in self._steer:
            if stamp <= t + 1e-9:
                best = delta
        return best

    # --- wheels, steering, torque -----------------------------------------------------------

    def _wheel_sample(self, s: SensorSample) -> None:
        p = self.p
        for i, (name, z) in enumerate(zip(FIELDS['wheels'], s.values)):
            key = f'wheels.{name}'
            mon, filt = self.monitors[key], self.wheels[i]
            if filt.x is not None and abs(z) < 0.5 * p.stuck_min_speed \
                    and abs(filt.at(s.stamp)) > p.stuck_min_speed:
                self._stuck[i] += 1
                if self._stuck[i] >= p.stuck_samples and mon.excluded is None:
                    mon.excluded = 'stuck at zero'
                    self._event(key, 'stuck at zero')
                continue   # a reading of zero under a moving car never reaches the filter
            self._stuck[i] = 0
            if mon.excluded == 'stuck at zero':
                mon.excluded = None
                filt.reset(s.stamp, z)
                continue
            # a wheel at rest repeats its zero: frozen is judged on a turning wheel only
            if abs(z) >= 0.5 * p.stuck_min_speed and self._frozen_check(key, z, s.stamp):
                continue
            if mon.excluded == 'frozen':   # it stopped turning: no longer judged frozen
                mon.excluded = None
            self._scalar(filt, key, s.stamp, z)

    def _scalar(self, filt: _RateFilter, name: str, stamp: float, z: float) -> bool:
        """Test one sample against its channel's filter, then update (or re-initialise);
        True when the sample was taken."""
        if filt.x is None:
            filt.update(stamp, z)
            return True
        nu, S = filt.innovation(stamp, z)
        verdict = self.monitors[name].judge(nu * nu / S, nu / math.sqrt(S), stamp)
        if verdict == 'jump':
            self._event(name, 'jump')
        if verdict == 'step':
            self._event(name, 'step accepted')
            filt.reset(stamp, z)
        elif verdict not in ('reject', 'jump'):
            filt.update(stamp, z)
        return verdict not in ('reject', 'jump')

    def _frozen_check(self, name: str, z: float, stamp: float) -> bool:
        """True while ``name`` is frozen (left out); names the fault once, clears on change."""
        mon = self.monitors[name]
        frozen = mon.frozen(z, stamp)
        if frozen and mon.excluded is None:
            mon.excluded = 'frozen'
            self._event(name, 'frozen')
        elif not frozen and mon.excluded == 'frozen':
            mon.excluded = None
        return frozen

    def _check_silence(self, now: float) -> None:
        """Name a unit that stopped sending (a GNSS/INS dropout), and its return."""
        for unit, last in self._arrived.items():
            silent = now - last > self.p.timeout
            if silent and unit not in self._silent:
                self._silent.add(unit)
                self._event(unit, 'dropout')
            elif not silent and unit in self._silent:
                self._silent.discard(unit)
                self._event(unit, 'back')

    def _event(self, channel: str, reason: str) -> None:
        self.events.append(FaultEvent(self._now, channel, reason))

    # --- output -------------------------------------------------------------------------------

    def _output(self, now: float) -> VehicleState:
        """The EKF carried from its horizon to ``now`` on the newer IMU samples (no covariance)."""
        x, u, t = self.x.copy(), self._u, self.t
        for sample in self._imu:
            if t + 1e-9 < sample[0] <= now + 1e-9:
                x = self._f(x, self._input(t, sample[0], u, sample), sample[0] - t)
                t, u = sample[0], sample
        x = self._f(x, u, max(0.0, now - t))
        vx, vy = x[E.VX], x[E.VY]
        ax, ay = u[1] - x[E.B_AX], self._lateral(u[2] - x[E.B_AY])[0]
        wheels = [f.at(now) if f.x is not None else 0.0 for f in self.wheels]
        for i, j in ((0, 1), (1, 0), (2, 3), (3, 2)):   # a faulty wheel: its axle partner's
            if self.monitors[f'wheels.{FIELDS["wheels"][i]}'].excluded is not None:
                wheels[i] = wheels[j]
        validity = Validity.ALL
        if now - self._last_aided > self.p.max_coast:
            validity &= ~(Validity.V | Validity.BETA | Validity.VX_VY)
        # a unit that has not sent yet (a slower one at the start) has no value to give
        if any(f.x is None for f in self.wheels):
            validity &= ~Validity.WHEEL_SPEEDS
        if self.steering.x is None:
            validity &= ~(Validity.DELTA | Validity.STEERING_TORQUE)
        if self.torque.x is None:
            validity &= ~Validity.DRIVE_TORQUE
        return VehicleState(
            stamp=now, V=math.hypot(vx, vy), beta=math.atan2(vy, vx),
            r=self.yaw_rate.at(now) if self.yaw_rate.x is not None else u[3] - x[E.B_R],
            vx=vx, vy=vy, ax=ax, ay=ay, wheel_speeds=tuple(wheels),
            delta=self.steering.at(now) if self.steering.x is not None else 0.0,
            steering_torque=self._steering_torque,
            drive_torque=self.torque.at(now) if self.torque.x is not None else 0.0,
            x=x[E.X], y=x[E.Y], yaw=math.remainder(x[E.PSI], 2.0 * math.pi),
            validity=int(validity))

    # --- consistency ---------------------------------------------------------------------------

    def clear_records(self) -> None:
        """Forget the NIS and step-time records: they grow with every sample (a node reports
        and clears them once a second)."""
        self.step_times.clear()
        self._pairs.clear()
        for mon in self.monitors.values():
            mon.nis.clear()
            mon.nis_var = 0.0

    def nis_summary(self, intervals: bool = True) -> dict[str, dict]:
        """Per channel: samples, mean NIS, the share within the 95 % chi^2(1) bound, and (with
        ``intervals``) the 95 % interval of the mean of a consistent filter's NIS for that many
        samples, counted as ``n_eff`` independent ones (successive innovations are correlated).

        For the EKF's aiding channels ``n_eff`` comes from the covariances of the channel's
        innovations with each other that the actual covariance implies (``interval_from``
        'model': the INS's slow errors correlate them over seconds, which one run's own series
        cannot show); for the others from the series' autocorrelation ('samples', ~60 us a
        channel, which a node's periodic status need not pay)."""
        out = {}
        for name, mon in self.monitors.items():
            if mon.nis:
                nis = np.asarray(mon.nis)
                out[name] = {'n': int(nis.size), 'mean': float(nis.mean()),
                             'within_95': float(np.mean(nis <= CHI2_1_95))}
                if intervals:
                    if mon.nis_var > 0.0:
                        n_eff, source = 2.0 * nis.size ** 2 / mon.nis_var, 'model'
                    else:
                        n_eff, source = effective_samples(nis), 'samples'
                    out[name].update(n_eff=n_eff, interval_95=mean_nis_interval(n_eff),
                                     interval_from=source)
        return out


CHI2_1_95 = 3.841   # 95 % quantile of chi^2 with one degree of freedom


def effective_samples(series) -> float:
    """How many independent samples the mean of ``series`` is worth: ``n / tau``, with the
    integrated autocorrelation ``tau`` summed over Geyer's initial positive sequence (pairs of
    autocorrelations, up to the first pair that is not positive)."""
    x = np.asarray(series, dtype=float)
    n = x.size
    x = x - x.mean()
    var = float(x @ x)
    if n < 4 or var <= 0.0:
        return float(n)
    f = np.fft.rfft(x, 2 * n)
    rho = np.fft.irfft(f * np.conj(f))[:n] / var
    tau = -1.0
    for k in range(0, n - 1, 2):
        pair = rho[k] + rho[k + 1]
        if pair <= 0.0:
            break
        tau += 2.0 * pair
    return float(n / max(tau, 1.0))


def mean_nis_interval(n_eff: float, dof: int = 1) -> tuple[float, float]:
    """95 % interval of the mean NIS of a consistent filter (``dof`` per sample) over
    ``n_eff`` independent samples: chi^2(n_eff dof) / n_eff, by Wilson and Hilferty's cube-root
    approximation (within 0.1 % from 30 degrees of freedom)."""
    k = n_eff * dof
    c = 2.0 / (9.0 * k)
    return tuple(float(dof * (1.0 - c + z * math.sqrt(c)) ** 3) for z in (-1.959964, 1.959964))


class LatestSamples:
    """No estimator: the newest sample of each unit as the state (what (b) of the issue's
    comparison feeds the controller), stamped at arrival."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.latest: dict[str, SensorSample] = {}
        self.torque_samples: list[tuple[float, float]] = []   # the last step's (stamp, Nm)

    def step(self, samples, now: float) -> VehicleState | None:
        for s in samples:
            self.latest[s.unit] = s
        self.torque_samples = [(s.stamp, s.values[0]) for s in samples if s.unit == 'torque']
        if not {'ins', 'imu', 'wheels', 'steering', 'torque'} <= self.latest.keys():
            return None
        V, beta, r, X, Y, yaw = self.latest['ins'].values
        ax, ay, _ = self.latest['imu'].values
        delta, steering_torque = self.latest['steering'].values
        return VehicleState(
            stamp=now, V=V, beta=beta, r=r, vx=V * math.cos(beta), vy=V * math.sin(beta),
            ax=ax, ay=ay, wheel_speeds=tuple(self.latest['wheels'].values), delta=delta,
            steering_torque=steering_torque, drive_torque=self.latest['torque'].values[0],
            x=X, y=Y, yaw=yaw)


ESTIMATORS = ('ekf', 'none')


def build_estimator(kind: str, vehicle: VehicleParams, params_file, overrides=(),
                    intervals: bool = True):
    """``'ekf'``: the ``Estimator``; ``'none'``: ``LatestSamples`` (the newest sample of each
    unit). ``params_file``: ``config/estimator.yaml``, read for the EKF only."""
    require(kind in ESTIMATORS, 'estimator', f'{kind!r} is not one of {list(ESTIMATORS)}')
    if kind == 'none':
        return LatestSamples()
    return Estimator(vehicle, load_estimator_params(params_file, overrides), intervals)


ABSURD_SPEED, ABSURD_RATE = 1e3, 1e2   # [m/s], [rad/s]: no car; the filter integrated garbage


class FrameStepper:
    """An estimator fed frame by frame as they arrive over a network: one step per frame of
    samples that arrived together. A frame offered again (the same arrival time: a simulator
    waiting for its controller repeats its first one) gets the same state without a step; a
    clock that steps back (a restarted simulator) starts the estimator over, and so does a
    step that fails or leaves a non-finite or absurd state (absurd samples the IMU integrates:
    the filter would never recover), named in ``failure``."""

    def __init__(self, estimator):
        self.estimator = estimator
        self.last_now = -math.inf
        self.state: VehicleState | None = None
        self.restarts = 0
        self.failure = ''   # why it last started over, '' if it never did for a failure

    def step(self, samples, now: float) -> VehicleState | None:
        """The state at ``now`` [s] after ``samples``; None until the estimator has one."""
        if now == self.last_now:
            return self.state
        if now < self.last_now:
            self._restart('')
        self.last_now = now
        try:
            state = self.estimator.step(samples, now)
        except (ValueError, ArithmeticError) as err:
            return self._restart(f'{type(err).__name__}: {err} at t = {now:.3f} s')
        if state is not None and not all(math.isfinite(v) for v in (
                state.V, state.beta, state.r, state.x, state.y, state.yaw)):
            return self._restart(f'non-finite state at t = {now:.3f} s')
        if state is not None and not (abs(state.V) < ABSURD_SPEED and abs(state.r) < ABSURD_RATE):
            return self._restart(f'absurd state (V {state.V:.3g} m/s, r {state.r:.3g} rad/s) '
                                 f'at t = {now:.3f} s')
        self.state = state or self.state
        return self.state

    def _restart(self, failure: str) -> None:
        self.estimator.reset()
        self.restarts += 1
        self.state = None
        if failure:
            self.failure = failure


__all__ = ['CHI2_1_95', 'E', 'ESTIMATORS', 'Estimator', 'EstimatorParams', 'FIELDS', 'FaultEvent',
           'FrameStepper', 'LatestSamples', 'SensorSample', 'build_estimator',
           'effective_samples', 'load_estimator_params', 'mean_nis_interval']
