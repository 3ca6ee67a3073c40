"""The SDRE kernels compiled with numba (``@njit``, plain loops over fingers, no Python objects):
the fused SDC network, one finger's warm-started Newton–Kleinman solve with its structured checks
and gains, and the laws built on them for n fingers. They take the settings, state and outputs as
record arrays, one record per finger (:mod:`soft_gripper_sdre.control.compiled` defines them and
:func:`~soft_gripper_sdre.control.compiled.warm_up`); the derivations are in
docs/design/compiled_kernel.md.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.compiled_cache import kernel

#: the bits of riccati.Check (written out: the compiled code keeps the values it was compiled with)
(STABILIZABLE, HURWITZ, ACL_SINGULAR, SOLVE_FAILED, NONFINITE, RESIDUAL,
 P_NOT_PD) = 1, 4, 8, 16, 32, 64, 128

# A symmetric 4×4 P has 10 unknowns: its upper triangle row by row, entry e = (ROW[e], COL[e]);
# SYM[i, j] is the unknown holding P[i, j] = P[j, i].
ROW, COL = (np.asarray(a, dtype=np.int64) for a in np.triu_indices(4))
SYM = np.zeros((4, 4), dtype=np.int64)
SYM[ROW, COL] = SYM[COL, ROW] = np.arange(10)


# ----------------------------------------------------------------------------------------------
# small dense linear algebra
# ----------------------------------------------------------------------------------------------

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


# ----------------------------------------------------------------------------------------------
# Newton–Kleinman and the checks, one finger
# ----------------------------------------------------------------------------------------------

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
      − Res) and ‖Res‖₂ < tol ‖Q‖_F (Lyapunov; docs/design/compiled_kernel.md);
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
        failed |= HURWITZ
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


# ----------------------------------------------------------------------------------------------
# the SDC networks
# ----------------------------------------------------------------------------------------------

@kernel
def network_arrays(network, hidden):
    """(layers, scratch) of the packed network: the layers w1 (4, h), b1 (h,), w2 (h, h), b2 (h,),
    w3 (h, 12), b3 (12,) as views of ``network``, which holds them one after the other
    (h = ``hidden``); the activations h1 (h,), h2 (h,), out (12,) that :func:`finger_blocks` works
    in, three arrays so that the compiler knows a store to one leaves the others unchanged."""
    h = hidden
    e1 = 4 * h
    e2 = e1 + h
    e3 = e2 + h * h
    e4 = e3 + h
    e5 = e4 + 12 * h
    layers = (network[:e1].reshape((4, h)), network[e1:e2], network[e2:e3].reshape((h, h)),
              network[e3:e4], network[e4:e5].reshape((h, 12)), network[e5:e5 + 12])
    return layers, (np.empty(h), np.empty(h), np.empty(12))


@kernel
def finger_blocks(x, layers, scratch, a2, g2):
    """a2 (2, 4) = [A21 A22](x) and g2 (2, 2) = G2(x) for one state x (4,): the fused network
    (``layers`` and ``scratch`` from :func:`network_arrays`).

    A negative hidden unit (ReLU: 0) is skipped; NaN is not, so a non-finite state gives
    non-finite blocks.
    """
    w1, b1, w2, b2, w3, b3 = layers
    h1, h2, out = scratch
    hidden = b1.shape[0]
    h1[:] = b1
    for k in range(4):
        for j in range(hidden):
            h1[j] += x[k] * w1[k, j]
    h2[:] = b2
    for k in range(hidden):
        if h1[k] < 0.0:
            continue                                   # relu(h) = 0
        for j in range(hidden):
            h2[j] += h1[k] * w2[k, j]
    out[:] = b3
    for k in range(hidden):
        if h2[k] < 0.0:
            continue
        for j in range(12):
            out[j] += h2[k] * w3[k, j]
    for r in range(2):
        for c in range(4):
            a2[r, c] = out[4 * r + c]
        for c in range(2):
            g2[r, c] = out[8 + 2 * r + c]


@kernel
def sdc_forward(x, network, hidden, a2, g2):
    """a2 (n, 2, 4) = [A21 A22](x) and g2 (n, 2, 2) = G2(x) for states x (n, 4): the fused network,
    packed (:func:`network_arrays`)."""
    layers, scratch = network_arrays(network, hidden)
    for i in range(x.shape[0]):
        finger_blocks(x[i], layers, scratch, a2[i], g2[i])


@kernel
def finite_finger(a2, g2, x, x_d):
    """Every model output and state entry of one finger is finite."""
    ok = True
    for r in range(2):
        for c in range(4):
            ok &= np.isfinite(a2[r, c]) and np.isfinite(x[c]) and np.isfinite(x_d[c])
        for c in range(2):
            ok &= np.isfinite(g2[r, c])
    return ok


# ----------------------------------------------------------------------------------------------
# the SDRE step for n fingers, the laws
# ----------------------------------------------------------------------------------------------

@kernel
def sdre_gains(finite, settings, state, outputs):
    """Gains of every warm finger with finite inputs (``finite``) by warm-started Newton–Kleinman
    and the checks, on the blocks a2, g2 in ``outputs``; the state records (P, warm, K, Ks) are
    updated in place.

    The warm fingers iterate together and stop at the first iteration where Σ ⟨Δ_low, W Δ_low⟩ <
    residual_tol ‖Q‖_F / 2 over them; a finger whose solve fails leaves the sum. A finger keeps its
    previous K, K_s and ends with warm False when it was cold or any check failed (``failed``: the
    Check bits; NONFINITE and STABILIZABLE hold for cold fingers too).
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


