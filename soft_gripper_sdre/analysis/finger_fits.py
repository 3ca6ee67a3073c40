"""Each finger's own linear model, with the lag of its actuator, fitted to its recordings: the
plants the derivation checks its candidate settings on beside the learned model.

The learned model is one model for every finger of the gripper, in the SDC form
ẋ = A(x)x + G(x)u on the tip's state x = [p; v] alone. An actuator that delivers its command
late has a state of its own the form has no room for: a pneumatic chamber fills through its valve
and tubing, ȧ = (u − a)/τ, with τ of tens of milliseconds. Trained on such a finger, the model
absorbs the lag as slowness and damping (``pneumatic1``: modes of 2.6 Hz, ζ 0.26, where the
fingers have 4.1 and 3.4 Hz, ζ 0.16 and 0.12), and settings that track within 1 % on the model
ring on the fingers (docs/own_gripper.md).

Per finger, :func:`fit_finger` fits

    p̈ = K [p; v] + B w + c,     ẇ = (u − w)/τ     (τ = 0: w = u)

by least squares on the finger's own KF + RTS acceleration labels, with w the recorded commands
passed through the lag, for each τ in :data:`LAGS`, and keeps the τ whose fit runs free closest
to the finger's validation recordings (windows of :data:`WINDOW`, as the model's verdict runs
them). On ``pneumatic1`` the lag found is 50 and 80 ms (the fingers' valves: 40 and 60 ms), and
the fitted modes are those of the fingers; on the fingers with torque inputs no lag runs free
closer than none. A fit is used only when its free run stays finite and within
:data:`~soft_gripper_sdre.analysis.model_fitness.FREE_RUN_LIMIT` of the validation motion, the
bar the learned model meets to be fit to control.

:meth:`LinearFinger.plant` puts the fit behind the check's plant interface (``tip()``,
``step(u, dt)``) in the model's frame, held at its equilibrium under the inputs' rest value
when the check starts, and steps it exactly (zero-order hold on the command).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.linalg import expm
from scipy.signal import butter, filtfilt, lfilter

from soft_gripper_sdre.analysis import model_fitness
from soft_gripper_sdre.analysis.model_fitness import FREE_RUN_LIMIT
from soft_gripper_sdre.sim.shape import INPUT_GAIN_RANGE

#: the actuator lags tried [s]
LAGS = (0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.12)
#: the free runs that pick the lag are this long [s] (as the model's verdict runs them)
WINDOW = 1.0
#: a finger's input gain is read from its recordings below this frequency [Hz], where inertia and
#: damping are small against the spring (under 2 % of it below first modes of 2 Hz and more)
STATIC_HZ = 0.25


def finger_of(sample) -> str:
    """The finger a :class:`~soft_gripper_sdre.analysis.bag_dataset.FingerSamples` belongs to
    (its name is ``<bag>/<finger>#<stretch>``)."""
    name = sample.name.rsplit('/', 1)[-1]
    return name.split('#', 1)[0]


@dataclass(frozen=True)
class LinearFinger:
    """p̈ = K [p; v] + B w + c with ẇ = (u − w)/lag (module doc), in the recordings' frame
    (p from the finger's rest tip) and SI units."""

    name: str
    K: np.ndarray               # (d, 2d) [1/s², 1/s]
    B: np.ndarray               # (d, m) [m/s² per unit of input]
    c: np.ndarray               # (d,) [m/s²]
    lag: float                  # [s]; 0: the input acts at once
    free_run: float             # the validation free run's error / the motion's spread [-]
    windows: int                # validation windows that free run was scored on

    @property
    def d(self) -> int:
        return self.K.shape[0]

    @property
    def m(self) -> int:
        return self.B.shape[1]

    def discrete(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(Ad, Bd): z ← Ad z + Bd u over ``dt`` [s] with u held, z = [p; v; w; 1] (the lag's
        state w only when ``lag`` > 0)."""
        d, m = self.d, self.m
        lagged = self.lag > 0
        nz = 2 * d + (m if lagged else 0) + 1
        F = np.zeros((nz + m, nz + m))
        F[:d, d:2 * d] = np.eye(d)
        F[d:2 * d, :2 * d] = self.K
        F[d:2 * d, nz - 1] = self.c
        if lagged:
            F[d:2 * d, 2 * d:2 * d + m] = self.B
            F[2 * d:2 * d + m, 2 * d:2 * d + m] = -np.eye(m) / self.lag
            F[2 * d:2 * d + m, nz:] = np.eye(m) / self.lag
        else:
            F[d:2 * d, nz:] = self.B
        E = expm(F * dt)
        return E[:nz, :nz], E[:nz, nz:]

    def equilibrium(self, u: np.ndarray) -> np.ndarray:
        """(d,) the position [m] the fit holds still at under the constant input ``u`` (m,)."""
        return np.linalg.solve(self.K[:, :self.d], -(self.B @ np.asarray(u, dtype=float)
                                                     + self.c))

    def plant(self, rest_tip: np.ndarray, rest_input: np.ndarray,
              input_gain: float = 1.0) -> LinearFingerPlant:
        """The fit as the check's plant (:func:`~soft_gripper_sdre.analysis.loop_settings.
        check_on_model`'s ``plant``): at its equilibrium under ``rest_input`` (m,), its tip
        ``rest_tip`` (d,) [m] of the model's frame; a command v of the law in the model's units
        reaches it as v / ``input_gain`` (the finger's :func:`input_gains`)."""
        return LinearFingerPlant(self, rest_tip, rest_input, input_gain)

    @property
    def modes_hz(self) -> list[float]:
        """The natural frequencies [Hz] of the fit's oscillating modes, ascending."""
        modes = np.linalg.eigvals(np.block([[np.zeros((self.d, self.d)), np.eye(self.d)],
                                            [self.K]]))
        return sorted(float(abs(v) / (2 * math.pi)) for v in modes[modes.imag > 0])

    def summary(self) -> dict:
        return {'finger': self.name, 'lag_s': self.lag, 'free_run': self.free_run,
                'windows': self.windows, 'modes_hz': self.modes_hz}


class LinearFingerPlant:
    """A :class:`LinearFinger` stepped exactly over each held command, divided by
    ``input_gain``; ``tip()`` (d,) [m] is ``rest_tip`` plus the displacement from the equilibrium
    it starts at."""

    def __init__(self, fit: LinearFinger, rest_tip: np.ndarray, rest_input: np.ndarray,
                 input_gain: float = 1.0) -> None:
        d, m = fit.d, fit.m
        if not (math.isfinite(input_gain) and input_gain > 0):
            raise ValueError(f'input_gain must be finite and > 0, got {input_gain!r}')
        self.fit, self.gain = fit, float(input_gain)
        self.rest_tip = np.asarray(rest_tip, dtype=float)[:d]
        rest_input = np.asarray(rest_input, dtype=float).reshape(m)
        self.origin = fit.equilibrium(rest_input)
        self.z = np.concatenate([self.origin, np.zeros(d),
                                 rest_input if fit.lag > 0 else [], [1.0]])
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def tip(self) -> np.ndarray:
        return self.rest_tip + self.z[:self.fit.d] - self.origin

    def matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(A_d, B_d): the exact step z ← A_d z + B_d u over ``dt`` [s] (u before the input gain;
        computed once per ``dt``)."""
        if dt not in self._cache:
            self._cache[dt] = self.fit.discrete(dt)
        return self._cache[dt]

    def step(self, u: np.ndarray, dt: float) -> None:
        """Hold ``u`` (1, m) or (m,) over ``dt`` [s]."""
        Ad, Bd = self.matrices(dt)
        u = np.asarray(u, dtype=float).reshape(-1)
        self.z = Ad @ self.z + Bd @ (u / self.gain if self.gain != 1.0 else u)


def _lagged(t: np.ndarray, u: np.ndarray, lag: float) -> np.ndarray:
    """The commands ``u`` (N, m), held between the samples ``t`` (N,) [s], through the lag: the
    delivered input at each sample, starting at the first command."""
    if lag <= 0:
        return u
    u = np.asarray(u, dtype=float)
    step = np.diff(t)
    if len(step) and np.allclose(step, step[0], rtol=1e-6, atol=0.0):
        # one period T: w[k] = a w[k−1] + (1 − a) u[k−1] from w[0] = u[0], a = exp(−T/τ)
        a = math.exp(-step[0] / lag)
        return u[0] + lfilter([0.0, 1.0 - a], [1.0, -a], u - u[0], axis=0)
    w = np.array(u)
    keep = np.exp(-step / lag)
    for k in range(1, len(t)):
        w[k] = keep[k - 1] * w[k - 1] + (1 - keep[k - 1]) * u[k - 1]
    return w


def _least_squares(samples, lag: float, d: int) -> tuple[np.ndarray, ...]:
    """(K, B, c) of the labels of ``samples`` with the commands through ``lag``."""
    rows = [np.column_stack([s.x, _lagged(s.t, s.u, lag), np.ones(len(s.t))]) for s in samples]
    theta, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate([s.acc for s in samples]),
                                rcond=None)
    theta = theta.T
    return theta[:, :2 * d], theta[:, 2 * d:-1], theta[:, -1]


def _free_run(fit: LinearFinger, samples) -> tuple[float, int]:
    """(error / spread, windows) of ``fit`` run free over :data:`WINDOW` windows of ``samples``,
    each window from the recorded state and the delivered input the lag gives there; inf when a
    window leaves the finite numbers or nothing is long enough."""
    d = fit.d
    errors, spread_pos, n_windows = [], [], 0
    for s in samples:
        dt = float(np.median(np.diff(s.t)))
        n = max(int(round(WINDOW / dt)), 1)
        starts = list(range(0, len(s.t) - n, n))
        spread_pos.append(s.x[:, :d])
        if not starts:
            continue
        Ad, Bd = fit.discrete(dt)
        w = _lagged(s.t, s.u, fit.lag)
        z = np.column_stack([s.x[starts], w[starts] if fit.lag > 0 else np.zeros((len(starts), 0)),
                             np.ones(len(starts))])
        for j in range(n):
            z = z @ Ad.T + s.u[[i + j for i in starts]] @ Bd.T
            errors.append(z[:, :d] - s.x[[i + j + 1 for i in starts], :d])
        n_windows += len(starts)
    if not errors:
        return math.inf, 0
    err = np.concatenate(errors)
    if not np.all(np.isfinite(err)):
        return math.inf, n_windows
    pos = np.concatenate(spread_pos)
    spread = float(np.sqrt(np.mean(np.sum((pos - pos.mean(axis=0)) ** 2, axis=1))))
    rmse = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    return (rmse / spread if spread > 0 else math.inf), n_windows


def fit_finger(name: str, train, val, lags: tuple[float, ...] = LAGS) -> LinearFinger | None:
    """``name``'s :class:`LinearFinger` from its training samples ``train`` and validation
    samples ``val`` (:class:`~soft_gripper_sdre.analysis.bag_dataset.FingerSamples`); None when
    no lag gives a fit whose free run stays within
    :data:`~soft_gripper_sdre.analysis.model_fitness.FREE_RUN_LIMIT`."""
    if not train or not val:
        return None
    d = train[0].acc.shape[1]
    best = None
    for lag in lags:
        K, B, c = _least_squares(train, lag, d)
        fit = LinearFinger(name, K, B, c, float(lag), math.inf, 0)
        if abs(np.linalg.det(K[:, :d])) < 1e-300:
            continue                                    # no equilibrium to start the check at
        error, windows = _free_run(fit, val)
        if best is None or error < best.free_run:
            best = LinearFinger(name, K, B, c, float(lag), error, windows)
    return best if best is not None and best.free_run <= FREE_RUN_LIMIT else None


def fit_fingers(train, val, lags: tuple[float, ...] = LAGS
                ) -> tuple[list[LinearFinger], list[str]]:
    """Every finger's fit (:func:`fit_finger`), in the order the fingers first appear in
    ``train``, and the names of the fingers no fit passed for."""
    return _each_finger(train, lambda name: fit_finger(
        name, _of(train, name), _of(val, name), lags))


def _of(samples, name: str) -> list:
    """The samples of finger ``name``."""
    return [s for s in samples if finger_of(s) == name]


def _each_finger(samples, read) -> tuple[list, list[str]]:
    """``read(name)`` for every finger of ``samples`` in the order they first appear: what it
    returned, and the names it returned None for."""
    found, missing = [], []
    for name in dict.fromkeys(finger_of(s) for s in samples):
        got = read(name)
        (found.append(got) if got is not None else missing.append(name))
    return found, missing


# -- each finger's input gain against the shared model ---------------------------------------

@dataclass(frozen=True)
class InputGain:
    """How much more strongly a finger's inputs act than the shared model's: G₂ᶠ(x) ≈ g G₂(x).
    ``gain`` is ``raw`` clipped into :data:`~soft_gripper_sdre.sim.shape.INPUT_GAIN_RANGE`."""

    name: str
    gain: float
    raw: float
    seconds: float              # of recordings it was read from [s]

    @property
    def clipped(self) -> bool:
        return self.gain != self.raw

    def summary(self) -> dict:
        return {'finger': self.name, 'gain': self.gain, 'raw': self.raw, 'seconds': self.seconds,
                'clipped': self.clipped}


def input_gain(model, name: str, samples) -> InputGain | None:
    """``name``'s input gain against ``model`` from its samples (train and validation alike:
    :class:`~soft_gripper_sdre.analysis.bag_dataset.FingerSamples`), None when none is long
    enough (1 / :data:`STATIC_HZ`) or its inputs did not move it. A ratio outside
    :data:`~soft_gripper_sdre.sim.shape.INPUT_GAIN_RANGE` (at or below zero too: a finger that
    moves against the model's input map) is clipped into it, and :attr:`InputGain.clipped`.

    The model is shared by fingers that differ (one lighter and softer, one stiffer), and the
    difference that leaves an offset under a model-inversion feedforward is the static one: the
    input that holds the finger at a displacement. Below :data:`STATIC_HZ` the recordings are
    that balance, p̈ − (A(x)x)₂ = g G₂(x)u with the finger's inertia negligible, so g is the
    least-squares ratio of the two sides, each low-passed (zero phase) over every sample:
    g = Σ⟨a − f, h⟩ / Σ⟨h, h⟩ with a the labels, f = (A(x)x)₂ and h = G₂(x)u at the recorded
    states and inputs. A sample's few left-out periods (a dropped tip) are far shorter than the
    filter's time scale and are filtered over."""
    num = den = seconds = 0.0
    for s in samples:
        dt = float(np.median(np.diff(s.t))) if len(s.t) > 1 else 0.0
        if not (dt > 0 and s.t[-1] - s.t[0] >= 1.0 / STATIC_HZ):
            continue
        b, a = butter(2, 2 * STATIC_HZ * dt)
        d = s.acc.shape[1]
        free = model_fitness.xdot(model, s.x, np.zeros_like(s.u))[:, d:]
        h = model_fitness.xdot(model, s.x, s.u)[:, d:] - free
        r, h = filtfilt(b, a, s.acc - free, axis=0), filtfilt(b, a, h, axis=0)
        num += float(np.sum(r * h))
        den += float(np.sum(h * h))
        seconds += float(s.t[-1] - s.t[0])
    if not (den > 0 and math.isfinite(num / den)):
        return None
    raw = num / den
    # a ratio at or below zero: the finger moves against the model's input map, far off the range
    return InputGain(name, float(np.clip(raw, *INPUT_GAIN_RANGE)), raw, seconds)


def input_gains(model, samples) -> tuple[list[InputGain], list[str]]:
    """Every finger's :func:`input_gain` from ``samples`` (train and validation together), in
    the order the fingers first appear, and the names of the fingers none was read for."""
    return _each_finger(samples, lambda name: input_gain(model, name, _of(samples, name)))


def gains_by_finger(gains: list[InputGain], unread: list[str]) -> dict[str, float]:
    """Every finger's gain by name for the check and the parameter file: the model's own (1) for
    a finger none was read for, so the check bounds the law through every finger the controller
    will (:meth:`~soft_gripper_sdre.sim.shape.InputBounds.through_gains`)."""
    return {**{g.name: g.gain for g in gains}, **{name: 1.0 for name in unread}}
