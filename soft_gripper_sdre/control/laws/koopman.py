"""Koopman baselines: linear MPC and LQR on the lifted linear model of
:mod:`soft_gripper_sdre.learning.koopman` (z_{k+1} = A z_k + B u_k, [p − p₀, ṗ] = C z).

Both track the lifted reference. At each step the reference is extrapolated from what every law
gets, (p_d, ṗ_d, p̈_d) at t_k, with constant acceleration,
p_d(t_k + τ) = p_d + ṗ_d τ + ½ p̈_d τ² (also backwards, for the delay coordinates), and lifted,
z_d(τ) = ψ(p_d(τ), ṗ_d(τ), p_d(τ − delays)). Its input is the lifted model's inversion along it,

    u_d(τ) = argmin_u ‖z_d(τ + h) − A_h z_d(τ) − B_h u‖²_P
           = (B_hᵀ P B_h)⁻¹ B_hᵀ P (z_d(τ + h) − A_h z_d(τ))

(h the law's step, P the LQR cost-to-go below), the lifted counterpart of ``sdre_ff``'s
feedforward. The cost is the SDRE's, in SI and per second of time: Q = diag(q_pos, q_pos, q_vel,
q_vel) on [p − p_d, ṗ − ṗ_d] and R on u − u_d, i.e. Q_z = Cᵀ Q C h and R h per step of length h.

* ``koopman_lqr``: u = u_d(0) + K (z − z_d(0)) at the control period, K the infinite-horizon LQR
  gain of (A, B, Q_z, R) (discrete Riccati equation), then saturated.
* ``koopman_mpc``: N blocks of ``block`` control periods (the input held over each block), the
  same cost plus the terminal cost-to-go ‖z_N − z_d,N‖²_{P_h} of the blocked LQR, and the box
  |u| ≤ u_max. Condensed over the inputs U it is the box-constrained QP
  min ½ Uᵀ H U + gᵀ U, with H constant (factored once). Solver: the unconstrained minimiser
  −H⁻¹ g, and where it leaves the box, scipy's bounded-variable least squares (BVLS, exact
  active-set) on the Cholesky form ‖Lᵀ U + L⁻¹ g‖² (H = L Lᵀ). With the box inactive the first
  move equals the blocked LQR's u_d + K_h (z − z_d) whenever the lifted reference is a
  trajectory of the model (the terminal cost makes the finite horizon the infinite one).

Both go through the saturation and roll-off every law shares (:class:`LawIO`). The delay
coordinates come from the law's own history of the estimated positions (filled with the first
position after :meth:`reset`). The 40 Hz roll-off is not in the prediction model, as it is not in
the other laws'.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_discrete_are, solve_triangular
from scipy.optimize import lsq_linear

from soft_gripper_sdre.control.laws.feedforward import reference_acceleration
from soft_gripper_sdre.control.laws.registry import (
    WEIGHT_PARAMS,
    LawSettings,
    model_shape,
    register_law,
)
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    LawIO,
    LawStep,
    Weights,
    hand_path,
    law_bounds,
)
from soft_gripper_sdre.learning.koopman import KoopmanFileError, KoopmanModel
from soft_gripper_sdre.sim.shape import HAND_SHAPE, ShapeError

#: the MPC's defaults: N blocks of ``block`` control periods (a 20 ms horizon at 1 ms)
MPC_HORIZON = 10
MPC_BLOCK = 2


def blocked(A: np.ndarray, B: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """The model over ``block`` steps with the input held: (A^m, Σ_{i<m} Aⁱ B)."""
    Am, Bm = np.eye(len(A)), np.zeros_like(B)
    for _ in range(block):
        Am, Bm = A @ Am, A @ Bm + B
    return Am, Bm


class LiftedTracking:
    """The lifted reference, its feedforward and the LQR of one step length (``block`` periods).

    Args:
        model: the Koopman model; weights: Q, R (SI, per second); block: step length [periods].
    """

    def __init__(self, model: KoopmanModel, weights: Weights, block: int = 1) -> None:
        if int(block) != block or block < 1:
            raise ValueError(f'block must be an integer >= 1, got {block!r}')
        self.model, self.block = model, int(block)
        self.h = model.dt * self.block
        self.A, self.B = blocked(model.A, model.B, self.block)
        self.Qz = model.C.T @ weights.Q @ model.C * self.h
        self.R = weights.R * self.h
        try:
            self.P = solve_discrete_are(self.A, self.B, self.Qz, self.R)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise ValueError(f'no stabilising LQR on the lifted model ({exc})') from None
        BtP = self.B.T @ self.P
        self.K = -np.linalg.solve(self.R + BtP @ self.B, BtP @ self.A)       # u = u_d + K (z − z_d)
        self.ff = np.linalg.solve(BtP @ self.B, BtP)                         # u_d = ff (z⁺ − A z)

    def reference(self, xd: np.ndarray, ref_acc: np.ndarray, points: int) -> np.ndarray:
        """Lifted reference z_d at t + j·h, j = 0 … points−1: (n, points, n_z) from x_d (n, 4)
        (translated) and p̈_d (n, 2), extrapolated with constant acceleration."""
        m = self.model
        tau = self.h * np.arange(points)                                     # (J,)
        delays = m.dt * np.asarray(m.settings.delays, dtype=float)           # (D,)
        n = len(xd)

        def pos(t):                                                          # t (…) → (n, …, 2)
            t = t[None, ..., None]
            shape = (n,) + (1,) * (t.ndim - 2) + (2,)
            return (xd[:, :2].reshape(shape) + xd[:, 2:].reshape(shape) * t
                    + 0.5 * ref_acc.reshape(shape) * t * t)
        x = np.concatenate([pos(tau), xd[:, None, 2:] + ref_acc[:, None, :] * tau[None, :, None]],
                           axis=-1)                                          # (n, J, 4)
        delayed = pos(tau[:, None] - delays[None, :])                        # (n, J, D, 2)
        return m.lift(x, delayed)

    def feedforward(self, zd: np.ndarray) -> np.ndarray:
        """u_d at each of zd's points but the last: (n, J−1, 2) from (n, J, n_z)."""
        return (zd[:, 1:] - zd[:, :-1] @ self.A.T) @ self.ff.T


