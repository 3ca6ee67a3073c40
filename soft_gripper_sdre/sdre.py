"""SDRE tracking control (the paper's eq. 22–24 with the checks of Remarks 2–3), batched over fingers.

For each finger, with A = A(x), G = G(x) from the learned model:

    P A + Aᵀ P + Q − P G R⁻¹ Gᵀ P = 0                       (24, stabilising solution)
    K = −R⁻¹ Gᵀ P,   A_cl = A − G R⁻¹ Gᵀ P,   K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q      (23)
    u = K x + K_s x_d, saturated to ±u_max                  (22)

Checks at every step (Remarks 2–3): (A, G) stabilisable, (A, Q^½) detectable, A_cl Hurwitz and
invertible, P symmetric positive definite, everything finite, small Riccati residual. A finger whose
step fails any check uses its last valid gains (fallback), or the gains of a nominal model before it
has any, or zero torque; the failure is counted. ``u`` is always finite.

Two solvers give the same P:

* ``'reference'`` — scipy's ``solve_continuous_are`` per finger (Schur method), general PBH checks.
* ``'fast'`` — Newton–Kleinman warm-started from each finger's previous P: each iteration solves
  the Lyapunov equation A_kᵀ P + P A_k = −(Q + K_kᵀ R K_k), A_k = A − G K_k, for all fingers at once
  as 16×16 linear systems (Kronecker form). A tracked state moves little in 1 ms, so one or two
  iterations reach a residual of 1e-10; otherwise (cold start, residual above tolerance, A_k not
  Hurwitz) that finger falls back to the exact solve. Structure-aware checks: with
  A = [[0, I], [·, ·]] and G = [[0], [G2]], rank [G, AG] = 4 iff G2 is invertible, so (A, G) is
  controllable (hence stabilisable) exactly when G2 is well conditioned; detectability holds for
  Q ≻ 0 (otherwise the general PBH test runs).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag

import numpy as np
from scipy.linalg import solve_continuous_are

from soft_gripper_sdre.units import LENGTH_SCALE, TORQUE_SCALE

METHODS = ('fast', 'reference')


class Check(IntFlag):
    """Bits of :attr:`SdreStep.failed_checks`."""

    STABILIZABLE = 1
    DETECTABLE = 2
    HURWITZ = 4
    ACL_SINGULAR = 8
    SOLVE_FAILED = 16
    NONFINITE = 32
    RESIDUAL = 64
    P_NOT_PD = 128


@dataclass
class SdreStep:
    """One control step for n fingers."""

    u: np.ndarray                # (n, 2) saturated torques, always finite
    u_unsat: np.ndarray          # (n, 2)
    K: np.ndarray                # (n, 2, 4) gains in use
    Ks: np.ndarray               # (n, 2, 4)
    P: np.ndarray                # (n, 4, 4) (NaN where the solve failed)
    residual: np.ndarray         # (n,) ‖PA + AᵀP + Q − PGR⁻¹GᵀP‖_F / ‖Q‖_F
    ok: np.ndarray               # (n,) every check passed
    fallback: np.ndarray         # (n,) fallback gains (or zero) used
    failed_checks: np.ndarray    # (n,) int bitmask of Check
    saturated: np.ndarray        # (n, 2)
    nk_iterations: np.ndarray    # (n,) Newton–Kleinman iterations (0 = exact solve)


def paper_weights_si() -> tuple[np.ndarray, np.ndarray]:
    """The paper's Q = diag(2,2,2,2), R = diag(0.1,0.1) (sim units) in SI.

    Positions and velocities scale by 20 (x_sim = 20 x_si) and torques by 400, so the cost
    x_simᵀ Q_sim x_sim + u_simᵀ R_sim u_sim equals x_siᵀ (400 Q_sim) x_si + u_siᵀ (160000 R_sim) u_si.
    """
    return (LENGTH_SCALE**2 * np.diag([2.0, 2.0, 2.0, 2.0]),
            TORQUE_SCALE**2 * np.diag([0.1, 0.1]))


def _check_weights(Q, R, u_max) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    Q = np.asarray(Q, dtype=float)
    R = np.asarray(R, dtype=float)
    if Q.shape != (4, 4) or not np.all(np.isfinite(Q)):
        raise ValueError(f'Q must be a finite (4, 4) matrix, got shape {Q.shape}')
    if not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q).min() < -1e-12 * max(1.0, np.abs(Q).max()):
        raise ValueError('Q must be symmetric positive semi-definite')
    if R.shape != (2, 2) or not np.all(np.isfinite(R)):
        raise ValueError(f'R must be a finite (2, 2) matrix, got shape {R.shape}')
    if not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0:
        raise ValueError('R must be symmetric positive definite')
    u_max = np.broadcast_to(np.asarray(u_max, dtype=float), (2,)).copy()
    if not np.all(np.isfinite(u_max)) or np.any(u_max <= 0):
        raise ValueError(f'u_max must be finite and > 0, got {u_max}')
    return Q, R, u_max


_CHECK_BITS = tuple((c.name, int(c)) for c in Check)
_I2 = np.eye(2)


def care(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Stabilising solution of PA + AᵀP + Q − PBR⁻¹BᵀP = 0 (reference: scipy, one system)."""
    return solve_continuous_are(A, B, Q, R)


