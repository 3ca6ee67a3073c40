"""One finger's warm-started Newton–Kleinman solve of the SDRE with the SDC structure's checks and
gains, and the solve for n fingers (:func:`sdre_gains`), compiled with numba: the fast counterpart
of :mod:`~soft_gripper_sdre.control.riccati`. They take the settings, state and outputs as record
arrays, one record per finger (:mod:`~soft_gripper_sdre.control.kernels`); the derivations are in
docs/design/compiled_kernel.md, "One step, per finger".
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel
from soft_gripper_sdre.control.kernels.linalg import (
    COL,
    ROW,
    SYM,
    lyapunov_operator,
    positive_definite,
    quadratic_term,
    solve_in_place,
    well_conditioned,
)

#: the bits of riccati.Check, written out in a kernel module: the compiled code keeps the values it
#: was compiled with, and the kernels' cache follows the kernel modules' sources alone
(STABILIZABLE, HURWITZ, ACL_SINGULAR, SOLVE_FAILED, NONFINITE, RESIDUAL,
 P_NOT_PD) = 1, 4, 8, 16, 32, 64, 128
#: the sign iteration's most steps and its relative change at convergence
#: (:func:`hamiltonian_solve`)
SIGN_ITERATIONS, SIGN_TOL = 50, 1e-13


@kernel
def newton_kleinman_step(A, W, q, P, WP, PSP, A_k, L, p):
    """One Newton–Kleinman step for one SDC finger, in place: P_k → P_k+1, the solution of

        A_kᵀ P_k+1 + P_k+1 A_k = −(Q + P_k S P_k),   A_k = A − S P_k,

    a 10×10 system in P's upper triangle; WP = W P_low and PSP = P S P follow P (they must hold
    those of P_k on entry). Returns ⟨Δ_low, W Δ_low⟩ (Δ = P_k+1 − P_k), which bounds
    ‖Res(P_k+1)‖_F since Res(P_k+1) = −Δ S Δ; NaN (and P NaN) when the solve fails.
    """
    A_k[:, :] = A
    for r in range(2):
        for c in range(4):
            A_k[2 + r, c] -= WP[r, c]                                # A_k = A − S P_k
    lyapunov_operator(A_k, L)
    for e in range(10):
        p[e] = -(q[ROW[e], COL[e]] + PSP[ROW[e], COL[e]])           # −(Q + P_k S P_k)
    if not solve_in_place(L, p):
        P[:, :] = np.nan
        return np.nan
    bound = 0.0                                                      # ⟨Δ_low, W Δ_low⟩
    for c in range(4):
        d0, d1 = p[SYM[2, c]] - P[2, c], p[SYM[3, c]] - P[3, c]
        bound += d0 * (W[0, 0] * d0 + W[0, 1] * d1) + d1 * (W[1, 0] * d0 + W[1, 1] * d1)
    for i in range(4):
        for j in range(4):
            P[i, j] = p[SYM[i, j]]
    quadratic_term(P, W, WP, PSP)
    return bound


@kernel
def finger_checks(A, P, WP, PSP, settings, q_norm, C, N, work):
    """(failed Check bits, relative residual) of one finger's solution P, A_cl = A − S P, with the
    settings record's Q, residual_tol and cond_max.

    * residual ‖PA + AᵀP + Q − P S P‖_F / ‖Q‖_F < residual_tol, formed directly from P;
    * P ≻ 0 and N = Q + P S P − 2 tol ‖Q‖_F I ≻ 0 prove A_cl Hurwitz: A_clᵀP + PA_cl = −(N + margin
      − Res) and ‖Res‖₂ < tol ‖Q‖_F (Lyapunov; docs/design/compiled_kernel.md); where that
      sufficient proof fails (a slow loop's Q = diag(q_pos I, 0) leaves N's velocity block
      under the margin), A_cl = A − S P's eigenvalues decide, as in the general kernels;
    * A_cl = [[0, I], [C, ·]] is invertible with cond(C) < cond_max, the only inverse K_s uses.
    """
    q, residual_tol = settings.q, settings.residual_tol
    failed = 0
    for i in range(4):
        for j in range(4):
            if not np.isfinite(P[i, j]):
                return SOLVE_FAILED, np.nan
    res2 = 0.0
    for i in range(4):
        for j in range(4):
            pa, ap = 0.0, 0.0
            for m in range(4):
                pa += P[i, m] * A[m, j]
                ap += A[m, i] * P[m, j]
            r = pa + ap + q[i, j] - PSP[i, j]
            res2 += r * r
    residual = np.sqrt(res2) / q_norm
    if not residual < residual_tol:
        failed |= RESIDUAL
    if not positive_definite(P, work):
        failed |= P_NOT_PD
    margin = 2.0 * residual_tol * q_norm
    for i in range(4):
        for j in range(4):
            N[i, j] = q[i, j] + PSP[i, j] - (margin if i == j else 0.0)
    if not positive_definite(N, work):
        # the Lyapunov argument is sufficient only: A_cl = A − S P's eigenvalues decide
        A_cl = np.zeros((4, 4), dtype=np.complex128)
        A_cl[0, 2] = A_cl[1, 3] = 1.0
        finite = True
        for r in range(2):
            for c in range(4):
                A_cl[2 + r, c] = A[2 + r, c] - WP[r, c]
                finite = finite and np.isfinite(A_cl[2 + r, c].real)
        if not finite:                     # S P overflowed: numba's eigvals refuses it
            failed |= HURWITZ
        else:
            for v in np.linalg.eigvals(A_cl):
                if not v.real < 0.0:
                    failed |= HURWITZ
                    break
    for r in range(2):
        for c in range(2):
            C[r, c] = A[2 + r, c] - WP[r, c]
    if not well_conditioned(C, settings.cond_max):
        failed |= ACL_SINGULAR
    return failed, residual


@kernel
def finger_gains(B, P, C, q, K, Ks):
    """K = −B P_low and K_s = −B C⁻ᵀ Q[:2, :] with B = R⁻¹ G2ᵀ (eq. 23 in the SDC form:
    Gᵀ A_cl⁻ᵀ = G2ᵀ [C⁻ᵀ, 0]); C⁻ᵀ = [[c11, −c10], [−c01, c00]] / det C."""
    det = C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]
    c00, c01, c10, c11 = C[1, 1] / det, -C[1, 0] / det, -C[0, 1] / det, C[0, 0] / det
    for r in range(2):
        for c in range(4):
            K[r, c] = -(B[r, 0] * P[2, c] + B[r, 1] * P[3, c])
            ciq0 = c00 * q[0, c] + c01 * q[1, c]                    # (C⁻ᵀ Q[:2, :])[0, c]
            ciq1 = c10 * q[0, c] + c11 * q[1, c]
            Ks[r, c] = -(B[r, 0] * ciq0 + B[r, 1] * ciq1)


@kernel
def finger_setup(a2, g2, r_inv, P, A, W, B, WP, PSP):
    """One finger's matrices for Newton–Kleinman, in place: A = [[0, I], [a2]] (A zero on entry),
    B = R⁻¹ G2ᵀ, W = G2 R⁻¹ G2ᵀ, and WP, PSP of the warm start P (:func:`quadratic_term`)."""
    for r in range(2):
        for c in range(2):
            B[r, c] = r_inv[r, 0] * g2[c, 0] + r_inv[r, 1] * g2[c, 1]          # R⁻¹ G2ᵀ
    for r in range(2):
        for c in range(2):
            W[r, c] = g2[r, 0] * B[0, c] + g2[r, 1] * B[1, c]                  # G2 R⁻¹ G2ᵀ
    A[0, 2] = A[1, 3] = 1.0                                          # Ẋ, Ẏ rows: [0 I]
    A[2:, :] = a2
    quadratic_term(P, W, WP, PSP)


@kernel
def finger_accept(A, B, WP, PSP, settings, q_norm, state, out, work):
    """The checks on one finger's solution, its state record's P (:func:`finger_checks`, bits and
    residual into its outputs record ``out``); if it passes them all and its gains are finite, they
    become the state's K, K_s and ``warm`` is True, else the state keeps its gains and ``warm`` is
    False. ``work``: scratch (C (2, 2), N (4, 4), Cholesky (4, 4), K (2, 4), K_s (2, 4))."""
    C, N, cholesky, K, Ks = work
    out.failed, out.residual = finger_checks(A, state.P, WP, PSP, settings, q_norm, C, N, cholesky)
    if out.failed == 0:
        finger_gains(B, state.P, C, settings.q, K, Ks)
        if np.all(np.isfinite(K)) and np.all(np.isfinite(Ks)):
            state.K[:], state.Ks[:] = K, Ks
        else:
            out.failed = NONFINITE
    state.warm = out.failed == 0


@kernel
def hamiltonian_solve(A, W, q, P):
    """The stabilizing solution of AᵀP + PA − P S P + Q = 0 into P (k × k), from scratch, for the
    SDC structure's S = [[0, 0], [0, W]] (W = G2 R⁻¹ G2ᵀ, d × d, in the lower right), by the
    matrix sign function of the Hamiltonian H = [[A, −S], [−Q, −Aᵀ]]: Newton's iteration
    Z ← (Z / c + c Z⁻¹) / 2 with c = |det Z|^(1/2k) converges to sign(H), whose blocks give P as
    the solution of [Z₁₂; Z₂₂ + I] P = −[Z₁₁ + I; Z₂₁] (a consistent 2k × k system, solved by
    least squares), symmetrized. For a finger whose warm-started Newton–Kleinman ended unstable:
    tens of µs where an exact scipy solve costs milliseconds. False (P untouched) when A, W or Q
    is not finite (W overflows for a G2 far off the data), or the iteration does not converge or
    meets a singular or non-finite Z; the caller's checks judge P either way."""
    k, d = A.shape[0], W.shape[0]
    n = 2 * k
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(W)) and np.all(np.isfinite(q))):
        return False                       # W = G2 R⁻¹ G2ᵀ overflowed: numba's det refuses it
    Z = np.zeros((n, n))
    for i in range(k):
        for j in range(k):
            Z[i, j] = A[i, j]
            Z[k + i, k + j] = -A[j, i]
            Z[k + i, j] = -q[i, j]
    for r in range(d):
        for c in range(d):
            Z[k - d + r, n - d + c] = -W[r, c]
    power = 1.0 / n
    converged = False
    for _ in range(SIGN_ITERATIONS):
        det = np.linalg.det(Z)
        if not (np.isfinite(det) and det != 0.0):
            return False
        c = abs(det) ** power
        Z_next = 0.5 * (Z / c + c * np.linalg.inv(Z))
        change, size = 0.0, 0.0
        for i in range(n):
            for j in range(n):
                change += abs(Z_next[i, j] - Z[i, j])
                size += abs(Z_next[i, j])
        Z = Z_next
        if not np.isfinite(size):
            return False
        if change <= SIGN_TOL * size:
            converged = True
            break
    if not converged:
        return False
    M, N = np.empty((n, k)), np.empty((n, k))
    for i in range(k):
        for j in range(k):
            M[i, j] = Z[i, k + j]
            M[k + i, j] = Z[k + i, k + j] + (1.0 if i == j else 0.0)
            N[i, j] = -(Z[i, j] + (1.0 if i == j else 0.0))
            N[k + i, j] = -Z[k + i, j]
    X = np.linalg.lstsq(M, N)[0]
    for i in range(k):
        for j in range(k):
            P[i, j] = 0.5 * (X[i, j] + X[j, i])
    return True