class DelayHistory:
    """The law's record of the translated positions of the last ``max_delay`` periods."""

    def __init__(self, n: int, delays: tuple[int, ...]) -> None:
        self.delays = np.asarray(delays, dtype=int)
        self.buffer = np.zeros((n, max(delays, default=0) + 1, 2))
        self.filled = False

    def reset(self) -> None:
        self.filled = False

    def push(self, p: np.ndarray) -> np.ndarray:
        """Record p (n, 2) as the current position; the delayed positions (n, D, 2)."""
        if not self.filled:
            self.buffer[:] = p[:, None, :]
            self.filled = True
        else:
            self.buffer[:, 1:] = self.buffer[:, :-1]
            self.buffer[:, 0] = p
        return self.buffer[:, self.delays]


class BoxQP:
    """min ½ Uᵀ H U + gᵀ U subject to |U| ≤ u_max, for a constant positive definite H."""

    def __init__(self, H: np.ndarray, u_max: float) -> None:
        self.H = H
        self.chol = cho_factor(H, lower=True)
        self.L = np.tril(self.chol[0])
        self.u_max = float(u_max)
        self.bounds = (-self.u_max, self.u_max)

    def solve(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(U (n, m), box active (n,)) for n gradients g (n, m)."""
        U = -cho_solve(self.chol, g.T).T
        outside = np.abs(U).max(axis=1) > self.u_max
        for i in np.flatnonzero(outside):
            b = -solve_triangular(self.L, g[i], lower=True)                     # ‖Lᵀ U − b‖²
            U[i] = lsq_linear(self.L.T, b, bounds=self.bounds, method='bvls').x
        return U, outside


class KoopmanLqrLaw:
    """Koopman-LQR: u = u_d + K (ψ(x) − z_d), saturated (module doc)."""

    def __init__(self, koopman: KoopmanModel, weights: Weights, u_max: float, n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3) -> None:
        check_period(koopman, dt)
        self.io = LawIO(koopman.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        self.koopman = koopman
        self.tracking = LiftedTracking(koopman, weights, block=1)
        self.history = DelayHistory(self.io.n_fingers, koopman.settings.delays)

    def reset(self) -> None:
        self.io.reset()
        self.history.reset()

    def lifted(self, pos, vel, ref_pos, ref_vel, ref_acc):
        """(z (n, n_z), x_d, a_d, finite, acc_ok) for a step, the history advanced by one period.
        A non-finite p̈_d row is taken as zero (``acc_ok`` False: the step is flagged fallback)."""
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        a_d, acc_ok = reference_acceleration(ref_acc, self.io.n_fingers)
        z = self.koopman.lift(x, self.history.push(x[:, :2]))
        return z, xd, a_d, finite, acc_ok

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        z, xd, a_d, finite, acc_ok = self.lifted(pos, vel, ref_pos, ref_vel, ref_acc)
        zd = self.tracking.reference(xd, a_d, 2)
        u = self.tracking.feedforward(zd)[:, 0] + (z - zd[:, 0]) @ self.tracking.K.T
        step = self.io.finish(u, finite)
        step.fallback |= ~acc_ok
        return step


class KoopmanMpcLaw(KoopmanLqrLaw):
    """Koopman MPC: the box-constrained QP over ``horizon`` blocks of ``block`` periods (module
    doc)."""

    def __init__(self, koopman: KoopmanModel, weights: Weights, u_max: float, n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 horizon: int = MPC_HORIZON, block: int = MPC_BLOCK) -> None:
        super().__init__(koopman, weights, u_max, n_fingers, lowpass_hz, dt)
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f'horizon must be an integer >= 1 (blocks), got {horizon!r}')
        self.horizon = N = int(horizon)
        self.blocks = t = LiftedTracking(koopman, weights, block=block)
        nz = koopman.n_z
        powers = [np.eye(nz)]
        for _ in range(N):
            powers.append(t.A @ powers[-1])
        self.Phi = np.concatenate(powers[1:], axis=0)                          # (N nz, nz): z_{j+1}
        Gamma = np.zeros((N * nz, 2 * N))
        for j in range(N):
            for i in range(j + 1):
                Gamma[j * nz:(j + 1) * nz, 2 * i:2 * i + 2] = powers[j - i] @ t.B
        W = np.kron(np.eye(N), t.Qz)
        W[-nz:, -nz:] = t.P                                                    # terminal cost-to-go
        Rbar = np.kron(np.eye(N), t.R)
        self.qp = BoxQP(Gamma.T @ W @ Gamma + Rbar, self.io.u_max)
        self.WGamma, self.Rbar = W @ Gamma, Rbar

    def gradient(self, z: np.ndarray, zd: np.ndarray, ud: np.ndarray) -> np.ndarray:
        """g (n, 2N) of the condensed QP from z (n, nz), the lifted reference at the N+1 block
        starts zd (n, N+1, nz) and its inputs ud (n, N, 2)."""
        n = len(z)
        E = (z @ self.Phi.T) - zd[:, 1:].reshape(n, -1)                        # free response − z_d
        return E @ self.WGamma - ud.reshape(n, -1) @ self.Rbar

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        z, xd, a_d, finite, acc_ok = self.lifted(pos, vel, ref_pos, ref_vel, ref_acc)
        zd = self.blocks.reference(xd, a_d, self.horizon + 1)
        with np.errstate(over='ignore', invalid='ignore'):
            g = self.gradient(z, zd, self.blocks.feedforward(zd))
        # a state far off the lifting's range overflows its features: that finger rests
        finite_gradient = np.isfinite(g).all(axis=1)
        if finite_gradient.all():
            U, active = self.qp.solve(g)
        else:
            U, active = np.zeros_like(g), np.zeros(len(g), dtype=bool)
            if finite_gradient.any():
                U[finite_gradient], active[finite_gradient] = self.qp.solve(g[finite_gradient])
        step = self.io.finish(U[:, :2], finite & finite_gradient)
        step.fallback |= ~acc_ok
        step.saturated = active[:, None] & (np.abs(U[:, :2]) >= self.io.u_max * (1 - 1e-9))
        return step


def check_period(koopman: KoopmanModel, dt: float) -> None:
    """The delay coordinates count control periods: the law's must be the model's."""
    if not np.isclose(koopman.dt, dt, rtol=1e-9):
        raise ValueError(f'the Koopman model was fitted at a {koopman.dt:g} s period, the law runs '
                         f'at {dt:g} s')


def _koopman(s: LawSettings, law=KoopmanMpcLaw, koopman_path=None):
    shape = model_shape(s.model)
    if not hand_path(shape, law_bounds(shape, s.u_max, s.bounds)):
        raise ShapeError(f'the Koopman laws are the hand\'s ({HAND_SHAPE}, bounds ±u_max on both '
                         f'inputs); this model has {shape}'
                         + ('' if s.bounds is None else f' and bounds {s.bounds}'))
    try:
        koopman = KoopmanModel.load(koopman_path)
    except KoopmanFileError as exc:
        raise ValueError(f'koopman_path: {exc}') from None
    fitted = (koopman.d, koopman.B.shape[1])
    if fitted != (HAND_SHAPE.d, HAND_SHAPE.m):
        raise ValueError(f'koopman_path: {koopman_path or "the shipped model"} was fitted to a tip '
                         f'of {fitted[0]} coordinates and {fitted[1]} input(s); the Koopman laws '
                         f'are the hand\'s ({HAND_SHAPE})')
    u_max = s.u_max if s.bounds is None else s.bounds.symmetric_limit
    return law(koopman, s.weights, u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz, dt=s.dt)


def _koopman_lqr(s: LawSettings, koopman_path=None):
    return _koopman(s, KoopmanLqrLaw, koopman_path)


register_law('koopman_mpc', _koopman, ('koopman_path',), params=WEIGHT_PARAMS, graph=True,
             summary='the Koopman baseline\'s linear MPC on the shipped Koopman model '
             '(models/koopman.npz; docs/results.md "Koopman baseline")',
             meanings={'koopman_path': 'the Koopman model file'})
register_law('koopman_lqr', _koopman_lqr, ('koopman_path',), params=WEIGHT_PARAMS, graph=True,
             summary='the Koopman baseline\'s LQR on the same lifted model')
