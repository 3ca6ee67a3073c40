"""The SDRE laws' per-step work for a finger of any shape compiled with numba: d = 2 or 3 tip
coordinates, m = 1 to 4 inputs, per-input bounds [lower, upper]. The general path of the laws
(:func:`~soft_gripper_sdre.control.tracking.hand_path` False) calls them with ``method='fast'``;
the hand keeps its own kernels (:mod:`~soft_gripper_sdre.control.kernels.sdre`).

The sizes come from the arrays' shapes (a state of k = 2d, G2 (d, m)), so one compiled kernel
serves every shape. Each kernel does what the general numpy path does
(:mod:`~soft_gripper_sdre.control.riccati`, :mod:`~soft_gripper_sdre.control.laws.feedforward`,
:class:`~soft_gripper_sdre.control.laws.integral.ReachableIntegralAction`), in loops over fingers:

* the fused network of the shape, x (2d) ↦ [A21 A22] (d, 2d), G2 (d, m) (:func:`shaped_blocks`);
* Newton–Kleinman from each warm finger's last accepted P, at most ``max_iterations`` Lyapunov
  solves, stopping when an iterate changes by at most 1e-12 of its norm
  (:func:`finger_newton_kleinman`; :func:`~soft_gripper_sdre.control.riccati.newton_kleinman`'s
  iteration and rule), each Lyapunov equation solved as the linear system of P's upper triangle,
  k(k + 1)/2 unknowns;
* the checks of :func:`~soft_gripper_sdre.control.riccati.checked_gains` on the result (P finite,
  the relative residual, P ≻ 0, A_cl Hurwitz, cond(A_cl) < cond_max; Hurwitz and the condition
  number first by cheap sufficient tests, then, where those do not prove them, by the
  eigenvalues and singular values as numpy decides) and the gains K = −R⁻¹GᵀP,
  K_s = −R⁻¹GᵀA_cl⁻ᵀQ (:func:`finger_general_checks`);
* the torques u = K x + K_s x_d clipped to the bounds (:func:`general_torques`), the feedforward
  u_ff = G2⁺(a_d − A2 x_d) with its unreachable part (:func:`finger_pseudo_inversion`), the
  reachable integral's step (:func:`reachable_integral_update`).

A warm finger whose result fails a check is solved again from scratch (:func:`finger_restart`:
the Hamiltonian's sign function, then Newton–Kleinman and the checks again). A finger that is cold
(no accepted P yet, or its last step failed), whose inputs are not finite, or whose result still
fails a check ends with ``warm`` False and its previous gains: the supervisor
(:class:`~soft_gripper_sdre.control.sdre.SdreController`) solves it with scipy and the general
checks (:func:`~soft_gripper_sdre.control.riccati.solve_and_check`) and then forms the torques
(:func:`general_torques`). Stabilisability and detectability are not tested here: a result that
passes the Hurwitz test proves (A, G) stabilisable, and the supervisor uses these kernels only for
weights whose Q or position block is ≻ 0, which make (A, Q^½) detectable in the SDC form.

numba's linear algebra (eigenvalues, singular values, solves) raises on a non-finite matrix; the
kernels call it only on finite ones.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel
from soft_gripper_sdre.control.kernels.linalg import solve_in_place
from soft_gripper_sdre.control.kernels.riccati import hamiltonian_solve

#: the bits of riccati.Check these kernels set, written out (as in kernels/riccati.py)
(HURWITZ, ACL_SINGULAR, SOLVE_FAILED, NONFINITE, RESIDUAL, P_NOT_PD) = 4, 8, 16, 32, 64, 128
#: Newton–Kleinman stops when ‖P_k+1 − P_k‖_F ≤ this × ‖P_k+1‖_F (riccati.newton_kleinman's rule)
NK_STEP_TOL = 1e-12
#: the feedforward's closed form serves a G2 whose Gram matrix's bound ‖M‖_F‖M⁻¹‖_F is below this
#: (cond₂(G2) below about 1e4: the normal equations then lose at most some 1e-8 of the input);
#: a worse conditioned one takes the SVD
PROVEN_GRAM_COND = 1e8


@kernel
def shaped_network_arrays(network, hidden, n_in, n_out):
    """(layers, scratch) of a packed fused network of ``n_in`` = 2d inputs and ``n_out`` =
    2d² + dm outputs: w1 (n_in, h), b1 (h,), w2 (h, h), b2 (h,), w3 (h, n_out), b3 (n_out,) as views
    of ``network`` (h = ``hidden``), and the activations h1 (h,), h2 (h,), out (n_out,)."""
    h = hidden
    e1 = n_in * h
    e2 = e1 + h
    e3 = e2 + h * h
    e4 = e3 + h
    e5 = e4 + n_out * h
    layers = (network[:e1].reshape((n_in, h)), network[e1:e2], network[e2:e3].reshape((h, h)),
              network[e3:e4], network[e4:e5].reshape((h, n_out)), network[e5:e5 + n_out])
    return layers, (np.empty(h), np.empty(h), np.empty(n_out))


@kernel
def shaped_blocks(x, layers, scratch, a2, g2):
    """a2 (d, 2d) = [A21 A22](x) and g2 (d, m) = G2(x) for one state x (2d,): the fused network's
    output, row-major [A21 A22] then G2 (SDCModel.fused_network). A negative hidden unit (ReLU: 0)
    is skipped; NaN is not, so a non-finite state gives non-finite blocks."""
    w1, b1, w2, b2, w3, b3 = layers
    h1, h2, out = scratch
    hidden, n_in, n_out = b1.shape[0], x.shape[0], b3.shape[0]
    h1[:] = b1
    for k in range(n_in):
        for j in range(hidden):
            h1[j] += x[k] * w1[k, j]
    h2[:] = b2
    for k in range(hidden):
        if h1[k] < 0.0:
            continue
        for j in range(hidden):
            h2[j] += h1[k] * w2[k, j]
    out[:] = b3
    for k in range(hidden):
        if h2[k] < 0.0:
            continue
        for j in range(n_out):
            out[j] += h2[k] * w3[k, j]
    d, k2, m = a2.shape[0], a2.shape[1], g2.shape[1]
    for r in range(d):
        for c in range(k2):
            a2[r, c] = out[k2 * r + c]
        for c in range(m):
            g2[r, c] = out[d * k2 + m * r + c]


@kernel
def shaped_forward(x, network, hidden, a2, g2):
    """a2 (n, d, 2d), g2 (n, d, m) for states x (n, 2d): the packed fused network."""
    layers, scratch = shaped_network_arrays(network, hidden, x.shape[1],
                                            a2.shape[1] * a2.shape[2] + g2.shape[1] * g2.shape[2])
    for i in range(x.shape[0]):
        shaped_blocks(x[i], layers, scratch, a2[i], g2[i])


@kernel
def upper_index(i, j, k):
    """The unknown that holds P[i, j] = P[j, i] of a symmetric k × k P whose upper triangle is
    numbered row by row."""
    if i > j:
        i, j = j, i
    return i * k - (i * (i - 1)) // 2 + (j - i)


@kernel
def general_lyapunov_operator(A, L):
    """L (k(k+1)/2, k(k+1)/2) such that L p = the upper triangle of AᵀP + PA for the symmetric
    k × k P with unknowns p: (AᵀP + PA)_ij = Σ_m A_mi P_mj + P_im A_mj."""
    k = A.shape[0]
    L[:, :] = 0.0
    e = 0
    for i in range(k):
        for j in range(i, k):
            for m in range(k):
                L[e, upper_index(m, j, k)] += A[m, i]
                L[e, upper_index(i, m, k)] += A[m, j]
            e += 1


@kernel
def sdc_matrix(a2, A):
    """A (2d, 2d) = [[0, I], a2] for the lower rows a2 (d, 2d)."""
    d = a2.shape[0]
    A[:, :] = 0.0
    for r in range(d):
        A[r, d + r] = 1.0
        for c in range(2 * d):
            A[d + r, c] = a2[r, c]


@kernel
def finger_newton_kleinman(A, g2, B, q, r, P, iterations, work):
    """Newton–Kleinman for one SDC finger from the warm start P (k × k), in place:

        K = R⁻¹ Gᵀ P_j,   (A − G K)ᵀ P_j+1 + P_j+1 (A − G K) = −(Q + Kᵀ R K)

    with G = [[0], [g2]] and B = R⁻¹ g2ᵀ (m, d), for at most ``iterations`` solves, stopping when an
    iterate changes by at most :data:`NK_STEP_TOL` of its norm. Returns the solves run; P NaN
    where a solve fails. ``work``: scratch (A_k (k, k), K (m, k), L, p, P_next)."""
    A_k, K, L, p, P_next = work
    k, d, m = A.shape[0], g2.shape[0], g2.shape[1]
    for it in range(iterations):
        for a in range(m):
            for c in range(k):
                s = 0.0
                for rr in range(d):
                    s += B[a, rr] * P[d + rr, c]
                K[a, c] = s                                             # R⁻¹ Gᵀ P
        A_k[:, :] = A
        for rr in range(d):
            for c in range(k):
                s = 0.0
                for a in range(m):
                    s += g2[rr, a] * K[a, c]
                A_k[d + rr, c] -= s                                     # A − G K
        general_lyapunov_operator(A_k, L)
        e = 0
        for i in range(k):
            for j in range(i, k):
                s = 0.0
                for a in range(m):
                    t = 0.0
                    for b in range(m):
                        t += r[a, b] * K[b, j]
                    s += K[a, i] * t
                p[e] = -(q[i, j] + s)                                   # −(Q + Kᵀ R K)
                e += 1
        if not solve_in_place(L, p):
            P[:, :] = np.nan
            return it + 1
        change, size = 0.0, 0.0
        for i in range(k):
            for j in range(k):
                v = p[upper_index(i, j, k)]
                P_next[i, j] = v
                change += (v - P[i, j]) ** 2
                size += v * v
        P[:, :] = P_next
        if not np.isfinite(change):
            P[:, :] = np.nan
            return it + 1
        if np.sqrt(change) <= NK_STEP_TOL * np.sqrt(size):
            return it + 1
    return iterations


@kernel
def all_finite(M):
    """Every entry of the 2-D array M is finite."""
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            if not np.isfinite(M[i, j]):
                return False
    return True


@kernel
def cholesky_exists(S, work):
    """S ≻ 0 for a symmetric k × k S: its Cholesky factor (built in ``work``, k × k) exists."""
    k = S.shape[0]
    for j in range(k):
        d = S[j, j]
        for c in range(j):
            d -= work[j, c] * work[j, c]
        if not d > 0.0:                                        # also False for NaN
            return False
        work[j, j] = np.sqrt(d)
        for i in range(j + 1, k):
            s = S[i, j]
            for c in range(j):
                s -= work[i, c] * work[j, c]
            work[i, j] = s / work[j, j]
    return True


@kernel
def invert_in_place(M, out):
    """out = M⁻¹ for a small square M by Gauss–Jordan elimination with partial pivoting (M is
    overwritten); False when a pivot is zero or not finite."""
    n = M.shape[0]
    out[:, :] = 0.0
    for i in range(n):
        out[i, i] = 1.0
    for col in range(n):
        pivot, big = col, abs(M[col, col])
        for r in range(col + 1, n):
            if abs(M[r, col]) > big:
                pivot, big = r, abs(M[r, col])
        if not (0.0 < big < np.inf):
            return False
        if pivot != col:
            for c in range(n):
                M[col, c], M[pivot, c] = M[pivot, c], M[col, c]
                out[col, c], out[pivot, c] = out[pivot, c], out[col, c]
        inv = 1.0 / M[col, col]
        for c in range(n):
            M[col, c] *= inv
            out[col, c] *= inv
        for r in range(n):
            if r != col and M[r, col] != 0.0:
                f = M[r, col]
                for c in range(n):
                    M[r, c] -= f * M[col, c]
                    out[r, c] -= f * out[col, c]
    return True


@kernel
def input_weight(g2, B):
    """W = G2 R⁻¹ G2ᵀ (d × d), S's lower-right block, from g2 (d, m) and B = R⁻¹ G2ᵀ (m, d)."""
    d, m = g2.shape[0], g2.shape[1]
    W = np.empty((d, d))
    for a in range(d):
        for b in range(d):
            s = 0.0
            for c in range(m):
                s += g2[a, c] * B[c, b]
            W[a, b] = s
    return W


