"""The reference Riccati solver (scipy) and the SDRE's checks in their general form.

For each finger, with A = A(x), G = G(x) from the learned model (the paper's eq. 23–24):

    P A + Aᵀ P + Q − P G R⁻¹ Gᵀ P = 0                       (24, stabilising solution)
    K = −R⁻¹ Gᵀ P,   A_cl = A − G R⁻¹ Gᵀ P,   K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q      (23)

and the checks of Remarks 2–3, each a bit of :class:`Check`: (A, G) stabilisable, (A, Q^½)
detectable, everything finite, P symmetric positive definite with a small residual, A_cl Hurwitz
and invertible. These hold for any (A, G) of any size: a state of 2d (d = 2 or 3 tip coordinates)
and m inputs (the finger's :class:`~soft_gripper_sdre.sim.shape.FingerShape`); the compiled kernels
(:mod:`~soft_gripper_sdre.control.kernels`) have cheaper versions for the hand's SDC structure,
A = [[0, I], [A21 A22]] and G = [[0], [G2]] with 2×2 blocks.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag

import numpy as np
from scipy.linalg import solve_continuous_are, solve_continuous_lyapunov

from soft_gripper_sdre.control.batched_linalg import well_conditioned_2x2


class Check(IntFlag):
    """The SDRE's checks: bits of
    :attr:`~soft_gripper_sdre.control.tracking.LawStep.failed_checks`."""

    STABILIZABLE = 1
    DETECTABLE = 2
    HURWITZ = 4
    ACL_SINGULAR = 8
    SOLVE_FAILED = 16
    NONFINITE = 32
    RESIDUAL = 64
    P_NOT_PD = 128


_I2 = np.eye(2)
#: the rows of A that the SDC form fixes: Ẋ, Ẏ = [0 I] x
SDC_TOP_ROWS = np.hstack([np.zeros((2, 2)), _I2])


def sdc_top_rows(d: int) -> np.ndarray:
    """(d, 2d) the rows of A that the SDC form fixes, ṗ = [0 I] x (:data:`SDC_TOP_ROWS` for
    d = 2)."""
    return SDC_TOP_ROWS if d == 2 else np.hstack([np.zeros((d, d)), np.eye(d)])


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


def in_sdc_form(A: np.ndarray, G: np.ndarray) -> bool:
    """Every (A (n, 2d, 2d), G (n, 2d, m)) has the SDC form's top rows: A[:d] = [0 I], G[:d] = 0."""
    d = A.shape[1] // 2
    return bool((A[:, :d, :] == sdc_top_rows(d)).all()) and not G[:, :d, :].any()


def full_sdc_matrices(A2: np.ndarray, G2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A = [[0, I], A2] (n, 2d, 2d) and G = [[0], G2] (n, 2d, m) from the lower rows A2 (n, d, 2d),
    G2 (n, d, m)."""
    n, d, m = G2.shape
    A = np.zeros((n, 2 * d, 2 * d))
    A[:, :d, :] = sdc_top_rows(d)
    A[:, d:, :] = A2
    G = np.zeros((n, 2 * d, m))
    G[:, d:, :] = G2
    return A, G


def is_stabilizable(A: np.ndarray, B: np.ndarray, tol: float = 1e-9) -> bool:
    """(A, B) stabilisable by the PBH test: rank [A − λI, B] = n for every eigenvalue λ of A with
    Re λ ≥ 0."""
    n = A.shape[0]
    for lam in np.linalg.eigvals(A):
        if lam.real >= -tol:
            M = np.hstack([A - lam * np.eye(n), B])
            s = np.linalg.svd(M, compute_uv=False)
            if s[-1] < tol * max(1.0, s[0]):
                return False
    return True


def is_detectable(A: np.ndarray, C: np.ndarray, tol: float = 1e-9) -> bool:
    """(A, C) detectable: (Aᵀ, Cᵀ) stabilisable."""
    return is_stabilizable(A.T, C.T, tol)


def checked_weights(Q, R, u_max) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Q (2d, 2d), R (m, m), u_max (m,)) as float arrays, for a state of 2d (d = 2 or 3) and m
    inputs (1 to 4) read from the sizes of Q and R.

    Raises:
        ValueError: Q is not a symmetric PSD matrix of size 4 or 6, R not a symmetric PD matrix of
            size 1 to 4, or u_max not finite and > 0 (a scalar or one per input).
    """
    Q = np.asarray(Q, dtype=float)
    R = np.asarray(R, dtype=float)
    if (Q.ndim != 2 or Q.shape[0] != Q.shape[1] or Q.shape[0] not in (4, 6)
            or not np.all(np.isfinite(Q))):
        raise ValueError(f'Q must be a finite (2d, 2d) matrix with d = 2 or 3, got shape {Q.shape}')
    if not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q).min() < -1e-12 * max(1.0, np.abs(Q).max()):
        raise ValueError('Q must be symmetric positive semi-definite')
    if (R.ndim != 2 or R.shape[0] != R.shape[1] or not 1 <= R.shape[0] <= 4
            or not np.all(np.isfinite(R))):
        raise ValueError(f'R must be a finite (m, m) matrix with m = 1 to 4 inputs, got shape '
                         f'{R.shape}')
    if not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0:
        raise ValueError('R must be symmetric positive definite')
    m = R.shape[0]
    try:
        u_max = np.broadcast_to(np.asarray(u_max, dtype=float), (m,)).copy()
    except ValueError:
        raise ValueError(f'u_max must be a scalar or one limit per input ({m}), got '
                         f'{u_max!r}') from None
    if not np.all(np.isfinite(u_max)) or np.any(u_max <= 0):
        raise ValueError(f'u_max must be finite and > 0, got {u_max}')
    return Q, R, u_max


