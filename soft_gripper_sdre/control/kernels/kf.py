"""The constant-velocity Kalman filter step
(:class:`~soft_gripper_sdre.control.kf.ConstantVelocityKF`) compiled with numba, for n fingers at
once, in place.

Per finger, with F, Σ_v from :func:`~soft_gripper_sdre.control.kf.cv_matrices`, H = [I 0], Σ_r:

    predict:  x̂ = F x̂,                  S = F S Fᵀ + Σ_v
    update:   K = S Hᵀ (H S Hᵀ + Σ_r)⁻¹,   x̂ = x̂ + K (z − H x̂),
              S = (I − K H) S (I − K H)ᵀ + K Σ_r Kᵀ      (Joseph form)

A finger whose measurement is not valid or not finite only predicts. :func:`kf_step` takes F and Σ_v
built once for a fixed step; :func:`kf_step_dt` builds them for each call's Δt (a source whose
stamps are not evenly spaced).
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel


@kernel
def kf_step(x, P, z, valid, F, Q, R):
    """One period for every finger: x (n, 4) and P (n, 4, 4) updated in place with measurements
    z (n, 2) where ``valid`` (n,) is True and z is finite."""
    FP, Pp, IKH, T = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    xp, K = np.empty(4), np.empty((4, 2))
    for i in range(x.shape[0]):
        for r in range(4):
            xp[r] = F[r, 0] * x[i, 0] + F[r, 1] * x[i, 1] + F[r, 2] * x[i, 2] + F[r, 3] * x[i, 3]
        for r in range(4):                                            # S = F S Fᵀ + Σ_v
            for c in range(4):
                FP[r, c] = (F[r, 0] * P[i, 0, c] + F[r, 1] * P[i, 1, c] + F[r, 2] * P[i, 2, c]
                            + F[r, 3] * P[i, 3, c])
        for r in range(4):
            for c in range(4):
                Pp[r, c] = (FP[r, 0] * F[c, 0] + FP[r, 1] * F[c, 1] + FP[r, 2] * F[c, 2]
                            + FP[r, 3] * F[c, 3] + Q[r, c])
        if not (valid[i] and np.isfinite(z[i, 0]) and np.isfinite(z[i, 1])):
            x[i], P[i] = xp, Pp
            continue
        s00, s01, s10, s11 = (Pp[0, 0] + R[0, 0], Pp[0, 1] + R[0, 1], Pp[1, 0] + R[1, 0],
                              Pp[1, 1] + R[1, 1])
        det = s00 * s11 - s01 * s10
        i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det      # (H S Hᵀ + Σ_r)⁻¹
        for r in range(4):
            K[r, 0] = Pp[r, 0] * i00 + Pp[r, 1] * i10
            K[r, 1] = Pp[r, 0] * i01 + Pp[r, 1] * i11
        e0, e1 = z[i, 0] - xp[0], z[i, 1] - xp[1]
        for r in range(4):
            x[i, r] = xp[r] + K[r, 0] * e0 + K[r, 1] * e1
        # I − K H: H picks the positions
        for r in range(4):
            for c in range(4):
                IKH[r, c] = (1.0 if r == c else 0.0) - (K[r, c] if c < 2 else 0.0)
        for r in range(4):
            for c in range(4):
                T[r, c] = (IKH[r, 0] * Pp[0, c] + IKH[r, 1] * Pp[1, c] + IKH[r, 2] * Pp[2, c]
                           + IKH[r, 3] * Pp[3, c])
        for r in range(4):
            for c in range(4):
                krk = (K[r, 0] * (R[0, 0] * K[c, 0] + R[0, 1] * K[c, 1])
                       + K[r, 1] * (R[1, 0] * K[c, 0] + R[1, 1] * K[c, 1]))
                P[i, r, c] = (T[r, 0] * IKH[c, 0] + T[r, 1] * IKH[c, 1] + T[r, 2] * IKH[c, 2]
                              + T[r, 3] * IKH[c, 3] + krk)


@kernel
def cv_matrices_into(dt, accel_psd, axis_coupling, F, Q):
    """F (4, 4) and Σ_v (4, 4) of the constant-velocity model for step ``dt``, written in place:
    the arithmetic of :func:`~soft_gripper_sdre.control.kf.cv_matrices`, with C = [[1, c], [c, 1]]
    and c = ``axis_coupling`` (0: independent axes, 1: the paper's D = [0 0 1 1]ᵀ)."""
    q3, q2, q1 = dt**3 / 3, dt**2 / 2, dt
    for r in range(4):
        for c in range(4):
            F[r, c] = 1.0 if r == c else 0.0
            coupling = 1.0 if r % 2 == c % 2 else axis_coupling
            scale = q3 if r < 2 and c < 2 else (q1 if r >= 2 and c >= 2 else q2)
            Q[r, c] = accel_psd * (scale * coupling)
    F[0, 2] = dt
    F[1, 3] = dt


@kernel
def kf_step_dt(x, P, z, valid, dt, accel_psd, axis_coupling, F, Q, R):
    """:func:`kf_step` over a step of ``dt`` seconds: F and Σ_v are built for it into the scratch
    arrays F, Q (4, 4) first (:func:`cv_matrices_into`), so a variable-rate source costs no Python
    matrix work per message."""
    cv_matrices_into(dt, accel_psd, axis_coupling, F, Q)
    kf_step(x, P, z, valid, F, Q, R)