@kernel
def finger_general_checks(A, g2, B, P, q, q_norm, residual_tol, cond_max, K, Ks):
    """(failed Check bits, relative residual) of one finger's solution P (k × k) by the checks of
    riccati.checked_gains, and its gains into K, K_s (m, k) where A_cl is invertible:

    * P finite (else SOLVE_FAILED, residual NaN);
    * ‖PA + AᵀP + Q − P S P‖_F / ‖Q‖_F < residual_tol, S = G R⁻¹ Gᵀ (RESIDUAL);
    * P ≻ 0 (P_NOT_PD): its Cholesky factor exists;
    * A_cl = A + G K Hurwitz (HURWITZ): proven where P ≻ 0, the residual passed and
      N = Q + P S P − 2 tol ‖Q‖_F I ≻ 0 (A_clᵀP + PA_cl = −(Q + PSP − Res), the hand kernels'
      argument), else decided by A_cl's eigenvalues;
    * cond₂(A_cl) < cond_max (ACL_SINGULAR): proven by cond₂ ≤ ‖A_cl‖_F ‖A_cl⁻¹‖_F < cond_max
      with A_cl⁻¹ = [[−C⁻¹D, C⁻¹], [I, 0]] for A_cl = [[0, I], [C, D]], else decided by the
      singular values. Then K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q, which is −R⁻¹ G2ᵀ C⁻ᵀ Q[:d, :].

    Each proof only ever accepts what the exact test accepts; where it fails the exact test
    decides, so a finger's bits are those of the eigenvalue and singular-value tests.
    """
    k, d, m = A.shape[0], g2.shape[0], g2.shape[1]
    if not all_finite(P):
        return SOLVE_FAILED, np.nan
    W = input_weight(g2, B)                                    # G2 R⁻¹ G2ᵀ
    PSP = np.empty((k, k))                                     # P S P = P_lowᵀ W P_low
    res2 = 0.0
    for i in range(k):
        for j in range(k):
            pa, ap = 0.0, 0.0
            for c in range(k):
                pa += P[i, c] * A[c, j]
                ap += A[c, i] * P[c, j]
            psp = 0.0
            for a in range(d):
                t = 0.0
                for b in range(d):
                    t += W[a, b] * P[d + b, j]
                psp += P[d + a, i] * t
            PSP[i, j] = psp
            v = pa + ap + q[i, j] - psp
            res2 += v * v
    residual = np.sqrt(res2) / q_norm
    failed = 0
    if not residual < residual_tol:
        failed |= RESIDUAL
    work = np.zeros((k, k))
    if not cholesky_exists(P, work):
        failed |= P_NOT_PD
    for a in range(m):
        for c in range(k):
            s = 0.0
            for rr in range(d):
                s += B[a, rr] * P[d + rr, c]
            K[a, c] = -s                                        # K = −R⁻¹ Gᵀ P
    A_cl = A.copy()
    for rr in range(d):
        for c in range(k):
            s = 0.0
            for a in range(m):
                s += g2[rr, a] * K[a, c]
            A_cl[d + rr, c] += s                                # A + G K
    if not all_finite(A_cl):
        return failed | HURWITZ | ACL_SINGULAR, residual
    proven = False
    if failed == 0:
        margin = 2.0 * residual_tol * q_norm
        N = q + PSP
        for i in range(k):
            N[i, i] -= margin
        proven = cholesky_exists(N, work)
    if not proven:
        for v in np.linalg.eigvals(A_cl.astype(np.complex128)):
            if not v.real < 0.0:
                failed |= HURWITZ
                break
    C_inv = np.empty((d, d))
    C = A_cl[d:, :d].copy()
    fro2, inv2 = 0.0, float(d)                                 # ‖A_cl‖²_F, ‖A_cl⁻¹‖²_F
    invertible = invert_in_place(C, C_inv)
    if invertible:
        for i in range(k):
            for j in range(k):
                fro2 += A_cl[i, j] * A_cl[i, j]
        for i in range(d):
            for j in range(d):
                inv2 += C_inv[i, j] * C_inv[i, j]
                s = 0.0
                for c in range(d):
                    s += C_inv[i, c] * A_cl[d + c, d + j]
                inv2 += s * s                                  # (C⁻¹ D)_ij
    if not (invertible and np.sqrt(fro2 * inv2) < cond_max):
        sv = np.linalg.svd(A_cl)[1]
        if not sv[0] < cond_max * sv[k - 1]:                   # cond₂ = σ_max / σ_min
            return failed | ACL_SINGULAR, residual
        X = np.linalg.solve(A_cl.T.copy(), q.copy())           # A_cl⁻ᵀ Q
        for a in range(m):
            for c in range(k):
                s = 0.0
                for rr in range(d):
                    s += B[a, rr] * X[d + rr, c]
                Ks[a, c] = -s
        return failed, residual
    for a in range(m):
        for c in range(k):
            s = 0.0
            for rr in range(d):
                t = 0.0
                for j in range(d):
                    t += C_inv[j, rr] * q[j, c]                # (C⁻ᵀ Q[:d, :])_rr,c
                s += B[a, rr] * t
            Ks[a, c] = -s                                       # −R⁻¹ G2ᵀ C⁻ᵀ Q[:d, :]
    return failed, residual


