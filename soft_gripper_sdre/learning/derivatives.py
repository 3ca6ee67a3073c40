"""Velocities and accelerations from measured tip positions: constant-acceleration KF + RTS.

The method trains on accelerations estimated by a Kalman filter. Offline, the whole record is
known, so a Rauch–Tung–Striebel smoother runs the filter forward and back and removes the filter's
lag. Per axis the state is [p, ṗ, p̈] driven by white jerk of intensity q [(m/s³)²/Hz]:

    F = [[1, Δt, Δt²/2], [0, 1, Δt], [0, 0, 1]],   H = [1, 0, 0],
    Σ_v = q [[Δt⁵/20, Δt⁴/8, Δt³/6], [Δt⁴/8, Δt³/3, Δt²/2], [Δt³/6, Δt²/2, Δt]],   Σ_r = σ_r².

q sets the smoother's bandwidth. :func:`tune_jerk_psd` picks it from the measurements alone, by the
innovation log-likelihood of the forward filter over a grid (no ground truth needed), which is how
a real data set would be processed; the tools report the error against the simulator's truth.

Three implementations run the same filter. :func:`estimate_kinematics` smooths evenly sampled
axes with filterpy's arithmetic, operation for operation (the same NumPy products and inverses in
the same order, so the same bits as filterpy's ``batch_filter`` and ``rts_smoother``), stacked
over the axes instead of one filter object per axis: the simulator's ``.npz`` labels that the
shipped model is trained on, its six signals' axes in one pass (docs/own_gripper.md, "What
training costs"). ``compiled=True`` runs
:mod:`~soft_gripper_sdre.learning.compiled_labels` (the same estimates to rounding, about a
thousand times faster), as the bag path does. filterpy itself runs the reference paths (the
non-compiled likelihoods and irregular stamps), imported when they run.
"""
from __future__ import annotations

from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from soft_gripper_sdre.learning import compiled_labels

if TYPE_CHECKING:
    from filterpy.kalman import KalmanFilter

#: lower bound on σ_r [m], so noise-free simulated data still gives the filter a positive Σ_r
MEAS_STD_FLOOR = 1e-7


def _transition(dt: float) -> np.ndarray:
    """F over a step of ``dt`` [s]."""
    return np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])


def _process_noise(dt: float, jerk_psd: float) -> np.ndarray:
    """Σ_v over a step of ``dt`` [s], computed as filterpy's ``Q_continuous_white_noise(dim=3)``
    computes it (the same bits)."""
    return np.array([[(dt**5) / 20., (dt**4) / 8., (dt**3) / 6.],
                     [(dt**4) / 8., (dt**3) / 3., (dt**2) / 2.],
                     [(dt**3) / 6., (dt**2) / 2., dt]]) * jerk_psd


def _filter(dt: float, jerk_psd: float, meas_std: float) -> KalmanFilter:
    # the reference paths only (module doc)
    from filterpy.kalman import KalmanFilter
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.F = _transition(dt)
    kf.H = np.array([[1.0, 0.0, 0.0]])
    kf.Q = _process_noise(dt, jerk_psd)
    kf.R = np.array([[_meas_var(meas_std)]])
    return kf


def _smoothed(dt: float, pos: np.ndarray, jerk_psd: float, meas_std: float) -> np.ndarray:
    """(N, k, 3) RTS-smoothed [p, ṗ, p̈] of each column of ``pos`` (N, k), each column's filter
    started as :func:`_started_filter` starts it: filterpy's ``batch_filter(update_first=True)``
    then ``rts_smoother``, every product and inverse the one filterpy computes, on (k, ·, ·)
    stacks (NumPy's stacked ``matmul`` and ``inv`` give each slice the bits of ``dot`` and ``inv``
    on it alone; test/test_derivatives.py holds them to filterpy's)."""
    n, k = pos.shape
    F = _transition(dt)
    FT = F.T
    H = np.array([[1.0, 0.0, 0.0]])
    HT = H.T
    Q, R = _process_noise(dt, jerk_psd), np.array([[_meas_var(meas_std)]])
    eye = np.eye(3)
    x = np.zeros((k, 3, 1))
    x[:, 0, 0] = pos[0]
    P = np.broadcast_to(np.diag([R[0, 0], 1.0, 1e3]), (k, 3, 3)).copy()
    z = pos.reshape(n, k, 1, 1)
    means, covs = np.empty((n, k, 3, 1)), np.empty((n, k, 3, 3))
    for i in range(n):
        y = z[i] - H @ x                                 # update ...
        PHT = P @ HT
        gain = PHT @ np.linalg.inv(H @ PHT + R)
        x = x + gain @ y
        I_KH = eye - gain @ H
        KT = gain.transpose(0, 2, 1)
        P = I_KH @ P @ I_KH.transpose(0, 2, 1) + gain @ R @ KT
        means[i], covs[i] = x, P
        x = F @ x                                        # ... then predict
        P = F @ P @ FT + Q
    for i in range(n - 2, -1, -1):
        predicted = F @ covs[i] @ FT + Q
        gain = covs[i] @ FT @ np.linalg.inv(predicted)
        means[i] += gain @ (means[i + 1] - F @ means[i])
        covs[i] += gain @ (covs[i + 1] - predicted) @ gain.transpose(0, 2, 1)
    return means[:, :, :, 0]


