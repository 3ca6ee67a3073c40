"""The fast SDRE kernel: warm-started Newton–Kleinman on the SDC structure, with its checks.

For a model in SDC form, A = [[0, I], [A21, A22]] and G = [[0], [G2]], so each finger is given by
its lower rows a = [A21 A22] (2×4) and G2 (2×2). :func:`structured_gains` solves the Riccati
equation of m such fingers at once from warm starts, runs the structure's cheap checks and forms
the gains [K K_s]; the supervisor (:class:`~soft_gripper_sdre.control.sdre.SdreController`) sends
any finger that fails a check to scipy's solver (:mod:`~soft_gripper_sdre.control.riccati`).

The boundary is plain arrays and numbers: :func:`kernel_constants` (called once) turns the weights
into a :class:`KernelConstants` tuple, :func:`structured_gains` maps arrays and that tuple to a
:class:`StructuredGains` tuple, and nothing here keeps state, so a compiled kernel with the same
signatures can replace this module. The derivations (operator tables, stop rule, checks) are in
docs/design/fast_riccati.md.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.batched_linalg import batched_cholesky, batched_solve, well_conditioned_2x2

# ----------------------------------------------------------------------------------------------
# the SDC structure, tabulated once
# ----------------------------------------------------------------------------------------------
# A symmetric 4×4 P has 10 unknowns p, its upper triangle row by row.
_ROWS, _COLS = np.triu_indices(4)
#: p = P.reshape(16)[UPPER_TRIANGLE]
UPPER_TRIANGLE = 4 * _ROWS + _COLS
#: P = p[SYMMETRIC_FROM_UPPER].reshape(4, 4)
SYMMETRIC_FROM_UPPER = np.array([[int(np.flatnonzero((_ROWS == min(i, j)) & (_COLS == max(i, j)))[0])
                                  for j in range(4)] for i in range(4)]).reshape(16)
#: P[2:, :] = p[LOWER_ROWS_FROM_UPPER].reshape(2, 4): with G = [[0], [G2]] these rows are all of P
#: that Gᵀ sees (Gᵀ P = G2ᵀ P[2:, :])
LOWER_ROWS_FROM_UPPER = SYMMETRIC_FROM_UPPER.reshape(4, 4)[2:, :].reshape(8)
#: the rows of A that the SDC form fixes: Ẋ, Ẏ = [0 I] x
SDC_TOP_ROWS = np.hstack([np.zeros((2, 2)), np.eye(2)])
#: adj(C)ᵀ = _ADJUGATE_SIGNS ∘ C[::-1, ::-1] for a 2×2 C, so C⁻ᵀ = _ADJUGATE_SIGNS ∘ C[::-1, ::-1] / det C
_ADJUGATE_SIGNS = np.array([[1.0, -1.0], [-1.0, 1.0]])
#: weights of the upper-triangle entries in ‖S‖_F² of a symmetric 4×4 S (off-diagonals count twice)
_FROBENIUS_WEIGHTS = np.where(_ROWS == _COLS, 1.0, 2.0)


def _lyapunov_tables() -> tuple[np.ndarray, np.ndarray]:
    """The Lyapunov operator of an SDC matrix as an affine function of its lower rows c (2×4):
    upper triangle of −(Aᵀ P + P A) = (BASE + c.reshape(8) @ SLOPES).reshape(10, 10) @ p.
    Returns (BASE (100,), SLOPES (8, 100)); the entries are small integers, exact in floating point."""
    basis = [np.eye(10)[j][SYMMETRIC_FROM_UPPER].reshape(4, 4) for j in range(10)]

    def operator(A: np.ndarray) -> np.ndarray:
        return np.stack([(-(A.T @ B + B @ A)).reshape(16)[UPPER_TRIANGLE] for B in basis], axis=1)

    top = np.zeros((4, 4))
    top[:2] = SDC_TOP_ROWS
    slopes = []
    for r in range(2):
        for s in range(4):
            E = np.zeros((4, 4))
            E[2 + r, s] = 1.0
            slopes.append(operator(E).reshape(100))
    return operator(top).reshape(100), np.stack(slopes)


#: L(A) = (LYAPUNOV_BASE + c.reshape(8) @ LYAPUNOV_SLOPES).reshape(10, 10) for A = [[0, I], [c]]:
#: L(A) p is the upper triangle of −(Aᵀ P + P A)
LYAPUNOV_BASE, LYAPUNOV_SLOPES = _lyapunov_tables()


def upper_triangle(S: np.ndarray) -> np.ndarray:
    """(m, 4, 4) → (m, 10): the upper triangle, row by row (the order of p)."""
    return S.reshape(-1, 16).take(UPPER_TRIANGLE, axis=1)


def full_sdc_matrices(A2: np.ndarray, G2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A = [[0, I], A2] (n, 4, 4) and G = [[0], G2] (n, 4, 2) from the lower rows A2 (n, 2, 4), G2 (n, 2, 2)."""
    n = A2.shape[0]
    A = np.zeros((n, 4, 4))
    A[:, :2, :] = SDC_TOP_ROWS
    A[:, 2:, :] = A2
    G = np.zeros((n, 4, 2))
    G[:, 2:, :] = G2
    return A, G