@kernel
def finite_blocks(a2, g2, x, x_d):
    """Every entry of one finger's blocks a2, g2 and states x, x_d is finite."""
    ok = all_finite(a2) and all_finite(g2)
    for c in range(x.shape[0]):
        ok = ok and np.isfinite(x[c]) and np.isfinite(x_d[c])
    return ok


@kernel
def finger_restart(A, g2, B, q, P):
    """A warm finger whose Newton–Kleinman failed a check (its SDC blocks moved too far since its
    last solution): P (k × k) solved again from scratch by the Hamiltonian's sign function
    (:func:`~soft_gripper_sdre.control.kernels.riccati.hamiltonian_solve`, S's block
    W = G2 R⁻¹ G2ᵀ from B = R⁻¹ G2ᵀ), for Newton–Kleinman to refine. False (P untouched) when the
    sign iteration fails."""
    return hamiltonian_solve(A, input_weight(g2, B), q, P)


@kernel
def general_gains(finite, a2, g2, q, r, r_inv, residual_tol, cond_max, max_iterations,
                  P, K, Ks, warm, P_out, residual, iterations, failed):
    """The gains of every warm finger with ``finite`` inputs by Newton–Kleinman from its state's
    P and the general checks, for the blocks a2 (n, d, 2d), g2 (n, d, m); Q (2d, 2d), R and R⁻¹
    (m, m).

    The state (P, K, K_s (n, m, 2d), warm (n,)) is updated in place: a finger that passes every
    check with finite gains, at once or after its restart (:func:`finger_restart`), gets its new
    P, K, K_s and warm True; every other keeps P, K, K_s and ends warm False (the supervisor
    solves it exactly). The step's record: P_out (n, 2d, 2d) the Newton–Kleinman result, after
    the restart where there was one (NaN where not solved), ``residual`` (NaN where not solved),
    ``iterations`` (the Lyapunov solves), ``failed`` (Check bits; NONFINITE for a finger whose
    inputs are not finite).
    """
    n, d, k, m = a2.shape[0], a2.shape[1], a2.shape[2], g2.shape[2]
    nu = k * (k + 1) // 2
    work = (np.empty((k, k)), np.empty((m, k)), np.empty((nu, nu)), np.empty(nu),
            np.empty((k, k)))
    A, B, Pi = np.empty((k, k)), np.empty((m, d)), np.empty((k, k))
    Ki, Ksi = np.empty((m, k)), np.zeros((m, k))
    q_norm = max(np.sqrt(np.sum(q * q)), 1e-300)
    for i in range(n):
        P_out[i] = np.nan
        residual[i], iterations[i], failed[i] = np.nan, 0, 0
        if not finite[i]:
            failed[i] = NONFINITE
        solving = warm[i] and failed[i] == 0
        warm[i] = False
        if not solving:
            continue
        sdc_matrix(a2[i], A)
        for a in range(m):
            for c in range(d):
                s = 0.0
                for b in range(m):
                    s += r_inv[a, b] * g2[i, c, b]
                B[a, c] = s                                     # R⁻¹ G2ᵀ
        Pi[:, :] = P[i]
        iterations[i] = finger_newton_kleinman(A, g2[i], B, q, r, Pi, max_iterations, work)
        P_out[i] = Pi
        Ksi[:, :] = 0.0
        failed[i], residual[i] = finger_general_checks(A, g2[i], B, Pi, q, q_norm, residual_tol,
                                                       cond_max, Ki, Ksi)
        if failed[i] != 0 and finger_restart(A, g2[i], B, q, Pi):
            iterations[i] += finger_newton_kleinman(A, g2[i], B, q, r, Pi, max_iterations, work)
            P_out[i] = Pi
            Ksi[:, :] = 0.0
            failed[i], residual[i] = finger_general_checks(A, g2[i], B, Pi, q, q_norm,
                                                           residual_tol, cond_max, Ki, Ksi)
        if failed[i] == 0 and all_finite(Ki) and all_finite(Ksi):
            P[i] = Pi
            K[i] = Ki
            Ks[i] = Ksi
            warm[i] = True


