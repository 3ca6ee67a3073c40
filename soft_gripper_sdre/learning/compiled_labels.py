"""The labels' constant-acceleration KF + RTS (:mod:`soft_gripper_sdre.learning.derivatives`)
compiled with numba: the same filter, smoother and innovation log-likelihood as filterpy's
``KalmanFilter`` (``batch_filter(update_first=True)``, ``rts_smoother``, ``log_likelihood``),
step for step, for one coordinate at a time.

Per step k (from sample k to k + 1, h_k = t_{k+1} − t_k), with white jerk of intensity q:

    F_k = [[1, h, h²/2], [0, 1, h], [0, 0, 1]],
    Σ_v,k = q [[h⁵/20, h⁴/8, h³/6], [h⁴/8, h³/3, h²/2], [h³/6, h²/2, h]],   H = [1, 0, 0],

started at the first measurement z₀ with x̂ = [z₀, 0, 0], P = diag(σ_r², 1, 1e3). The update is
filterpy's (Joseph form), the log-likelihood of an innovation y of variance S is scipy's
``multivariate_normal.logpdf`` for one dimension, −(log 2π + log S + (y / √S)²) / 2. The results
agree with filterpy's to rounding (test/test_compiled_labels.py: 1e-12 relative); a model trained
on them is not the one trained on filterpy's bit for bit, so the ``.npz`` path of the shipped model
keeps filterpy's and the bag path uses these.

The estimator's constant-velocity likelihood, whose maximum over a grid picks the loop's
estimator intensity (:func:`~soft_gripper_sdre.analysis.data_facts.tune_accel_psd`), is compiled
here too (:func:`cv_loglik_axis`; numpy's matrix steps to 1e-12, test/test_model_fitness.py).

The kernels call only each other, in this file, so numba's own on-disk cache rule (a kernel's
cache is keyed on its source file) holds for them; they are not part of the controller's kernels
(:mod:`soft_gripper_sdre.control.compiled_cache`).
"""
from __future__ import annotations

import math

from numba import njit
import numpy as np

_njit = njit(cache=True, error_model='numpy', nogil=True)

#: log(2π), as scipy's multivariate normal takes it
_LOG_2PI = math.log(2.0 * math.pi)


@_njit
def _models(h: float, q: float, F: np.ndarray, Q: np.ndarray) -> None:
    """F and Σ_v of a step of ``h`` seconds into ``F`` and ``Q`` (3, 3), as filterpy's
    ``Q_continuous_white_noise(dim=3, dt=h, spectral_density=q)``."""
    F[0, 0], F[0, 1], F[0, 2] = 1.0, h, 0.5 * h * h
    F[1, 0], F[1, 1], F[1, 2] = 0.0, 1.0, h
    F[2, 0], F[2, 1], F[2, 2] = 0.0, 0.0, 1.0
    h2, h3, h4, h5 = h ** 2, h ** 3, h ** 4, h ** 5
    Q[0, 0], Q[0, 1], Q[0, 2] = h5 / 20 * q, h4 / 8 * q, h3 / 6 * q
    Q[1, 0], Q[1, 1], Q[1, 2] = h4 / 8 * q, h3 / 3 * q, h2 / 2 * q
    Q[2, 0], Q[2, 1], Q[2, 2] = h3 / 6 * q, h2 / 2 * q, h * q


@_njit
def _predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray,
             T: np.ndarray) -> None:
    """x = F x, P = F P Fᵀ + Σ_v, in place (T: scratch (3, 3))."""
    x0 = F[0, 0] * x[0] + F[0, 1] * x[1] + F[0, 2] * x[2]
    x1 = F[1, 0] * x[0] + F[1, 1] * x[1] + F[1, 2] * x[2]
    x2 = F[2, 0] * x[0] + F[2, 1] * x[1] + F[2, 2] * x[2]
    x[0], x[1], x[2] = x0, x1, x2
    for r in range(3):
        for c in range(3):
            T[r, c] = F[r, 0] * P[0, c] + F[r, 1] * P[1, c] + F[r, 2] * P[2, c]
    for r in range(3):
        for c in range(3):
            P[r, c] = (T[r, 0] * F[c, 0] + T[r, 1] * F[c, 1] + T[r, 2] * F[c, 2]) + Q[r, c]


