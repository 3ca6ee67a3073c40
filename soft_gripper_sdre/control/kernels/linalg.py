"""Small dense linear algebra for the SDRE kernels, compiled with numba: the 2×2 condition test, the
4×4 Cholesky test, Gaussian elimination for the 10×10 Lyapunov system, that system's operator on
P's upper triangle, and the SDC form's quadratic term P S P (docs/design/compiled_kernel.md, "One
step, per finger").
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel

# A symmetric 4×4 P has 10 unknowns: its upper triangle row by row, entry e = (ROW[e], COL[e]);
# SYM[i, j] is the unknown holding P[i, j] = P[j, i].
ROW, COL = (np.asarray(a, dtype=np.int64) for a in np.triu_indices(4))
SYM = np.zeros((4, 4), dtype=np.int64)
SYM[ROW, COL] = SYM[COL, ROW] = np.arange(10)


@kernel
def well_conditioned(M, c_max):
    """cond₂(M) < c_max for a 2×2 M, without an SVD: with σ₁ ≥ σ₂, σ₁² + σ₂² = ‖M‖_F² and
    σ₁σ₂ = |det M|, so κ + 1/κ = ‖M‖_F² / |det M| and κ < c_max ⇔ ‖M‖_F² < (c_max + 1/c_max)
    |det M|. False for a singular or non-finite M."""
    fro2 = M[0, 0] ** 2 + M[0, 1] ** 2 + M[1, 0] ** 2 + M[1, 1] ** 2
    det = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    return fro2 < (c_max + 1.0 / c_max) * abs(det)


@kernel
def positive_definite(S, work):
    """S ≻ 0 for a symmetric 4×4 S: its Cholesky factor (built in ``work``) exists."""
    for j in range(4):
        d = S[j, j]
        for k in range(j):
            d -= work[j, k] * work[j, k]
        if not d > 0.0:                                    # also False for NaN
            return False
        work[j, j] = np.sqrt(d)
        for i in range(j + 1, 4):
            s = S[i, j]
            for k in range(j):
                s -= work[i, k] * work[j, k]
            work[i, j] = s / work[j, j]
    return True


@kernel
def solve_in_place(L, b):
    """Solve L y = b (small dense L) by Gaussian elimination with partial pivoting: b becomes y,
    L is overwritten (its diagonal by the pivots' reciprocals, so that back substitution multiplies
    instead of dividing). False when a pivot is zero or not finite (y is then meaningless)."""
    n = b.shape[0]
    for col in range(n):
        pivot, big = col, abs(L[col, col])
        for r in range(col + 1, n):
            if abs(L[r, col]) > big:
                pivot, big = r, abs(L[r, col])
        if not (0.0 < big < np.inf):
            return False
        if pivot != col:
            for c in range(col, n):
                L[col, c], L[pivot, c] = L[pivot, c], L[col, c]
            b[col], b[pivot] = b[pivot], b[col]
        inv = L[col, col] = 1.0 / L[col, col]
        for r in range(col + 1, n):
            f = L[r, col] * inv
            if f != 0.0:                                   # the Lyapunov operator is mostly zeros
                for c in range(col + 1, n):
                    L[r, c] -= f * L[col, c]
                b[r] -= f * b[col]
    for r in range(n - 1, -1, -1):
        s = b[r]
        for c in range(r + 1, n):
            s -= L[r, c] * b[c]
        b[r] = s * L[r, r]
    return True


@kernel
def lyapunov_operator(A, L):
    """L (10, 10) such that L p = upper triangle of AᵀP + PA for the symmetric P with unknowns p:
    (AᵀP + PA)_ij = Σ_m A_mi P_mj + P_im A_mj."""
    L[:, :] = 0.0
    for e in range(10):
        i, j = ROW[e], COL[e]
        for m in range(4):
            L[e, SYM[m, j]] += A[m, i]
            L[e, SYM[i, m]] += A[m, j]


@kernel
def quadratic_term(P, W, WP, PSP):
    """S P's lower rows WP = W P_low (2, 4) and P S P = P_lowᵀ W P_low (4, 4),
    S = [[0, 0], [0, W]]."""
    for r in range(2):
        for c in range(4):
            WP[r, c] = W[r, 0] * P[2, c] + W[r, 1] * P[3, c]
    for i in range(4):
        for j in range(4):
            PSP[i, j] = P[2, i] * WP[0, j] + P[3, i] * WP[1, j]