@kernel
def general_torques(x, x_d, finite, K, Ks, lower, upper, u_unsat, u):
    """u_unsat = K x + K_s x_d (eq. 22) with the gains K, K_s (n, m, 2d), zero for a finger whose
    inputs are not ``finite`` and wherever the product is not finite; u = u_unsat clipped to
    [lower, upper] (m,)."""
    for i in range(x.shape[0]):
        for a in range(K.shape[1]):
            v = 0.0
            if finite[i]:
                for c in range(x.shape[1]):
                    v += K[i, a, c] * x[i, c] + Ks[i, a, c] * x_d[i, c]
                if not np.isfinite(v):
                    v = 0.0
            u_unsat[i, a] = v
            u[i, a] = min(max(v, lower[a]), upper[a])


@kernel
def general_step_gains(x, x_d, a2, g2, q, r, r_inv, residual_tol, cond_max, max_iterations,
                       P, K, Ks, warm, finite, P_out, residual, iterations, failed):
    """:func:`general_gains` on given blocks at states x, x_d (n, 2d): ``finite`` (n,) is set to
    whether each finger's blocks and states are finite."""
    for i in range(x.shape[0]):
        finite[i] = finite_blocks(a2[i], g2[i], x[i], x_d[i])
    general_gains(finite, a2, g2, q, r, r_inv, residual_tol, cond_max, max_iterations,
                  P, K, Ks, warm, P_out, residual, iterations, failed)