@dataclass(frozen=True)
class RiccatiCost:
    """The weights and what the general checks derive from them once (:func:`riccati_cost`)."""

    Q: np.ndarray                 # (2d, 2d) symmetric PSD
    R: np.ndarray                 # (m, m) symmetric PD
    R_inv: np.ndarray
    q_norm: float                 # ‖Q‖_F (at least 1e-300)
    q_half: np.ndarray            # Q^½
    q_definite: bool              # Q ≻ 0
    q_position_definite: bool     # Q's position block Q[:d, :d] ≻ 0


def riccati_cost(Q: np.ndarray, R: np.ndarray) -> RiccatiCost:
    """:class:`RiccatiCost` of weights already checked by :func:`checked_weights`."""
    scale = 1e-12 * max(1.0, np.abs(Q).max())
    d = Q.shape[0] // 2
    w, V = np.linalg.eigh(Q)
    return RiccatiCost(Q=Q, R=R, R_inv=np.linalg.inv(R), q_norm=max(np.linalg.norm(Q), 1e-300),
                       q_half=V @ np.diag(np.sqrt(np.clip(w, 0, None))) @ V.T,
                       q_definite=bool(np.linalg.eigvalsh(Q).min() > scale),
                       q_position_definite=bool(np.linalg.eigvalsh(Q[:d, :d]).min() > scale))


