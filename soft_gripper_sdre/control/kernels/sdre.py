"""The SDRE laws' steps for n fingers compiled with numba (plain loops over fingers, no Python
objects): the tracking law on given SDC blocks (:func:`sdre_step`) and on the fused network
(:func:`tracking_step`), the model inversion and the feedforward law (:func:`feedforward_step`).
They take the settings, state and outputs as record arrays, one record per finger
(:mod:`soft_gripper_sdre.control.kernels` defines them and
:func:`~soft_gripper_sdre.control.kernels.warm_up`); the derivations are in
docs/design/compiled_kernel.md.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel
from soft_gripper_sdre.control.kernels.linalg import well_conditioned
from soft_gripper_sdre.control.kernels.riccati import sdre_gains
from soft_gripper_sdre.control.kernels.sdc_network import finger_blocks, network_arrays


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