def _meas_var(meas_std: float) -> float:
    """σ_r² [m²] as the filter takes it (σ_r floored at :data:`MEAS_STD_FLOOR`)."""
    return float(max(meas_std, MEAS_STD_FLOOR) ** 2)


def _compiled_loglik(steps: np.ndarray, pos: np.ndarray, jerk_psd: float,
                     meas_std: float) -> float:
    """:func:`innovation_loglik` by :mod:`~soft_gripper_sdre.learning.compiled_labels`, the step
    into sample k being ``steps[k − 1]`` [s]."""
    pos = np.asarray(pos, dtype=float)
    pos = pos[:, None] if pos.ndim == 1 else pos
    steps = np.ascontiguousarray(steps, dtype=float)
    return float(sum(compiled_labels.innovation_loglik(steps, np.ascontiguousarray(pos[:, j]),
                                                       float(jerk_psd), _meas_var(meas_std))
                     for j in range(pos.shape[1])))


def _started_filter(x0: float, dt: float, jerk_psd: float, meas_std: float) -> KalmanFilter:
    """The filter at the first measurement ``x0``: the position known to σ_r, the velocity and
    the acceleration vague."""
    kf = _filter(dt, jerk_psd, meas_std)
    kf.x = np.array([[x0], [0.0], [0.0]])
    kf.P = np.diag([kf.R[0, 0], 1.0, 1e3])
    return kf


def _best_on_grid(loglik, t: np.ndarray, pos: np.ndarray, meas_std: float,
                  grid: np.ndarray | None) -> float:
    """The jerk intensity on ``grid`` (default 1 … 1e8, a decade apart) that maximises
    ``loglik``."""
    grid = np.logspace(0, 8, 9) if grid is None else np.asarray(grid, dtype=float)
    scores = [loglik(t, pos, q, meas_std) for q in grid]
    return float(grid[int(np.argmax(scores))])