@kernel
def tracking_torques(x, x_d, finite, settings, state, outputs):
    """u = K x + K_s x_d (eq. 22) with the state's gains, saturated to ±u_max, into ``outputs``;
    zero for a finger whose inputs are not all finite, and wherever the product is not finite."""
    u_max = settings[0].u_max
    for i in range(x.shape[0]):
        K, Ks, out = state[i].K, state[i].Ks, outputs[i]
        for r in range(2):
            v = 0.0
            if finite[i]:
                for c in range(4):
                    v += K[r, c] * x[i, c] + Ks[r, c] * x_d[i, c]
                if not np.isfinite(v):
                    v = 0.0
            out.u_unsat[r] = v
            out.u[r] = min(max(v, -u_max[r]), u_max[r])


@kernel
def sdre_step(x, x_d, settings, state, outputs):
    """One step of the SDRE tracking law for the SDC blocks a2, g2 at x in ``outputs``
    (:meth:`SdreController.step_sdc` for warm fingers; the caller solves exactly the fingers that
    end with warm False)."""
    n = x.shape[0]
    finite = np.empty(n, dtype=np.bool_)
    for i in range(n):
        finite[i] = finite_finger(outputs[i].a2, outputs[i].g2, x[i], x_d[i])
    sdre_gains(finite, settings, state, outputs)
    tracking_torques(x, x_d, finite, settings, state, outputs)


@kernel
def rest_frame_states(z, origin, x, x_d):
    """x = [p − p₀, ṗ], x_d = [p_d − p₀, ṗ_d] (n, 4) from the rows z = [p, ṗ, p_d, ṗ_d, …]
    (RestFrame.states)."""
    for i in range(z.shape[0]):
        for k in range(2):
            x[i, k], x[i, 2 + k] = z[i, k] - origin[k], z[i, 2 + k]
            x_d[i, k], x_d[i, 2 + k] = z[i, 4 + k] - origin[k], z[i, 6 + k]


@kernel
def tracking_step(z, origin, network, hidden, settings, state, outputs):
    """SdreLaw.compute before its roll-off: the paper's law on the model's blocks at the estimated
    states, z (n, 8) = [p, ṗ, p_d, ṗ_d] the base-frame positions and velocities of the estimate and
    the reference, origin = the rest tip p₀ (2,), the packed network of ``hidden`` units."""
    n = z.shape[0]
    x, x_d = np.empty((n, 4)), np.empty((n, 4))
    rest_frame_states(z, origin, x, x_d)
    layers, scratch = network_arrays(network, hidden)
    for i in range(n):
        finger_blocks(x[i], layers, scratch, outputs[i].a2, outputs[i].g2)
    sdre_step(x, x_d, settings, state, outputs)