class KernelConstants(NamedTuple):
    """What :func:`structured_gains` needs of the weights and settings. The (n, …) arrays repeat
    one constant for n fingers (sliced to [:m]): an elementwise operation between arrays of one
    shape skips numpy's broadcasting set-up."""

    neg_R_inv: np.ndarray          # (2, 2) −R⁻¹
    lyapunov_base: np.ndarray      # (n, 100) LYAPUNOV_BASE
    q_upper: np.ndarray            # (n, 10) Q's upper triangle
    q_shifted: np.ndarray          # (n, 4, 4) Q − 2 residual_tol ‖Q‖_F I (the Lyapunov test's margin)
    adjugate_signs: np.ndarray     # (n, 2, 2)
    q_top: np.ndarray              # (2, 4) Q[:2, :] (K_s)
    residual_weights: np.ndarray   # (10,) ‖S‖_F² / ‖Q‖_F² = (S's upper triangle)² @ residual_weights
    stop_threshold: float          # residual_tol ‖Q‖_F / 2: Newton–Kleinman's stop rule
    residual_tol: float            # largest accepted ‖Res‖_F / ‖Q‖_F
    cond_max: float                # largest accepted cond(G2) and cond(C)
    max_iterations: int


def kernel_constants(Q: np.ndarray, R: np.ndarray, n: int, residual_tol: float, cond_max: float,
                     max_iterations: int) -> KernelConstants:
    """The kernel's constants for weights Q (4, 4) and R (2, 2), already checked, and n fingers."""
    q_norm = max(np.linalg.norm(Q), 1e-300)

    def tile(c):
        return np.ascontiguousarray(np.broadcast_to(c, (n,) + np.shape(c)))
    return KernelConstants(
        neg_R_inv=-np.linalg.inv(R), lyapunov_base=tile(LYAPUNOV_BASE),
        q_upper=tile(Q.reshape(16)[UPPER_TRIANGLE]),
        q_shifted=tile(Q - 2.0 * residual_tol * q_norm * np.eye(4)),
        adjugate_signs=tile(_ADJUGATE_SIGNS), q_top=Q[:2, :].copy(),
        residual_weights=_FROBENIUS_WEIGHTS / q_norm**2, stop_threshold=0.5 * residual_tol * q_norm,
        residual_tol=float(residual_tol), cond_max=float(cond_max), max_iterations=int(max_iterations))


class StructuredGains(NamedTuple):
    """What :func:`structured_gains` found for m fingers (NaN where a solve failed)."""

    p: np.ndarray              # (m, 10) P's upper triangle: the next warm start
    P: np.ndarray              # (m, 4, 4)
    gains: np.ndarray          # (m, 2, 8) [K K_s]: u = gains @ [x; x_d]
    residual: np.ndarray       # (m,) ‖PA + AᵀP + Q − PGR⁻¹GᵀP‖_F / ‖Q‖_F
    iterations: int            # Newton–Kleinman iterations done (the same for all m)
    passed: np.ndarray         # (2m,) [G2 well conditioned and P ≻ 0; C well conditioned and N − margin ≻ 0]


def checks_passed(result: StructuredGains, constants: KernelConstants) -> np.ndarray:
    """(m,) every check of :func:`structured_gains` passed, finger by finger."""
    m = result.residual.shape[0]
    return result.passed[:m] & result.passed[m:] & (result.residual < constants.residual_tol)


def every_check_passed(result: StructuredGains, constants: KernelConstants) -> bool:
    """``checks_passed(…).all()``, by counting the flags that hold (cheaper than combining them)."""
    return (np.count_nonzero(result.passed) == result.passed.shape[0]
            and np.count_nonzero(result.residual < constants.residual_tol) == result.residual.shape[0])