def estimate_kinematics(t: np.ndarray, pos: np.ndarray, jerk_psd: float, meas_std: float,
                        smooth: bool = True,
                        compiled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity, acceleration estimates of each column of ``pos``.

    Args:
        t: (N,) uniformly sampled times [s].
        pos: (N, d) measured positions [m].
        jerk_psd: white-jerk intensity q [(m/s³)²/Hz].
        meas_std: measurement σ_r [m] (floored at :data:`MEAS_STD_FLOOR`).
        smooth: run the RTS smoother (offline) instead of only the causal filter.
        compiled: smooth with :mod:`~soft_gripper_sdre.learning.compiled_labels` (the same
            estimates to rounding, about a thousand times faster) instead of filterpy.

    Returns:
        pos, vel, acc, each (N, d).
    """
    t = np.asarray(t, dtype=float)
    pos = np.asarray(pos, dtype=float)
    if pos.ndim == 1:
        pos = pos[:, None]
    if t.ndim != 1 or pos.shape[0] != t.size or t.size < 3:
        raise ValueError(f't must be (N,) and pos (N, d) with N >= 3, got {t.shape} and '
                         f'{pos.shape}')
    dt = float(np.median(np.diff(t)))
    if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-12):
        raise ValueError('t must be uniformly sampled')
    if not (np.isfinite(jerk_psd) and jerk_psd > 0):
        raise ValueError(f'jerk_psd must be finite and > 0, got {jerk_psd!r}')
    out = np.empty((3,) + pos.shape)
    if compiled and smooth:
        steps, measured = np.full(t.size, dt), np.ones(t.size, dtype=bool)
        for j in range(pos.shape[1]):
            z = np.ascontiguousarray(pos[:, j])
            out[:, :, j] = compiled_labels.smoothed(steps, z, measured, float(z[0]),
                                                    float(jerk_psd), _meas_var(meas_std)).T
        return out[0], out[1], out[2]
    if smooth:
        smoothed = _smoothed(dt, pos, jerk_psd, meas_std)
        return smoothed[:, :, 0], smoothed[:, :, 1], smoothed[:, :, 2]
    for j in range(pos.shape[1]):
        kf = _started_filter(pos[0, j], dt, jerk_psd, meas_std)
        means, _, _, _ = kf.batch_filter(pos[:, j], update_first=True)  # x₀ is the state at t₀
        out[:, :, j] = means[:, :, 0].T
    return out[0], out[1], out[2]


def innovation_loglik(t: np.ndarray, pos: np.ndarray, jerk_psd: float, meas_std: float,
                      compiled: bool = False) -> float:
    """Log-likelihood of the measurements under the forward filter (sum over samples and axes);
    ``compiled``: :mod:`~soft_gripper_sdre.learning.compiled_labels`'s (the same to rounding)."""
    dt = float(np.median(np.diff(t)))
    if compiled:
        return _compiled_loglik(np.full(max(len(pos) - 1, 0), dt), pos, jerk_psd, meas_std)
    total = 0.0
    for j in range(pos.shape[1]):
        kf = _started_filter(pos[0, j], dt, jerk_psd, meas_std)
        for z in pos[1:, j]:
            kf.predict()
            kf.update(z)
            total += kf.log_likelihood
    return float(total)


def tune_jerk_psd(t: np.ndarray, pos: np.ndarray, meas_std: float,
                  grid: np.ndarray | None = None, compiled: bool = False) -> float:
    """The jerk intensity on ``grid`` that maximises the innovation likelihood of ``pos``
    (``compiled``: as :func:`innovation_loglik`)."""
    return _best_on_grid(partial(innovation_loglik, compiled=compiled), t, pos, meas_std, grid)


def estimate_errors(vel_est: np.ndarray, acc_est: np.ndarray, vel_true: np.ndarray,
                    acc_true: np.ndarray) -> dict[str, list[float]]:
    """RMS velocity and acceleration errors per axis, and acceleration R² per axis."""
    acc_res = np.sum((acc_est - acc_true) ** 2, axis=0)
    acc_tot = np.sum((acc_true - acc_true.mean(axis=0)) ** 2, axis=0)
    return {
        'vel_rmse': np.sqrt(np.mean((vel_est - vel_true) ** 2, axis=0)).tolist(),
        'acc_rmse': np.sqrt(np.mean((acc_est - acc_true) ** 2, axis=0)).tolist(),
        'acc_r2': (1.0 - acc_res / acc_tot).tolist(),
    }


# -- irregular stamps (recordings of a real sensor) ------------------------------------------

def _irregular_models(times: np.ndarray,
                      jerk_psd: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """F and Σ_v of each step between consecutive ``times``: element i goes from i to i + 1."""
    Fs, Qs = [], []
    for h in np.diff(times).tolist():
        Fs.append(_transition(h))
        Qs.append(_process_noise(h, jerk_psd))
    return Fs, Qs


def is_uniform(t: np.ndarray) -> bool:
    """Whether ``t`` is evenly spaced, as :func:`estimate_kinematics` requires."""
    t = np.asarray(t, dtype=float)
    if t.size < 3:
        return False
    d = np.diff(t)
    return bool(np.allclose(d, float(np.median(d)), rtol=1e-6, atol=1e-12))


def estimate_kinematics_irregular(t: np.ndarray, pos: np.ndarray, grid: np.ndarray, jerk_psd: float,
                                  meas_std: float, compiled: bool = False
                                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The smoothed position, velocity and acceleration at the times ``grid`` from measurements
    ``pos`` at the increasing, unevenly spaced times ``t`` (jittery stamps, dropped samples).

    The filter of :func:`estimate_kinematics` with a step of its own between consecutive instants
    of the merged time axis: at a measurement time it updates, at a grid time without one it only
    predicts, and the RTS smoother runs back over the same steps, so every grid value is the
    smoothed estimate from all measurements (no interpolation of the data).

    Args:
        t: (N,) strictly increasing measurement times [s], N >= 3.
        pos: (N, d) measured positions [m].
        grid: (M,) times to estimate at [s], within [t[0], t[-1]].
        jerk_psd, meas_std, compiled: as :func:`estimate_kinematics`.

    Returns:
        pos, vel, acc, each (M, d).
    """
    t = np.asarray(t, dtype=float)
    grid = np.asarray(grid, dtype=float)
    pos = np.asarray(pos, dtype=float)
    if pos.ndim == 1:
        pos = pos[:, None]
    if t.ndim != 1 or pos.shape[0] != t.size or t.size < 3:
        raise ValueError(f't must be (N,) and pos (N, d) with N >= 3, got {t.shape} and '
                         f'{pos.shape}')
    if np.any(np.diff(t) <= 0):
        raise ValueError('t must be strictly increasing')
    if grid.ndim != 1 or grid.size == 0 or grid[0] < t[0] or grid[-1] > t[-1]:
        raise ValueError('grid must be a non-empty (M,) array within [t[0], t[-1]]')
    if not (np.isfinite(jerk_psd) and jerk_psd > 0):
        raise ValueError(f'jerk_psd must be finite and > 0, got {jerk_psd!r}')
    times, inverse = np.unique(np.concatenate([t, grid]), return_inverse=True)
    meas_at = inverse[:t.size]               # index of each measurement on the merged axis
    grid_at = inverse[t.size:]
    out = np.empty((3, grid.size, pos.shape[1]))
    if compiled:
        steps = np.append(np.diff(times), 0.0)
        measured = np.zeros(times.size, dtype=bool)
        measured[meas_at] = True
        for j in range(pos.shape[1]):
            z = np.zeros(times.size)
            z[meas_at] = pos[:, j]
            out[:, :, j] = compiled_labels.smoothed(steps, z, measured, float(pos[0, j]),
                                                    float(jerk_psd), _meas_var(meas_std))[grid_at].T
        return out[0], out[1], out[2]
    Fs, Qs = _irregular_models(times, jerk_psd)
    Fs.append(Fs[-1] if Fs else np.eye(3))   # the filter's last prediction is never used
    Qs.append(Qs[-1] if Qs else np.zeros((3, 3)))
    for j in range(pos.shape[1]):
        zs: list = [None] * times.size
        for i, z in zip(meas_at.tolist(), pos[:, j].tolist()):
            zs[i] = z
        kf = _started_filter(pos[0, j], float(np.median(np.diff(t))), jerk_psd, meas_std)
        means, covs, _, _ = kf.batch_filter(zs, Fs=Fs, Qs=Qs, update_first=True)
        # the smoother's step k + 1 is the transition from k to k + 1
        means, _, _, _ = kf.rts_smoother(means, covs, Fs=[Fs[-1]] + Fs[:-1], Qs=[Qs[-1]] + Qs[:-1])
        out[:, :, j] = means[grid_at, :, 0].T
    return out[0], out[1], out[2]


def innovation_loglik_irregular(t: np.ndarray, pos: np.ndarray, jerk_psd: float,
                                meas_std: float, compiled: bool = False) -> float:
    """:func:`innovation_loglik` for unevenly spaced times ``t`` (a step per interval)."""
    t = np.asarray(t, dtype=float)
    if compiled:
        return _compiled_loglik(np.diff(t), pos, jerk_psd, meas_std)
    Fs, Qs = _irregular_models(t, jerk_psd)
    total = 0.0
    for j in range(pos.shape[1]):
        kf = _started_filter(pos[0, j], float(np.median(np.diff(t))), jerk_psd, meas_std)
        for z, F, Q in zip(pos[1:, j], Fs, Qs):
            kf.predict(F=F, Q=Q)
            kf.update(z)
            total += kf.log_likelihood
    return float(total)


def tune_jerk_psd_irregular(t: np.ndarray, pos: np.ndarray, meas_std: float,
                            grid: np.ndarray | None = None, compiled: bool = False) -> float:
    """:func:`tune_jerk_psd` for unevenly spaced times ``t``."""
    return _best_on_grid(partial(innovation_loglik_irregular, compiled=compiled), t, pos,
                         meas_std, grid)