@kernel
def shaped_rest_frame(z, origin, x, x_d):
    """x = [p − p₀, ṗ], x_d = [p_d − p₀, ṗ_d] (n, 2d) from the rows z = [p, ṗ, p_d, ṗ_d, …] of
    d columns each (RestFrame.states)."""
    d = origin.shape[0]
    for i in range(z.shape[0]):
        for c in range(d):
            x[i, c], x[i, d + c] = z[i, c] - origin[c], z[i, d + c]
            x_d[i, c], x_d[i, d + c] = z[i, 2 * d + c] - origin[c], z[i, 3 * d + c]


@kernel
def general_tracking_gains(z, origin, network, hidden, q, r, r_inv, residual_tol, cond_max,
                           max_iterations, P, K, Ks, warm, a2, g2, x, x_d, finite, P_out,
                           residual, iterations, failed):
    """SdreLaw's step up to the torques for any shape: the states x, x_d from the base-frame rows
    z (n, 4d) = [p, ṗ, p_d, ṗ_d] and the rest tip ``origin`` (d,), the fused network's blocks at x
    into a2, g2, then :func:`general_step_gains`."""
    shaped_rest_frame(z, origin, x, x_d)
    shaped_forward(x, network, hidden, a2, g2)
    general_step_gains(x, x_d, a2, g2, q, r, r_inv, residual_tol, cond_max, max_iterations,
                       P, K, Ks, warm, finite, P_out, residual, iterations, failed)