def solvability(A: np.ndarray, G: np.ndarray, finite: np.ndarray, sdc: bool, cost: RiccatiCost,
                cond_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Remark 3 for n fingers: (usable (n,), failed (n,) bits of STABILIZABLE and DETECTABLE).

    A finger is usable when it is ``finite``, (A, G) is stabilisable and (A, Q^½) detectable. In
    the hand's SDC form (``sdc``, 2×2 G2) stabilisable means G2 invertible, tested as
    cond(G2) < cond_max; in another SDC form, G2 (d, m) of full row rank (cond(G2) < cond_max over
    its d singular values) makes it controllable and a G2 of lower rank (one input, a 2-D tip)
    takes the PBH test; outside the SDC form the PBH test. Detectability holds for Q ≻ 0, and for
    a Q whose position block is ≻ 0 when A has the SDC rows [0 I] (Q^½ sees p and, through those
    rows, its rate); else the PBH test.
    """
    n = A.shape[0]
    d = A.shape[1] // 2
    failed = np.zeros(n, dtype=int)
    if sdc and G.shape[1:] == (4, 2):
        with np.errstate(all='ignore'):
            stab = finite & well_conditioned_2x2(G[:, 2:, :], cond_max)[0]
    elif sdc:
        full_rank = np.zeros(n, dtype=bool)
        if G.shape[2] >= d and finite.any():
            sv = np.linalg.svd(np.where(finite[:, None, None], G[:, d:, :], 0.0),
                               compute_uv=False)
            with np.errstate(all='ignore'):
                full_rank = finite & (sv[:, 0] < cond_max * sv[:, d - 1])
        stab = np.array([bool(full_rank[i]) or (bool(finite[i])
                                                and is_stabilizable(A[i], G[i]))
                         for i in range(n)], dtype=bool).reshape(n)
    else:
        stab = np.array([finite[i] and is_stabilizable(A[i], G[i]) for i in range(n)])
    failed[finite & ~stab] |= Check.STABILIZABLE
    if cost.q_definite:
        detect = np.ones(n, dtype=bool)
    elif (cost.q_position_definite and np.all(A[:, :d, :d] == 0.0)
          and np.all(A[:, :d, d:] == np.eye(d))):
        detect = np.ones(n, dtype=bool)
    else:
        detect = np.array([finite[i] and is_detectable(A[i], cost.q_half) for i in range(n)])
        failed[finite & ~detect] |= Check.DETECTABLE
    return finite & stab & detect, failed


@dataclass
class CheckedGains:
    """The gains of eq. 23 for n fingers and the checks they passed (:func:`checked_gains`)."""

    K: np.ndarray                # (n, m, 2d)
    Ks: np.ndarray               # (n, m, 2d)
    residual: np.ndarray         # (n,) ‖Res‖_F / ‖Q‖_F, NaN where there is no solution
    ok: np.ndarray               # (n,) every check passed and the gains are finite
    failed: np.ndarray           # (n,) bits of Check


def checked_gains(A: np.ndarray, G: np.ndarray, P: np.ndarray, usable: np.ndarray,
                  failed: np.ndarray, cost: RiccatiCost, residual_tol: float,
                  cond_max: float) -> CheckedGains:
    """K, K_s from P (n, 2d, 2d) and every check of eq. 23–24 and Remark 2, finger by finger.

    ``usable`` and ``failed`` are :func:`solvability`'s answer (``failed`` is updated in place); P
    is NaN where no solution was found. Checks: solved (P finite), residual < residual_tol, P ≻ 0,
    A_cl Hurwitz, A_cl invertible (cond(A_cl) < cond_max).
    """
    n = A.shape[0]
    solved = usable & np.all(np.isfinite(P), axis=(1, 2))
    failed[usable & ~solved] |= Check.SOLVE_FAILED
    Psafe = np.where(solved[:, None, None], P, 0.0)
    with np.errstate(over='ignore', invalid='ignore'):     # a G far off the data overflows:
        GRG = G @ cost.R_inv @ G.transpose(0, 2, 1)         # its checks fail below
        Res = Psafe @ A + A.transpose(0, 2, 1) @ Psafe + cost.Q - Psafe @ GRG @ Psafe
        residual = np.where(solved, np.linalg.norm(Res, axis=(1, 2)) / cost.q_norm, np.nan)
    failed[solved & ~(residual < residual_tol)] |= Check.RESIDUAL
    pd = np.zeros(n, dtype=bool)
    if solved.any():
        pd[solved] = np.linalg.eigvalsh(Psafe[solved]).min(axis=1) > 0
    failed[solved & ~pd] |= Check.P_NOT_PD

    Rinv_Gt = cost.R_inv @ G.transpose(0, 2, 1)                  # (n, m, 2d)
    with np.errstate(over='ignore', invalid='ignore'):
        K = -Rinv_Gt @ Psafe                                     # K = −R⁻¹GᵀP
        A_cl = A + G @ K                                         # A − G R⁻¹ Gᵀ P
    hurwitz = np.zeros(n, dtype=bool)
    invertible = np.zeros(n, dtype=bool)
    Ks = np.zeros(K.shape)
    # a finger whose A_cl overflowed is neither Hurwitz nor invertible (numpy's eigvals refuses it)
    closed = solved & np.all(np.isfinite(A_cl), axis=(1, 2))
    if closed.any():
        s = np.flatnonzero(closed)
        hurwitz[s] = np.all(np.linalg.eigvals(A_cl[s]).real < 0, axis=1)
        with np.errstate(all='ignore'):
            invertible[s] = np.linalg.cond(A_cl[s]) < cond_max
        ok_inv = s[invertible[s]]
        if ok_inv.size:
            # K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q
            Ks[ok_inv] = -Rinv_Gt[ok_inv] @ np.linalg.solve(
                A_cl[ok_inv].transpose(0, 2, 1),
                np.broadcast_to(cost.Q, (ok_inv.size,) + cost.Q.shape))
    failed[solved & ~hurwitz] |= Check.HURWITZ
    failed[solved & ~invertible] |= Check.ACL_SINGULAR
    ok = failed == 0
    ok &= np.all(np.isfinite(K), axis=(1, 2)) & np.all(np.isfinite(Ks), axis=(1, 2))
    return CheckedGains(K=K, Ks=Ks, residual=residual, ok=ok, failed=failed)


def newton_kleinman(A: np.ndarray, G: np.ndarray, P0: np.ndarray, cost: RiccatiCost,
                    iterations: int) -> np.ndarray:
    """The CARE's stabilising solution for one system by Newton–Kleinman from a warm start P0:

        K = R⁻¹ Gᵀ P_k,   (A − G K)ᵀ P_k+1 + P_k+1 (A − G K) = −(Q + Kᵀ R K)

    for at most ``iterations`` Lyapunov solves, stopping when an iterate changes by less than
    1e-12 of its norm. NaN where a solve fails; the caller's checks decide whether it is used."""
    P = P0
    try:
        for _ in range(iterations):
            K = cost.R_inv @ G.T @ P
            Ak = A - G @ K
            P_next = solve_continuous_lyapunov(Ak.T, -(cost.Q + K.T @ cost.R @ K))
            done = np.linalg.norm(P_next - P) <= 1e-12 * np.linalg.norm(P_next)
            P = P_next
            if done:
                break
    except (np.linalg.LinAlgError, ValueError):
        return np.full(P0.shape, np.nan)
    return 0.5 * (P + P.T)


def solve_and_check(A: np.ndarray, G: np.ndarray, finite: np.ndarray, sdc: bool, cost: RiccatiCost,
                    residual_tol: float, cond_max: float, warm: tuple | None = None
                    ) -> tuple[np.ndarray, CheckedGains, int]:
    """The reference path for n fingers: Remark 3 (:func:`solvability`), scipy's solution for every
    usable finger and every check of :func:`checked_gains`.

    ``finite`` (n,) says which fingers' A, G and states are finite (the others are flagged
    NONFINITE and not solved; their A, G may hold anything). ``warm`` = (P (n, 2d, 2d), which (n,),
    iterations): those usable fingers first take :func:`newton_kleinman` from P, and scipy solves
    only the ones whose result fails a check. Returns (P (n, 2d, 2d), NaN where not solved; the
    checked gains; how many scipy solves were attempted).
    """
    A = np.where(finite[:, None, None], A, 0.0)
    G = np.where(finite[:, None, None], G, 0.0)
    usable, failed = solvability(A, G, finite, sdc, cost, cond_max)
    failed[~finite] |= Check.NONFINITE
    P = np.full(A.shape, np.nan)
    if warm is not None:
        P_warm, warm_rows, iterations = warm
        tried = usable & warm_rows
        for i in np.flatnonzero(tried):
            P[i] = newton_kleinman(A[i], G[i], P_warm[i], cost, iterations)
        trial = checked_gains(A, G, P, tried, failed.copy(), cost, residual_tol, cond_max)
        trial.ok &= tried | ~usable             # a usable finger not tried is solved below
        solves = np.flatnonzero(usable & ~trial.ok)
        if solves.size == 0:
            return P, trial, 0
        P[solves] = np.nan
    else:
        solves = np.flatnonzero(usable)
    for i in solves:
        try:
            P[i] = care(A[i], G[i], cost.Q, cost.R)
        except (np.linalg.LinAlgError, ValueError):
            pass                                     # stays NaN: SOLVE_FAILED
    if warm is None:
        return P, checked_gains(A, G, P, usable, failed, cost, residual_tol, cond_max), len(solves)
    exact = np.zeros(len(A), dtype=bool)
    exact[solves] = True
    checked = checked_gains(A[exact], G[exact], P[exact], usable[exact], failed[exact], cost,
                            residual_tol, cond_max)
    for name in ('K', 'Ks', 'residual', 'ok', 'failed'):
        getattr(trial, name)[exact] = getattr(checked, name)
    return P, trial, len(solves)
