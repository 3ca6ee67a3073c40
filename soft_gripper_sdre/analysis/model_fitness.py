"""Is a learned model fit to control? Judged as the controller will use it, not by R² alone.

R² of the acceleration labels says how well the networks fit one-step data. A controller uses the
model differently: the SDRE linearises it along the trajectory, the feedforward inverts it, and
the closed loop lives near rest. Three checks look at that:

* **rest stability** — the learned model has x = 0 as an equilibrium by construction
  (ẋ = A(x)x + G(x)u), and its linearisation there is A(0) itself, since
  ∂(A(x)x)/∂x |₀ = A(0). A soft finger at rest is stable, so every eigenvalue of A(0) must have
  a negative real part, and a free simulation from small offsets must come back
  (:func:`rest_stability`);
* **free-run error** — the model simulated open loop with the recorded validation inputs, from
  the estimated state at the start of each window of ``window`` seconds, against the estimated
  positions (:func:`free_run_error`). It is given relative to the positions' own spread over the
  validation data, so 1.0 is no better than predicting that the finger stays where it is;
* both together give the verdict (:func:`judge`): the model is fit to control when its rest is
  stable and its free run beats standing still by :data:`FREE_RUN_LIMIT`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
import itertools
import math

import numpy as np

from soft_gripper_sdre.control.kernels.network_plant import network_rk4, network_run
from soft_gripper_sdre.sim.shape import FingerShape

#: a free run whose error is above this share of the validation positions' spread is not fit
FREE_RUN_LIMIT = 0.5
#: free simulation from rest: offsets as a share of the data's position spread, length [s] and
#: the share of the offset that must remain at most at its end
REST_OFFSET = 0.1
REST_SECONDS = 3.0
REST_RETURN = 0.5


def model_shape(model) -> FingerShape:
    """The finger's shape of ``model``: its ``shape`` (a learned model), else read off the
    blocks its ``AG`` returns at rest (:func:`~soft_gripper_sdre.control.tracking.shape_of`).

    Raises:
        ShapeError: the model has no shape and ``AG`` answers with blocks of no finger's shape.
    """
    from soft_gripper_sdre.control.tracking import shape_of
    return shape_of(model)


def xdot(model, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """ẋ = A(x)x + G(x)u for a batch x (n, 2d), u (n, m) (the model's own ``xdot`` where it has
    one, else from AG)."""
    own = getattr(model, 'xdot', None)
    if own is not None:
        return own(x, u)
    A, G = model.AG(x)
    return np.einsum('nij,nj->ni', A, x) + np.einsum('nij,nj->ni', G, u)


def rk4_step(model, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """One classical Runge–Kutta step of ẋ = A(x)x + G(x)u for a batch x (n, 2d), u (n, m) held."""
    k1 = xdot(model, x, u)
    k2 = xdot(model, x + 0.5 * dt * k1, u)
    k3 = xdot(model, x + 0.5 * dt * k2, u)
    k4 = xdot(model, x + dt * k3, u)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


class CompiledRK4:
    """:func:`rk4_step` for one state of a learned model (``SDCModel``: its ``fused_network``)
    compiled: the whole of a held input's substeps in one call, a few microseconds, where the
    numpy path spends tens per evaluation of ẋ. The same arithmetic up to the order of the
    networks' sums (the closed-loop check's numbers agree to rounding:
    test/test_compiled_check_plant.py)."""

    def __init__(self, model) -> None:
        """Raises:
            ValueError: ``model`` is not evaluated by its fused network alone (:meth:`fits`).
        """
        if not self.fits(model):
            raise ValueError(f'CompiledRK4 needs a learned SDCModel (its fused network), got '
                             f'{type(model).__name__}')
        shape = model_shape(model)
        self.d, self.m = shape.d, shape.m
        self.layers = tuple(np.ascontiguousarray(a, dtype=np.float64)
                            for a in model.fused_network)

    @staticmethod
    def fits(model) -> bool:
        """``model`` is evaluated by its fused network alone (a learned ``SDCModel``; a test
        model with its own ``AG`` or ``xdot`` is not)."""
        from soft_gripper_sdre.learning.model import SDCModel
        kind = type(model)
        return all(getattr(kind, name, None) is getattr(SDCModel, name)
                   for name in ('xdot', 'AG', 'sdc_blocks', 'fused_network'))

    def step(self, x: np.ndarray, u: np.ndarray, dt: float, substeps: int) -> None:
        """x (2d,) float64 advanced in place by ``substeps`` RK4 steps over ``dt`` [s], u (m,)
        held.

        Raises:
            ShapeError: x or u of another shape than the model's, or x not a float64 array.
            ValueError: ``substeps`` not an int >= 1 or ``dt`` not finite and > 0.
        """
        if not (isinstance(x, np.ndarray) and x.dtype == np.float64
                and x.shape == (2 * self.d,) and np.shape(u) == (self.m,)):
            from soft_gripper_sdre.sim.shape import ShapeError
            raise ShapeError(f'CompiledRK4.step: x must be a float64 array ({2 * self.d},) and u '
                             f'({self.m},) for the model\'s shape (d={self.d}, m={self.m}), got '
                             f'{np.shape(x)} and {np.shape(u)}')
        if not (isinstance(substeps, int) and substeps >= 1 and math.isfinite(dt) and dt > 0):
            raise ValueError(f'CompiledRK4.step: substeps must be an int >= 1 and dt finite and '
                             f'> 0, got {substeps!r} and {dt!r}')
        network_rk4(x, np.asarray(u, dtype=np.float64), float(dt), substeps, *self.layers,
                     self.d)

    def simulate(self, x0: np.ndarray, u: np.ndarray, dt: float, substeps: int = 2,
                 bound: float = 1.0) -> np.ndarray:
        """:func:`simulate` of one trajectory: from x0 (2d,) under u (T, m), each held over
        ``dt`` [s]; returns (T + 1, 2d), NaN from where it leaves ``bound`` [m or m/s] or stops
        being finite.

        Raises:
            ShapeError: x0 or u of another shape than the model's.
            ValueError: ``substeps`` not an int >= 1, ``dt`` not finite and > 0, or ``bound``
                not > 0.
        """
        x0 = np.asarray(x0, dtype=np.float64)
        u = np.ascontiguousarray(u, dtype=np.float64)
        if x0.shape != (2 * self.d,) or u.ndim != 2 or u.shape[1] != self.m:
            from soft_gripper_sdre.sim.shape import ShapeError
            raise ShapeError(f'CompiledRK4.simulate: x0 must be ({2 * self.d},) and u (T, '
                             f'{self.m}) for the model\'s shape (d={self.d}, m={self.m}), got '
                             f'{x0.shape} and {u.shape}')
        if not (isinstance(substeps, int) and substeps >= 1 and math.isfinite(dt) and dt > 0
                and bound > 0):
            raise ValueError(f'CompiledRK4.simulate: substeps must be an int >= 1, dt finite and '
                             f'> 0 and bound > 0, got {substeps!r}, {dt!r} and {bound!r}')
        out = np.empty((u.shape[0] + 1, 2 * self.d))
        network_run(x0, u, float(dt), substeps, float(bound), *self.layers, self.d, out)
        return out


def simulate(model, x0: np.ndarray, u: np.ndarray, dt: float, substeps: int = 2,
             bound: float = 1.0) -> np.ndarray:
    """Open-loop trajectories of a batch: x0 (n, 2d), inputs u (T, n, m) held over each ``dt``.

    Returns (T + 1, n, 2d); a trajectory that leaves ``bound`` [m or m/s] or stops being finite is
    NaN from there on (a diverging model is not followed to overflow).
    """
    x = np.array(x0, dtype=float)
    out = np.full((u.shape[0] + 1,) + x.shape, np.nan)
    out[0] = x
    h = dt / substeps
    alive = np.ones(len(x), dtype=bool)
    for k in range(u.shape[0]):
        for _ in range(substeps):
            x[alive] = rk4_step(model, x[alive], u[k][alive], h)
        alive &= np.all(np.isfinite(x), axis=1) & (np.abs(x).max(axis=1) < bound)
        out[k + 1][alive] = x[alive]
        if not alive.any():
            break
    return out


@dataclass
class RestCheck:
    """Eigenvalues of A(0) and the free simulation from offsets around rest."""

    eigenvalues: list[complex]
    max_real: float               # largest real part of A(0)'s eigenvalues [1/s]
    natural_hz: list[float]       # |λ| / 2π of the eigenvalues with a positive imaginary part
    returned: float               # largest remaining offset at the end of the free run, share of it
    stable: bool

    def summary(self) -> dict:
        d = asdict(self)
        d['eigenvalues'] = [[float(e.real), float(e.imag)] for e in self.eigenvalues]
        return d


def rest_offsets(d: int) -> np.ndarray:
    """(k, d) unit directions the free run from rest starts along: for a planar tip ±X, ±Y and
    the diagonals (eight); for a 3-D tip ±X, ±Y, ±Z and the eight corners of the cube (14)."""
    if d == 2:
        angles = np.arange(8) * np.pi / 4
        return np.stack([np.cos(angles), np.sin(angles)], axis=1)
    axes = np.concatenate([np.eye(d), -np.eye(d)])
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=d))) / np.sqrt(d)
    return np.concatenate([axes, corners])


def rest_stability(model, offset: float, dt: float = 1e-3,
                   seconds: float = REST_SECONDS) -> RestCheck:
    """Eigenvalues of A(0) and a free run of ``seconds`` from offsets of ``offset`` [m] around
    rest along :func:`rest_offsets` (zero velocity, the input at zero)."""
    shape = model_shape(model)
    d = shape.d
    A = model.AG(np.zeros(shape.n_state))[0][0]
    eig = np.linalg.eigvals(A)
    dirs = rest_offsets(d)
    x0 = np.zeros((len(dirs), shape.n_state))
    if d == 2:
        x0[:, 0], x0[:, 1] = offset * dirs[:, 0], offset * dirs[:, 1]
    else:
        x0[:, :d] = offset * dirs
    steps = int(round(seconds / dt))
    traj = simulate(model, x0, np.zeros((steps, len(dirs), shape.m)), dt,
                    bound=max(1.0, 100 * offset))
    end = np.linalg.norm(traj[-1, :, :d], axis=1) / offset
    returned = float(np.nanmax(np.where(np.isfinite(end), end, np.inf)))
    max_real = float(eig.real.max())
    hz = sorted(float(abs(e) / (2 * np.pi)) for e in eig if e.imag > 0)
    return RestCheck(list(eig), max_real, hz, returned,
                     bool(max_real < 0 and returned <= REST_RETURN))


@dataclass
class FreeRun:
    """Open-loop error of the model on the validation inputs, window by window."""

    window_s: float
    windows: int
    rmse_m: float                 # over every window's positions [m]
    spread_m: float               # RMS of the validation positions about their mean [m]
    relative: float               # rmse / spread: 1.0 = no better than standing still
    diverged: int                 # windows whose run left the bound or stopped being finite

    def summary(self) -> dict:
        return asdict(self)


def free_run_error(model, segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                   window: float = 1.0, substeps: int = 2) -> FreeRun:
    """Free-run error over validation ``segments``: each (t (N,), x (N, 2d), u (N, m)) on a
    uniform grid, x the estimated (translated) states. Every window of ``window`` seconds starts
    from the estimated state and is driven by the held inputs."""
    starts, inputs, targets, dts = [], [], [], []
    d = np.shape(segments[0][1])[1] // 2 if segments else 2
    for t, x, u in segments:
        dt = float(np.median(np.diff(t)))
        n = max(int(round(window / dt)), 1)
        for i in range(0, len(t) - n, n):
            starts.append(x[i])
            inputs.append(u[i:i + n])
            targets.append(x[i + 1:i + n + 1, :d])
            dts.append(dt)
    if not starts:
        raise ValueError(f'no validation segment is longer than the {window:g} s window')
    errors, diverged = [], 0
    for dt in sorted(set(dts)):                # one batch per grid spacing
        pick = [i for i, d in enumerate(dts) if d == dt]
        length = min(len(inputs[i]) for i in pick)
        u = np.stack([inputs[i][:length] for i in pick], axis=1)
        run = simulate(model, np.stack([starts[i] for i in pick]), u, dt, substeps)[1:, :, :d]
        target = np.stack([targets[i][:length] for i in pick], axis=1)
        bad = ~np.all(np.isfinite(run), axis=(0, 2))
        diverged += int(bad.sum())
        err = run - target
        err[:, bad] = 10 * np.nanmax(np.abs(target))     # a diverged window counts as far off
        errors.append(err.reshape(-1, d))
    err = np.concatenate(errors)
    pos = np.concatenate([x[:, :d] for _, x, _ in segments])
    spread = float(np.sqrt(np.mean(np.sum((pos - pos.mean(axis=0)) ** 2, axis=1))))
    rmse = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    return FreeRun(window, len(starts), rmse, spread, rmse / spread if spread > 0 else np.inf,
                   diverged)


@dataclass
class Fitness:
    """The verdict and what it rests on."""

    fit: bool
    reasons: list[str] = field(default_factory=list)
    rest: RestCheck | None = None
    free_run: FreeRun | None = None

    def summary(self) -> dict:
        return {'fit_for_control': self.fit, 'reasons': self.reasons,
                'rest': self.rest.summary() if self.rest else None,
                'free_run': self.free_run.summary() if self.free_run else None}


def judge(model, segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
          window: float = 1.0) -> Fitness:
    """Rest stability and free-run error of ``model`` on validation ``segments``
    (:func:`free_run_error`), and the verdict."""
    run = free_run_error(model, segments, window)
    dt = float(np.median(np.diff(segments[0][0])))
    rest = rest_stability(model, REST_OFFSET * max(run.spread_m, 1e-4), dt=min(dt, 2e-3))
    reasons = []
    if rest.max_real >= 0:
        reasons.append(f'the learned rest is unstable: A(0) has an eigenvalue with real part '
                       f'{rest.max_real:+.3g} 1/s (the finger at rest is stable)')
    elif rest.returned > REST_RETURN:
        reasons.append(f'a free run from {1e3 * REST_OFFSET * run.spread_m:.2f} mm off rest keeps '
                       f'{100 * rest.returned:.0f} % of its offset after {REST_SECONDS:g} s')
    if run.relative > FREE_RUN_LIMIT:
        reasons.append(f'open loop over {window:g} s windows the model misses the validation '
                       f'positions by {100 * run.relative:.0f} % of their spread (limit '
                       f'{100 * FREE_RUN_LIMIT:.0f} %)'
                       + (f'; {run.diverged} of {run.windows} windows diverged'
                          if run.diverged else ''))
    return Fitness(not reasons, reasons, rest, run)