@kernel
def general_feedforward_gains(z, origin, ff_at_reference, network, hidden, q, r, r_inv,
                              residual_tol, cond_max, max_iterations, P, K, Ks, warm, a2, g2,
                              a2_ff, g2_ff, x, x_d, e, state_finite, finite, P_out, residual,
                              iterations, failed):
    """SdreFeedforwardLaw's step up to the torques for any shape, from the rows z (n, 5d) =
    [p, ṗ, p_d, ṗ_d, a_d]: x, x_d (zero rows where either is not finite: ``state_finite``), the
    blocks at x (a2, g2) and where the feedforward evaluates the model (a2_ff, g2_ff: at x_d with
    ``ff_at_reference``, else those at x), e = x − x_d, and the gains of the feedback step on
    (e, 0) (:func:`general_step_gains`)."""
    n, k = z.shape[0], x.shape[1]
    shaped_rest_frame(z, origin, x, x_d)
    zero = np.zeros((n, k))
    for i in range(n):
        ok = True
        for c in range(k):
            ok = ok and np.isfinite(x[i, c]) and np.isfinite(x_d[i, c])
        state_finite[i] = ok
        if not ok:
            x[i] = 0.0
            x_d[i] = 0.0
        for c in range(k):
            e[i, c] = x[i, c] - x_d[i, c]
    shaped_forward(x, network, hidden, a2, g2)
    if ff_at_reference:
        shaped_forward(x_d, network, hidden, a2_ff, g2_ff)
    else:
        a2_ff[:] = a2
        g2_ff[:] = g2
    general_step_gains(e, zero, a2, g2, q, r, r_inv, residual_tol, cond_max, max_iterations,
                       P, K, Ks, warm, finite, P_out, residual, iterations, failed)