@kernel
def finger_inversion(a2, g2, x_d, a_d, cond_max, u_ff):
    """u_ff (2,) = G2⁻¹ (a_d − A2 x_d) for one finger; whether it is usable: zero and False where
    cond(G2) ≥ cond_max or the result is not finite."""
    r0, r1 = a_d[0], a_d[1]
    for c in range(4):
        r0 -= a2[0, c] * x_d[c]
        r1 -= a2[1, c] * x_d[c]
    det = g2[0, 0] * g2[1, 1] - g2[0, 1] * g2[1, 0]
    u0, u1 = (g2[1, 1] * r0 - g2[0, 1] * r1) / det, (g2[0, 0] * r1 - g2[1, 0] * r0) / det
    usable = well_conditioned(g2, cond_max) and np.isfinite(u0) and np.isfinite(u1)
    u_ff[0], u_ff[1] = (u0, u1) if usable else (0.0, 0.0)
    return usable


@kernel
def model_inversion(a2, g2, x_d, a_d, cond_max, u_ff, usable):
    """u_ff = G2⁻¹ (a_d − A2 x_d) (laws.model_inversion) for n fingers: zero and ``usable`` False
    where cond(G2) ≥ cond_max or the result is not finite."""
    for i in range(x_d.shape[0]):
        usable[i] = finger_inversion(a2[i], g2[i], x_d[i], a_d[i], cond_max, u_ff[i])


@kernel
def feedforward_step(z, origin, ff_at_reference, network, hidden, settings, state, outputs,
                     feedforward):
    """SdreFeedforwardLaw.compute before its roll-off:

        u = u_ff + K(x) e,   e = x − x_d,   u_ff = G2(z)⁻¹ (a_d − A2(z) x_d),   z = x or x_d

    (``ff_at_reference``: z = x_d), from the rows z (n, 10) = [p, ṗ, p_d, ṗ_d, a_d] (base frames). A
    finger whose state or reference is not finite is solved at x = x_d = 0 and gets u = 0
    (``state_finite`` False in its ``feedforward`` record); a non-finite a_d counts as zero. The
    ``feedforward`` records also get ``ff_usable`` (the feedforward acted and a_d was finite), u_ff
    (the feedforward part of u_unsat) and a2_ff, g2_ff (the blocks at z).
    """
    n = z.shape[0]
    x, x_d, e, zero = np.empty((n, 4)), np.empty((n, 4)), np.empty((n, 4)), np.zeros((n, 4))
    a_d, finite = np.empty((n, 2)), np.empty(n, dtype=np.bool_)
    rest_frame_states(z, origin, x, x_d)
    layers, scratch = network_arrays(network, hidden)
    for i in range(n):
        out, ff = outputs[i], feedforward[i]
        ff.state_finite = np.all(np.isfinite(x[i])) and np.all(np.isfinite(x_d[i]))
        if not ff.state_finite:
            x[i], x_d[i] = 0.0, 0.0
        finger_blocks(x[i], layers, scratch, out.a2, out.g2)
        if ff_at_reference:
            finger_blocks(x_d[i], layers, scratch, ff.a2_ff, ff.g2_ff)
        else:
            ff.a2_ff[:], ff.g2_ff[:] = out.a2, out.g2
        e[i] = x[i] - x_d[i]
        finite[i] = finite_finger(out.a2, out.g2, e[i], zero[i])
    sdre_gains(finite, settings, state, outputs)
    tracking_torques(e, zero, finite, settings, state, outputs)          # u_unsat = K e
    s = settings[0]
    for i in range(n):
        out, ff = outputs[i], feedforward[i]
        acc_finite = np.isfinite(z[i, 8]) and np.isfinite(z[i, 9])
        for r in range(2):
            a_d[i, r] = z[i, 8 + r] if acc_finite else 0.0
        usable = finger_inversion(ff.a2_ff, ff.g2_ff, x_d[i], a_d[i], s.cond_max, ff.u_ff)
        ff.ff_usable = usable and acc_finite
        for r in range(2):
            v = ff.u_ff[r] + out.u_unsat[r]
            if not (ff.state_finite and np.isfinite(v)):
                v = 0.0
            out.u_unsat[r] = v
            out.u[r] = min(max(v, -s.u_max[r]), s.u_max[r])