@_njit
def _update(x: np.ndarray, P: np.ndarray, z: float, R: float, T: np.ndarray,
            U: np.ndarray) -> tuple[float, float]:
    """The measurement update (Joseph form) in place; returns (innovation y, its variance S)."""
    y = z - x[0]
    S = P[0, 0] + R
    k0, k1, k2 = P[0, 0] * (1.0 / S), P[1, 0] * (1.0 / S), P[2, 0] * (1.0 / S)
    x[0] += k0 * y
    x[1] += k1 * y
    x[2] += k2 * y
    # I − K H: the identity with −K in its first column
    for r in range(3):
        for c in range(3):
            U[r, c] = 1.0 if r == c else 0.0
    U[0, 0] -= k0
    U[1, 0] -= k1
    U[2, 0] -= k2
    for r in range(3):
        for c in range(3):
            T[r, c] = U[r, 0] * P[0, c] + U[r, 1] * P[1, c] + U[r, 2] * P[2, c]
    K = (k0, k1, k2)
    for r in range(3):
        for c in range(3):
            P[r, c] = ((T[r, 0] * U[c, 0] + T[r, 1] * U[c, 1] + T[r, 2] * U[c, 2])
                       + (K[r] * R) * K[c])
    return y, S


@_njit
def _start(z0: float, R: float, x: np.ndarray, P: np.ndarray) -> None:
    x[0], x[1], x[2] = z0, 0.0, 0.0
    P[:, :] = 0.0
    P[0, 0], P[1, 1], P[2, 2] = R, 1.0, 1e3


@_njit
def innovation_loglik(steps: np.ndarray, z: np.ndarray, q: float, R: float) -> float:
    """Log-likelihood of the measurements ``z`` (N,) under the forward filter started at z[0]:
    the sum over k ≥ 1 of each innovation's, the step into sample k being ``steps[k − 1]`` [s]
    (N − 1,); ``R`` = σ_r² [m²], ``q`` the jerk intensity."""
    x, P = np.empty(3), np.empty((3, 3))
    F, Q, T, U = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    _start(z[0], R, x, P)
    total = 0.0
    last = -1.0
    for k in range(1, z.shape[0]):
        h = steps[k - 1]
        if h != last:
            _models(h, q, F, Q)
            last = h
        _predict(x, P, F, Q, T)
        y, S = _update(x, P, z[k], R, T, U)
        total += -0.5 * (_LOG_2PI + math.log(S) + (y * (1.0 / math.sqrt(S))) ** 2)
    return total