def structured_gains(a: np.ndarray, g: np.ndarray, p0: np.ndarray, c: KernelConstants) -> StructuredGains:
    """Warm-started Newton–Kleinman, the structure's checks and the gains for m fingers in SDC form.

    Args:
        a: (m, 2, 4) lower rows [A21 A22] of A.
        g: (m, 2, 2) G2.
        p0: (m, 10) warm starts (upper triangles of P).
        c: the constants (m ≤ the n they were made for).

    Newton–Kleinman solves A_kᵀ P_{k+1} + P_{k+1} A_k = −(Q + P_k S P_k), S = G R⁻¹ Gᵀ, as one 10×10
    system per finger and stops once a bound on the next iterate's residual is below half the
    accepted one. The checks: (A, G) stabilisable and A_cl invertible (condition of G2 and of A_cl's
    lower-left block C), the residual formed directly from P, and P ≻ 0 with A_cl Hurwitz by a
    Lyapunov argument (one Cholesky of the stacked [P; Q + PSP − margin]). A failed solve or a
    non-finite input gives NaN, which fails the checks.
    """
    m = a.shape[0]
    q_upper = c.q_upper[:m]
    with np.errstate(all='ignore'):
        neg_G2_R_inv = g @ c.neg_R_inv                       # −G2 R⁻¹ = (−R⁻¹ G2ᵀ)ᵀ, R symmetric
        W = neg_G2_R_inv @ g.transpose(0, 2, 1)
        np.negative(W, out=W)                                # W = G2 R⁻¹ G2ᵀ
        L_open = a.reshape(m, 8) @ LYAPUNOV_SLOPES
        L_open += c.lyapunov_base[:m]                        # L(A), flattened
        L_A = L_open.reshape(m, 10, 10)
        P_low = p0.take(LOWER_ROWS_FROM_UPPER, axis=1).reshape(m, 2, 4)
        WP = W @ P_low                                       # S P (lower rows)
        PSP_upper = upper_triangle(P_low.transpose(0, 2, 1) @ WP)    # P S P = P_lowᵀ W P_low
        for iterations in range(1, c.max_iterations + 1):
            L = (L_open - WP.reshape(m, 8) @ LYAPUNOV_SLOPES).reshape(m, 10, 10)   # L(A − S P_k)
            p = batched_solve(L, PSP_upper + q_upper)        # A_kᵀP + PA_k = −(Q + P_k S P_k)
            P_next = p.take(LOWER_ROWS_FROM_UPPER, axis=1).reshape(m, 2, 4)
            D = P_next - P_low                               # lower rows of Δ_k = P_k+1 − P_k
            WP_next = W @ P_next
            WD = WP_next - WP                                # W Δ_low
            P_low, WP = P_next, WP_next
            PSP = P_low.transpose(0, 2, 1) @ WP
            PSP_upper = PSP.reshape(m, 16).take(UPPER_TRIANGLE, axis=1)
            # stop rule: ‖Res(P_k+1)‖_F ≤ ⟨Δ_low, W Δ_low⟩ per finger
            if np.vdot(D, WD) < c.stop_threshold:            # False for NaN: iterate on
                break
        res = np.matvec(L_A, p)
        res += PSP_upper
        res -= q_upper                                       # −Res = L(A)p + PSP − Q (upper)
        residual = np.sqrt((res * res) @ c.residual_weights)     # ‖Res‖_F / ‖Q‖_F
        P = p.take(SYMMETRIC_FROM_UPPER, axis=1).reshape(m, 4, 4)
        C = (a - WP)[:, :, :2]                               # A_cl = [[0, I], [C, D]] = A − S P
        # stabilisable (G2) and A_cl invertible (C), both 2×2 condition tests in one call
        well, det = well_conditioned_2x2(np.concatenate([g, C]), c.cond_max)
        # [K K_s] = −R⁻¹ G2ᵀ [P_low, C⁻ᵀ Q[:2, :]],  C⁻ᵀ = [[c11, −c10], [−c01, c00]] / det C
        C_inv_T_Q = (C[:, ::-1, ::-1] * c.adjugate_signs[:m]) @ c.q_top
        C_inv_T_Q /= det[m:, None, None]
        gains = neg_G2_R_inv.transpose(0, 2, 1) @ np.concatenate((P_low, C_inv_T_Q), axis=2)
        # P ≻ 0 and N − margin ≻ 0: both Cholesky factors exist. A failed one is all NaN, and
        # L₃₃ depends on every entry of the lower triangle, so a NaN in the input reaches it too
        # (+inf on a diagonal can leave L₃₃ finite or +inf; the residual, NaN then, rejects it)
        chol = batched_cholesky(np.concatenate([P, PSP + c.q_shifted[:m]]))
        passed = well & (chol[:, 3, 3] > 0.0)               # NaN > 0 is False
    return StructuredGains(p=p, P=P, gains=gains, residual=residual, iterations=iterations, passed=passed)