@kernel
def sdre_gains(finite, settings, state, outputs):
    """Gains of every warm finger with finite inputs (``finite``) by warm-started Newton–Kleinman
    and the checks, on the blocks a2, g2 in ``outputs``; the state records (P, warm, K, Ks) are
    updated in place.

    The warm fingers iterate together and stop at the first iteration where Σ ⟨Δ_low, W Δ_low⟩ <
    residual_tol ‖Q‖_F / 2 over them; a finger whose solve fails leaves the sum. A warm finger that
    fails a check is solved again from scratch (:func:`restart`). A finger keeps its previous K,
    K_s and ends with warm False when it was cold or still fails (``failed``: the Check bits;
    NONFINITE and STABILIZABLE hold for cold fingers too).
    """
    s = settings[0]
    n = state.shape[0]
    A, W, B = np.zeros((n, 4, 4)), np.empty((n, 2, 2)), np.empty((n, 2, 2))
    WP, PSP = np.empty((n, 2, 4)), np.empty((n, 4, 4))
    A_k, L, p = np.empty((4, 4)), np.empty((10, 10)), np.empty(10)
    work = (np.empty((2, 2)), np.empty((4, 4)), np.zeros((4, 4)), np.empty((2, 4)),
            np.empty((2, 4)))
    q_norm = max(np.sqrt(np.sum(s.q * s.q)), 1e-300)
    half_tol_q = 0.5 * s.residual_tol * q_norm
    solving = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        st, out = state[i], outputs[i]
        out.residual, out.iterations, out.failed = np.nan, 0, 0
        if not finite[i]:
            out.failed = NONFINITE
        elif not well_conditioned(out.g2, s.cond_max):      # rank [G, AG] = 4 iff G2 invertible
            out.failed = STABILIZABLE
        solving[i] = st.warm and out.failed == 0
        st.warm = False
        if solving[i]:
            finger_setup(out.a2, out.g2, s.r_inv, st.P, A[i], W[i], B[i], WP[i], PSP[i])
    for iteration in range(1, s.max_iterations + 1):
        total = 0.0
        for i in range(n):
            P = state[i].P
            if solving[i] and np.isfinite(P[0, 0]):                  # (a failed solve leaves P NaN)
                bound = newton_kleinman_step(A[i], W[i], s.q, P, WP[i], PSP[i], A_k, L, p)
                outputs[i].iterations = iteration
                if np.isfinite(bound):
                    total += bound
        if total < half_tol_q:
            break
    for i in range(n):
        if solving[i]:
            finger_accept(A[i], B[i], WP[i], PSP[i], s, q_norm, state[i], outputs[i], work)
            if not state[i].warm and outputs[i].failed & NONFINITE == 0:
                restart(A[i], W[i], B[i], WP[i], PSP[i], s, q_norm, half_tol_q, state[i],
                        outputs[i], A_k, L, p, work)


@kernel
def restart(A, W, B, WP, PSP, s, q_norm, half_tol_q, st, out, A_k, L, p, work):
    """A warm finger whose Newton–Kleinman ended unstable or short of the tolerance (the SDC
    blocks moved too far since its last solution): solved again from scratch
    (:func:`hamiltonian_solve`), refined by Newton–Kleinman, which converges quadratically from a
    stabilizing start, and checked again. Its ``iterations`` count the refinement's too; still
    failing, it ends cold for the exact path."""
    P = st.P
    if not hamiltonian_solve(A, W, s.q, P):
        P[:, :] = np.nan
        return
    quadratic_term(P, W, WP, PSP)
    for _ in range(s.max_iterations):
        bound = newton_kleinman_step(A, W, s.q, P, WP, PSP, A_k, L, p)
        out.iterations += 1
        if not bound >= half_tol_q:                  # converged, or NaN: the checks tell
            break
    finger_accept(A, B, WP, PSP, s, q_norm, st, out, work)