def sdre_gains(A, G, Q, R) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, K_s, P) of eq. 23–24 for one system, for readers and tests."""
    P = care(A, G, Q, R)
    Rinv_Gt = np.linalg.solve(R, G.T)
    K = -Rinv_Gt @ P
    A_cl = A + G @ K
    Ks = -Rinv_Gt @ np.linalg.solve(A_cl.T, Q)        # −R⁻¹ Gᵀ A_cl⁻ᵀ Q
    return K, Ks, P


def _pbh_fails(A: np.ndarray, B: np.ndarray, tol: float = 1e-9) -> bool:
    """True when some eigenvalue λ of A with Re λ ≥ 0 has rank [A − λI, B] < n (PBH test)."""
    n = A.shape[0]
    for lam in np.linalg.eigvals(A):
        if lam.real >= -tol:
            M = np.hstack([A - lam * np.eye(n), B])
            s = np.linalg.svd(M, compute_uv=False)
            if s[-1] < tol * max(1.0, s[0]):
                return True
    return False


def _lyap_batch(Ak: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Solve A_kᵀ P + P A_k = −M for a batch (n,4,4) via (I ⊗ A_kᵀ + A_kᵀ ⊗ I) vec P = −vec M."""
    n = Ak.shape[0]
    I4 = np.eye(4)
    AT = Ak.transpose(0, 2, 1)
    # row-major vec: vec(X Y Z) = (X ⊗ Zᵀ) vec(Y); A_kᵀ P → (A_kᵀ ⊗ I), P A_k → (I ⊗ A_kᵀ)
    L = np.einsum('nij,kl->nikjl', AT, I4).reshape(n, 16, 16) + \
        np.einsum('ij,nkl->nikjl', I4, AT).reshape(n, 16, 16)
    P = np.linalg.solve(L, -M.reshape(n, 16, 1)).reshape(n, 4, 4)
    return 0.5 * (P + P.transpose(0, 2, 1))