@_njit
def smoothed(steps: np.ndarray, z: np.ndarray, measured: np.ndarray, z0: float, q: float,
             R: float) -> np.ndarray:
    """The RTS-smoothed states [p, ṗ, p̈] (M, 3) of the filter started at ``z0`` on M instants:
    at instant i it updates with z[i] where ``measured[i]``, then predicts over ``steps[i]`` [s]
    to instant i + 1 (``steps`` (M,), its last element unused); the smoother runs back over the
    same steps."""
    M = z.shape[0]
    xs, Ps = np.empty((M, 3)), np.empty((M, 3, 3))
    x, P = np.empty(3), np.empty((3, 3))
    F, Q, T, U = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    _start(z0, R, x, P)
    for i in range(M):
        if measured[i]:
            _update(x, P, z[i], R, T, U)
        xs[i] = x
        Ps[i] = P
        if i + 1 < M:
            _models(steps[i], q, F, Q)
            _predict(x, P, F, Q, T)
    Pp, Pi, C, D = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    last = -1.0
    for k in range(M - 2, -1, -1):
        if steps[k] != last:
            _models(steps[k], q, F, Q)
            last = steps[k]
        Pk = Ps[k]
        for r in range(3):                                  # Pp = F P_k Fᵀ + Σ_v
            for c in range(3):
                T[r, c] = F[r, 0] * Pk[0, c] + F[r, 1] * Pk[1, c] + F[r, 2] * Pk[2, c]
        for r in range(3):
            for c in range(3):
                Pp[r, c] = (T[r, 0] * F[c, 0] + T[r, 1] * F[c, 1] + T[r, 2] * F[c, 2]) + Q[r, c]
        Pi[:, :] = np.linalg.inv(Pp)
        for r in range(3):                                  # C = P_k Fᵀ Pp⁻¹
            for c in range(3):
                U[r, c] = Pk[r, 0] * F[c, 0] + Pk[r, 1] * F[c, 1] + Pk[r, 2] * F[c, 2]
        for r in range(3):
            for c in range(3):
                C[r, c] = U[r, 0] * Pi[0, c] + U[r, 1] * Pi[1, c] + U[r, 2] * Pi[2, c]
        xk, xn = xs[k], xs[k + 1]
        e0 = xn[0] - (F[0, 0] * xk[0] + F[0, 1] * xk[1] + F[0, 2] * xk[2])
        e1 = xn[1] - (F[1, 0] * xk[0] + F[1, 1] * xk[1] + F[1, 2] * xk[2])
        e2 = xn[2] - (F[2, 0] * xk[0] + F[2, 1] * xk[1] + F[2, 2] * xk[2])
        for r in range(3):
            xk[r] += C[r, 0] * e0 + C[r, 1] * e1 + C[r, 2] * e2
        Pn = Ps[k + 1]
        for r in range(3):                                  # P_k += C (P_k+1 − Pp) Cᵀ
            for c in range(3):
                D[r, c] = (C[r, 0] * (Pn[0, c] - Pp[0, c]) + C[r, 1] * (Pn[1, c] - Pp[1, c])
                           + C[r, 2] * (Pn[2, c] - Pp[2, c]))
        for r in range(3):
            for c in range(3):
                Pk[r, c] += D[r, 0] * C[c, 0] + D[r, 1] * C[c, 1] + D[r, 2] * C[c, 2]
    return xs


@_njit
def cv_loglik_axis(t: np.ndarray, z: np.ndarray, q: float, R: float) -> float:
    """The estimator's innovation log-likelihood for one coordinate (``analysis.data_facts.
    cv_loglik``): the constant-velocity model of white acceleration ``q`` per step of ``t`` [s],
    F = [[1, h], [0, 1]], Σ_v = q [[h³/3, h²/2], [h²/2, h]], started at x̂ = [z₀, 0],
    P = diag(``R``, 1), each innovation's −(log 2πS + y²/S) / 2 summed (the update P − K P₀ᵀ)."""
    x0, x1 = z[0], 0.0
    p00, p01, p10, p11 = R, 0.0, 0.0, 1.0
    total = 0.0
    for k in range(1, z.shape[0]):
        h = t[k] - t[k - 1]
        q00, q01, q11 = q * (h ** 3 / 3), q * (h ** 2 / 2), q * h
        x0, x1 = x0 + h * x1, x1
        f00, f01, f10, f11 = p00 + h * p10, p01 + h * p11, p10, p11          # F P
        p00, p01 = f00 + f01 * h + q00, f01 + q01                            # F P Fᵀ + Σ_v
        p10, p11 = f10 + f11 * h + q01, f11 + q11
        S = p00 + R
        v = z[k] - x0
        total -= 0.5 * (math.log(2.0 * math.pi * S) + v * v / S)
        k0, k1 = p00 / S, p10 / S
        x0, x1 = x0 + k0 * v, x1 + k1 * v
        p00, p01, p10, p11 = p00 - k0 * p00, p01 - k0 * p01, p10 - k1 * p00, p11 - k1 * p01
    return total