@kernel
def finger_pseudo_inversion(a2, g2, x_d, a_d, cond_max, u_ff):
    """u_ff (m,) = G2⁺ (a_d − A2 x_d) for one finger (laws.feedforward.pseudo_inversion): returns
    (usable, unreachable). A well conditioned G2 of full rank takes the closed form of its Gram
    matrix (:data:`PROVEN_GRAM_COND`), any other the SVD. Zero and not usable where G2 or the
    demand is not finite, G2 is zero or σ_max ≥ cond_max σ_min over its min(d, m) singular values,
    or the result is not finite; ``unreachable`` [m/s²] = ‖(I − U Uᵀ) r‖ over the singular vectors
    above σ_max / cond_max (0 where the inputs are not finite)."""
    d, m = g2.shape[0], g2.shape[1]
    rhs = np.empty(d)
    finite = all_finite(g2)
    for rr in range(d):
        s = a_d[rr]
        for c in range(x_d.shape[0]):
            s -= a2[rr, c] * x_d[c]
        rhs[rr] = s
        finite = finite and np.isfinite(s)
    u_ff[:] = 0.0
    if not finite:
        return False, 0.0
    # G2 of full rank, proven well conditioned through M = G2 G2ᵀ (m ≥ d) or G2ᵀ G2 (m < d):
    # cond₂(G2)² = cond₂(M) ≤ ‖M‖_F ‖M⁻¹‖_F; then G2⁺ = G2ᵀ M⁻¹ or M⁻¹ G2ᵀ, and the demand
    # outside G2's range is r − G2 u_ff (none where m ≥ d). Else the SVD decides, as numpy does.
    wide = m >= d
    nm = d if wide else m
    M, M_inv = np.empty((nm, nm)), np.empty((nm, nm))
    fro2 = 0.0
    for a in range(nm):
        for b in range(nm):
            s = 0.0
            if wide:
                for c in range(m):
                    s += g2[a, c] * g2[b, c]
            else:
                for c in range(d):
                    s += g2[c, a] * g2[c, b]
            M[a, b] = s
            fro2 += s * s
    if invert_in_place(M, M_inv):
        inv2 = 0.0
        for a in range(nm):
            for b in range(nm):
                inv2 += M_inv[a, b] * M_inv[a, b]
        if np.sqrt(fro2 * inv2) < min(cond_max * cond_max, PROVEN_GRAM_COND):
            y = np.zeros(nm)
            for a in range(nm):
                s = 0.0
                for b in range(nm):
                    if wide:
                        s += M_inv[a, b] * rhs[b]
                    else:
                        t = 0.0
                        for c in range(d):
                            t += g2[c, b] * rhs[c]
                        s += M_inv[a, b] * t                    # (G2ᵀG2)⁻¹ G2ᵀ r
                y[a] = s
            usable = True
            for a in range(m):
                if wide:
                    s = 0.0
                    for c in range(d):
                        s += g2[c, a] * y[c]                    # G2ᵀ (G2G2ᵀ)⁻¹ r
                else:
                    s = y[a]
                u_ff[a] = s
                usable = usable and np.isfinite(s)
            if not usable:
                u_ff[:] = 0.0
            unreachable = 0.0
            if not wide:
                for rr in range(d):
                    s = rhs[rr]
                    for a in range(m):
                        s -= g2[rr, a] * u_ff[a]
                    unreachable += s * s
            return usable, np.sqrt(unreachable)
    U, sv, Vt = np.linalg.svd(g2.copy(), full_matrices=False)
    nk = sv.shape[0]
    c = np.empty(nk)
    for j in range(nk):
        s = 0.0
        for rr in range(d):
            s += U[rr, j] * rhs[rr]
        c[j] = s                                               # Uᵀ r
    usable = sv[0] > 0.0 and sv[0] < cond_max * sv[nk - 1]
    if usable:
        for a in range(m):
            s = 0.0
            for j in range(nk):
                s += Vt[j, a] * (c[j] / sv[j])
            u_ff[a] = s                                        # V Σ⁻¹ Uᵀ r
            usable = usable and np.isfinite(s)
        if not usable:
            u_ff[:] = 0.0
    unreachable = 0.0
    for rr in range(d):
        s = rhs[rr]
        for j in range(nk):
            if sv[j] > sv[0] / cond_max:                       # in G2's numerical range
                s -= U[rr, j] * c[j]
        unreachable += s * s
    return usable, np.sqrt(unreachable)