class SdreController:
    """The SDRE tracking law for ``n`` fingers with fallbacks and counters.

    Args:
        Q: (4, 4) state weight, symmetric PSD (SI).
        R: (2, 2) input weight, symmetric PD (SI).
        u_max: torque saturation per input [N·m] (scalar or (2,)).
        n: number of fingers.
        method: ``'fast'`` or ``'reference'``.
        residual_tol: largest accepted relative Riccati residual.
        cond_max: largest accepted condition number of G2 and of A_cl.
        nominal: optional (A0, G0) whose gains serve as the fallback before any valid step.
    """

    def __init__(self, Q, R, u_max, n: int = 4, method: str = 'fast', residual_tol: float = 1e-6,
                 cond_max: float = 1e8, max_nk_iterations: int = 2, nominal=None) -> None:
        self.Q, self.R, self.u_max = _check_weights(Q, R, u_max)
        if method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {method!r}')
        self.n, self.method = int(n), method
        self.residual_tol, self.cond_max = float(residual_tol), float(cond_max)
        self.max_nk = int(max_nk_iterations)
        self._Rinv = np.linalg.inv(self.R)
        self._q_norm = max(np.linalg.norm(self.Q), 1e-300)
        self._q_pd = np.linalg.eigvalsh(self.Q).min() > 1e-12 * max(1.0, np.abs(self.Q).max())
        self._q_pos_pd = np.linalg.eigvalsh(self.Q[:2, :2]).min() > 1e-12 * max(1.0, np.abs(self.Q).max())
        w, V = np.linalg.eigh(self.Q)
        self._q_half = V @ np.diag(np.sqrt(np.clip(w, 0, None))) @ V.T
        self._nominal = None
        if nominal is not None:
            K0, Ks0, _ = sdre_gains(np.asarray(nominal[0], float), np.asarray(nominal[1], float),
                                    self.Q, self.R)
            self._nominal = (K0, Ks0)
        self.reset()

    def reset(self) -> None:
        """Forget warm starts and last valid gains; zero the counters."""
        self._P = np.full((self.n, 4, 4), np.nan)
        self._K = np.zeros((self.n, 2, 4))
        self._Ks = np.zeros((self.n, 2, 4))
        self._have = np.zeros(self.n, dtype=bool)
        if self._nominal is not None:
            self._K[:] = self._nominal[0]
            self._Ks[:] = self._nominal[1]
        self.steps = 0
        self.fallbacks = 0
        self.exact_solves = 0
        self.check_failures = {c.name: 0 for c in Check}

    # -- solvers -----------------------------------------------------------------------------
    def _exact(self, A, G, i) -> np.ndarray:
        self.exact_solves += 1
        try:
            return care(A[i], G[i], self.Q, self.R)
        except (np.linalg.LinAlgError, ValueError):
            return np.full((4, 4), np.nan)

    def _solve(self, A, G, usable) -> tuple[np.ndarray, np.ndarray]:
        P = np.full((self.n, 4, 4), np.nan)
        iters = np.zeros(self.n, dtype=int)
        if self.method == 'reference':
            for i in np.flatnonzero(usable):
                P[i] = self._exact(A, G, i)
            return P, iters
        warm = usable & np.all(np.isfinite(self._P), axis=(1, 2))
        if warm.any():
            idx = np.flatnonzero(warm)
            Pk = self._P[idx]
            Aw, Gw = A[idx], G[idx]
            good = np.ones(idx.size, dtype=bool)
            for _ in range(self.max_nk):
                Kk = np.einsum('ij,njk,nkl->nil', self._Rinv, Gw.transpose(0, 2, 1), Pk)  # R⁻¹GᵀP
                Ak = Aw - Gw @ Kk                                                        # A − G K_k
                good &= np.all(np.linalg.eigvals(Ak).real < 0, axis=1)
                M = self.Q + Kk.transpose(0, 2, 1) @ self.R @ Kk                          # Q + KᵀRK
                with np.errstate(all='ignore'):
                    Pk = _lyap_batch(Ak, M)
                iters[idx] += 1
                res = self._residual(Aw, Gw, Pk)
                if np.all(res < 1e-3 * self.residual_tol):
                    break
            res = self._residual(Aw, Gw, Pk)
            good &= np.isfinite(res) & (res < self.residual_tol)
            P[idx[good]] = Pk[good]
            warm[idx[~good]] = False
        for i in np.flatnonzero(usable & ~warm):
            P[i] = self._exact(A, G, i)
            iters[i] = 0
        return P, iters

    def _residual(self, A, G, P) -> np.ndarray:
        GRG = G @ self._Rinv @ G.transpose(0, 2, 1)
        Res = P @ A + A.transpose(0, 2, 1) @ P + self.Q - P @ GRG @ P
        return np.linalg.norm(Res, axis=(1, 2)) / self._q_norm

    # -- the law -----------------------------------------------------------------------------
    def step(self, A, G, x, x_d) -> SdreStep:
        """Torques for every finger: A (n,4,4), G (n,4,2), x (n,4), x_d (n,4), translated SI."""
        A = np.asarray(A, dtype=float)
        G = np.asarray(G, dtype=float)
        x = np.asarray(x, dtype=float)
        x_d = np.asarray(x_d, dtype=float)
        n = self.n
        for name, a, shape in (('A', A, (n, 4, 4)), ('G', G, (n, 4, 2)), ('x', x, (n, 4)),
                               ('x_d', x_d, (n, 4))):
            if a.shape != shape:
                raise ValueError(f'{name} must have shape {shape}, got {a.shape}')
        self.steps += 1
        failed = np.zeros(n, dtype=int)
        finite = (np.all(np.isfinite(A), axis=(1, 2)) & np.all(np.isfinite(G), axis=(1, 2))
                  & np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(x_d), axis=1))
        failed[~finite] |= Check.NONFINITE
        A = np.where(finite[:, None, None], A, 0.0)
        G = np.where(finite[:, None, None], G, 0.0)

        # Remark 3: (A, G) stabilisable, (A, Q^½) detectable
        if self.method == 'fast':
            with np.errstate(all='ignore'):
                cond_g = np.linalg.cond(G[:, 2:, :])
            stab = finite & np.isfinite(cond_g) & (cond_g < self.cond_max)
        else:
            stab = np.array([finite[i] and not _pbh_fails(A[i], G[i]) for i in range(n)])
        failed[finite & ~stab] |= Check.STABILIZABLE
        if self._q_pd:
            detect = np.ones(n, dtype=bool)
        elif self._q_pos_pd and np.all(A[:, :2, :2] == 0.0) and np.all(A[:, :2, 2:] == _I2):
            # SDC structure A = [[0, I], ·] with Q weighting both positions: C = Q^½ sees X, Y and,
            # through the [0 I] rows, their rates, so (A, Q^½) is observable for every x
            detect = np.ones(n, dtype=bool)
        else:
            detect = np.array([finite[i] and not _pbh_fails(A[i].T, self._q_half.T) for i in range(n)])
            failed[finite & ~detect] |= Check.DETECTABLE
        usable = finite & stab & detect

        P, iters = self._solve(A, G, usable)
        solved = usable & np.all(np.isfinite(P), axis=(1, 2))
        failed[usable & ~solved] |= Check.SOLVE_FAILED
        Psafe = np.where(solved[:, None, None], P, 0.0)
        residual = np.where(solved, self._residual(A, G, Psafe), np.nan)
        failed[solved & ~(residual < self.residual_tol)] |= Check.RESIDUAL
        pd = np.zeros(n, dtype=bool)
        if solved.any():
            pd[solved] = np.linalg.eigvalsh(Psafe[solved]).min(axis=1) > 0
        failed[solved & ~pd] |= Check.P_NOT_PD

        # eq. 23 and Remark 2: A_cl Hurwitz and invertible
        Rinv_Gt = self._Rinv @ G.transpose(0, 2, 1)                  # (n, 2, 4)
        K = -Rinv_Gt @ Psafe                                         # K = −R⁻¹GᵀP
        A_cl = A + G @ K                                             # A − G R⁻¹ Gᵀ P
        hurwitz = np.zeros(n, dtype=bool)
        invertible = np.zeros(n, dtype=bool)
        Ks = np.zeros((n, 2, 4))
        if solved.any():
            s = np.flatnonzero(solved)
            hurwitz[s] = np.all(np.linalg.eigvals(A_cl[s]).real < 0, axis=1)
            with np.errstate(all='ignore'):
                invertible[s] = np.linalg.cond(A_cl[s]) < self.cond_max
            ok_inv = s[invertible[s]]
            if ok_inv.size:
                # K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q
                Ks[ok_inv] = -Rinv_Gt[ok_inv] @ np.linalg.solve(A_cl[ok_inv].transpose(0, 2, 1),
                                                                np.broadcast_to(self.Q, (ok_inv.size, 4, 4)))
        failed[solved & ~hurwitz] |= Check.HURWITZ
        failed[solved & ~invertible] |= Check.ACL_SINGULAR
        ok = failed == 0
        ok &= np.all(np.isfinite(K), axis=(1, 2)) & np.all(np.isfinite(Ks), axis=(1, 2))

        # accept or fall back
        self._K[ok] = K[ok]
        self._Ks[ok] = Ks[ok]
        self._have |= ok
        self._P[ok] = P[ok]
        self._P[~ok] = np.nan            # no warm start from a rejected solve
        fallback = ~ok
        use_zero = fallback & ~self._have & (self._nominal is None)
        Kuse, Ksuse = self._K.copy(), self._Ks.copy()
        Kuse[use_zero] = 0.0
        Ksuse[use_zero] = 0.0
        xs = np.where(finite[:, None], x, 0.0)
        xds = np.where(finite[:, None], x_d, 0.0)
        u_unsat = np.einsum('nij,nj->ni', Kuse, xs) + np.einsum('nij,nj->ni', Ksuse, xds)   # eq. 22
        u_unsat = np.where(np.isfinite(u_unsat), u_unsat, 0.0)
        u_unsat[~finite] = 0.0            # no torque from a state we cannot read
        u = np.clip(u_unsat, -self.u_max, self.u_max)
        saturated = np.abs(u_unsat) > self.u_max

        self.fallbacks += int(fallback.sum())
        if failed.any():
            for name, bit in _CHECK_BITS:
                self.check_failures[name] += int(np.count_nonzero(failed & bit))
        return SdreStep(u=u, u_unsat=u_unsat, K=Kuse, Ks=Ksuse, P=P, residual=residual, ok=ok,
                        fallback=fallback, failed_checks=failed, saturated=saturated,
                        nk_iterations=iters)
