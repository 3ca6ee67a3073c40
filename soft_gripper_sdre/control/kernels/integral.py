"""The integral action's per-step arithmetic compiled with numba
(:class:`~soft_gripper_sdre.control.laws.integral.IntegralAction` holds the state and the rules;
its constants come as one record of
:class:`~soft_gripper_sdre.control.kernels.IntegralSettings`: to_torque, from_torque, dt, band,
decay, u_max).
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel


@kernel
def integral_update(xi, settings, error, saturated, finite):
    """One step of the integral ξ (n, 2) [m·s] in place, per finger i with ``finite[i]``:

        ‖e‖ ≤ band and no torque saturated:  ξ ← ξ − Δt e        (e = p − p_d, so ξ = ∫(p_d − p)dt)
        ‖e‖ ≤ band and saturated:            ξ unchanged
        ‖e‖ > band (or e not finite):        ξ ← decay · ξ

    then bounded so that each torque of u_I = to_torque ξ is within ±u_max (ξ = from_torque u_I)."""
    s = settings[0]
    to_torque, from_torque, u_max = s.to_torque, s.from_torque, s.u_max
    dt, band, decay = s.dt, s.band, s.decay
    for i in range(xi.shape[0]):
        if not finite[i]:
            continue
        e0, e1 = error[i, 0], error[i, 1]
        if e0 * e0 + e1 * e1 <= band * band:
            if not (saturated[i, 0] or saturated[i, 1]):
                xi[i, 0] -= dt * e0
                xi[i, 1] -= dt * e1
        else:
            xi[i, 0] *= decay
            xi[i, 1] *= decay
        u0 = to_torque[0, 0] * xi[i, 0] + to_torque[0, 1] * xi[i, 1]
        u1 = to_torque[1, 0] * xi[i, 0] + to_torque[1, 1] * xi[i, 1]
        if abs(u0) > u_max or abs(u1) > u_max:
            u0, u1 = min(max(u0, -u_max), u_max), min(max(u1, -u_max), u_max)
            xi[i, 0] = from_torque[0, 0] * u0 + from_torque[0, 1] * u1
            xi[i, 1] = from_torque[1, 0] * u0 + from_torque[1, 1] * u1


@kernel
def integral_step(xi, settings, error, finite, u_unsat, u, saturated):
    """Add u_I = to_torque ξ to ``u_unsat`` of every finite finger, saturate it again into ``u`` and
    ``saturated`` (all (n, 2), in place), then :func:`integral_update` with that saturation."""
    to_torque, u_max = settings[0].to_torque, settings[0].u_max
    for i in range(xi.shape[0]):
        if finite[i]:
            u_unsat[i, 0] += to_torque[0, 0] * xi[i, 0] + to_torque[0, 1] * xi[i, 1]
            u_unsat[i, 1] += to_torque[1, 0] * xi[i, 0] + to_torque[1, 1] * xi[i, 1]
        for j in range(2):
            v = u_unsat[i, j]
            saturated[i, j] = abs(v) > u_max
            u[i, j] = min(max(v, -u_max), u_max)
    integral_update(xi, settings, error, saturated, finite)


@kernel
def integral_roll_off(xi, settings, z, finite, u_unsat, u, saturated, alpha, u_prev, has_prev):
    """The default law's last arithmetic in one call: :func:`integral_step` with the error
    e = p − p_d taken from the kernel rows z = [p, ṗ, p_d, …] (n, ≥ 6), then the roll-off of ``u``
    in place, u ← α u_prev + β u (β = 1 − α) where ``alpha`` > 0 and ``has_prev``, each element as
    :class:`~soft_gripper_sdre.control.tracking.RollOff` computes it."""
    n = xi.shape[0]
    error = np.empty((n, 2))
    for i in range(n):
        error[i, 0] = z[i, 0] - z[i, 4]
        error[i, 1] = z[i, 1] - z[i, 5]
    integral_step(xi, settings, error, finite, u_unsat, u, saturated)
    beta = 1.0 - alpha
    if alpha > 0.0 and has_prev:
        for i in range(n):
            for j in range(2):
                u[i, j] = alpha * u_prev[i, j] + beta * u[i, j]