@kernel
def reachable_integral_update(xi, error, u_unsat, finite, to_torque, from_torque, projector,
                              lower, upper, limit, dt, band, decay):
    """ReachableIntegralAction.update for n fingers, in place on ξ (n, d): with e = p − p_d
    (``error``, (n, d)), Δξ = −Δt Π e and the inputs it adds Δu = to_torque Δξ,

        ‖e‖ ≤ band, no input at a bound Δu pushes further: ξ ← ξ + Δξ
        ‖e‖ > band:                                          ξ ← decay · ξ

    for each ``finite`` finger; then ξ = from_torque clip(u_I, ±limit) where an input of
    u_I = to_torque ξ exceeds its ``limit``."""
    n, d, m = xi.shape[0], xi.shape[1], to_torque.shape[0]
    step, du, u_i = np.empty(d), np.empty(m), np.empty(m)
    for i in range(n):
        if not finite[i]:
            continue
        e2 = 0.0
        for c in range(d):
            e2 += error[i, c] * error[i, c]
        for rr in range(d):
            s = 0.0
            for c in range(d):
                s += error[i, c] * projector[rr, c]
            step[rr] = -dt * s
        if e2 <= band * band:
            pushes = False
            for a in range(m):
                s = 0.0
                for c in range(d):
                    s += step[c] * to_torque[a, c]
                du[a] = s
                if (u_unsat[i, a] >= upper[a] and s > 0.0) or (u_unsat[i, a] <= lower[a]
                                                                and s < 0.0):
                    pushes = True
            if not pushes:
                for c in range(d):
                    xi[i, c] += step[c]
        else:
            for c in range(d):
                xi[i, c] *= decay
        over = False
        for a in range(m):
            s = 0.0
            for c in range(d):
                s += xi[i, c] * to_torque[a, c]
            u_i[a] = s
            over = over or abs(s) > limit[a]
        if over:
            for a in range(m):
                u_i[a] = min(max(u_i[a], -limit[a]), limit[a])
            for c in range(d):
                s = 0.0
                for a in range(m):
                    s += u_i[a] * from_torque[c, a]
                xi[i, c] = s


@kernel
def general_feedforward_finish(z, x_d, e, state_finite, finite, K, a2_ff, g2_ff, cond_max,
                               lower, upper, integral, xi, to_torque, from_torque, projector,
                               limit, dt, band, decay, u_ff, ff_usable, unreachable, u_unsat, u,
                               saturated):
    """The feedforward law's command for any shape after its gains (laws.feedforward.
    combine_feedforward with its integral):

        u_unsat = u_ff + K e (+ u_I = to_torque ξ with ``integral``),   u_ff = G2⁺ (a_d − A2 x_d)

    zero for a finger whose state is not finite and wherever not finite, u = u_unsat clipped to
    [lower, upper], ``saturated`` where it was outside; a_d is z's last d columns, zero where not
    finite (and then ``ff_usable`` False, ``unreachable`` 0). Then, with ``integral``, ξ's step
    from the error p − p_d = e[:, :d] and u_unsat (:func:`reachable_integral_update`)."""
    n, m, d = u.shape[0], u.shape[1], x_d.shape[1] // 2
    a_d = np.empty(d)
    for i in range(n):
        acc_finite = True
        for c in range(d):
            acc_finite = acc_finite and np.isfinite(z[i, 4 * d + c])
        for c in range(d):
            a_d[c] = z[i, 4 * d + c] if acc_finite else 0.0
        usable, unreach = finger_pseudo_inversion(a2_ff[i], g2_ff[i], x_d[i], a_d, cond_max,
                                                  u_ff[i])
        ff_usable[i] = usable and acc_finite
        unreachable[i] = unreach if (state_finite[i] and acc_finite) else 0.0
        for a in range(m):
            v = 0.0
            if finite[i]:
                for c in range(e.shape[1]):
                    v += K[i, a, c] * e[i, c]
                if not np.isfinite(v):
                    v = 0.0
            v += u_ff[i, a]
            if integral and state_finite[i]:
                for c in range(d):
                    v += to_torque[a, c] * xi[i, c]
            if not (state_finite[i] and np.isfinite(v)):
                v = 0.0
            u_unsat[i, a] = v
            u[i, a] = min(max(v, lower[a]), upper[a])
            saturated[i, a] = v < lower[a] or v > upper[a]
    if integral:
        reachable_integral_update(xi, e[:, :d].copy(), u_unsat, state_finite, to_torque,
                                  from_torque, projector, lower, upper, limit, dt, band, decay)
