"""The closed-loop check's steps compiled: the default law on the hand's path (``sdre_ff`` with its
integral action, two bidirectional inputs, a planar tip) closing the loop around one finger,
noise, estimator, command delay and plant included, step after step in one call.

:func:`~soft_gripper_sdre.analysis.loop_settings.check_on_model` runs the law's own objects for
the step the compiled SDRE step hands back (a cold finger, a failed check, a state not finite: the
supervisor's exact path, in scipy) and this kernel for the others, on the same arrays: the KF's
estimate and covariance, the SDRE's records, the integral's ξ, the roll-off's last output, the
queue of delayed commands and the plant's state. Each step is the arithmetic of the Python step
(the same kernels, in the same order):

    z   = tip + σ n_k                                  (n_k: the run's k-th normal draw)
    x̂   = kf_step(x̂, z)
    u   = feedforward_step([x̂, p₀ + p_d, ṗ_d, a_d]) → integral_roll_off        (the law)
    the command ``delay`` steps old is held over Δt on the plant: the learned model
    (network_rk4, its input map scaled by ``gain``) or a linear fit (z ← A_d z + B_d u/gain)

A step whose SDRE step leaves a finger not warm or its state not finite is undone (the SDRE state
and the estimate as before it) and handed back: the caller runs it through the law, then calls
again.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel
from soft_gripper_sdre.control.kernels.integral import integral_roll_off
from soft_gripper_sdre.control.kernels.kf import kf_step
from soft_gripper_sdre.control.kernels.network_plant import network_rk4
from soft_gripper_sdre.control.kernels.sdre import feedforward_step

#: the plant kinds :func:`feedforward_check_steps` steps
NETWORK_PLANT, LINEAR_PLANT = 0, 1


@kernel
def _copy_sdre_state(source, target):
    """The SDRE state records' fields (P, K, K_s, warm) of ``source`` into ``target``."""
    for i in range(source.shape[0]):
        target[i].P[:, :] = source[i].P
        target[i].K[:, :] = source[i].K
        target[i].Ks[:, :] = source[i].Ks
        target[i].warm = source[i].warm


@kernel
def _plant_tip(state, rest, origin, tip):
    """tip = rest + p − origin: the plant's tip from its state's positions."""
    for j in range(tip.shape[0]):
        tip[j] = rest[j] + state[j] - origin[j]


@kernel
def feedforward_check_steps(k, noise, noise_std, rest, ref_pos, ref_vel, ref_acc,
                            kf_x, kf_P, kf_F, kf_Q, kf_R,
                            origin, ff_at_reference, network, hidden, settings, state, outputs,
                            feedforward, saved, xi, integral, alpha, u_prev, has_prev, pending,
                            plant, plant_kind, plant_rest, plant_origin, gain, dt, substeps,
                            w1, b1, w2, b2, w3, b3, Ad, Bd, bound, pos, u_hist, saturated_hist):
    """Steps k, k + 1, … of the check (module doc) until the last or one to hand back; returns
    (the first step not run here, whether the tip left ``bound`` or the finite numbers on the
    step before it).

    Args, each updated in place where it is state:
        noise: (steps, 2) the run's normal draws; ``noise_std`` σ [m].
        rest: (2,) the check's rest tip [m]; ref_pos, ref_vel, ref_acc (steps, 2) the move.
        kf_x, kf_P, kf_F, kf_Q, kf_R: the estimator (n = 1) and its matrices.
        origin … feedforward: the law's arguments of
            :func:`~soft_gripper_sdre.control.kernels.sdre.feedforward_step` (n = 1); ``saved``
            SDRE state records to undo a step into.
        xi, integral: the integral action's ξ (1, 2) and settings record.
        alpha, u_prev (1, 2), has_prev (1,) bool: the roll-off (u_prev, has_prev updated).
        pending: (delay, 2) the commands not yet applied, oldest first.
        plant: the plant's state ((4,) for the model, the fit's augmented state for a linear
            fit); plant_kind :data:`NETWORK_PLANT` or :data:`LINEAR_PLANT`; its tip is
            plant_rest + plant[:2] − plant_origin; ``gain`` its input gain (the model's input map
            scaled by it, or a command divided by it); dt, substeps: the model's RK4 steps;
            w1 … b3 the model's layers; Ad, Bd the fit's exact discretisation over dt.
        bound: the tip's largest displacement [m] before the run counts as diverged.
        pos, u_hist, saturated_hist: (steps, 2), (steps, 2), (steps,) what each step did.
    """
    steps = pos.shape[0]
    delay = pending.shape[0]
    z = np.empty((1, 2))
    valid = np.ones(1, dtype=np.bool_)
    rows = np.empty((1, 10))
    u, u_unsat = np.empty((1, 2)), np.empty((1, 2))
    saturated = np.empty((1, 2), dtype=np.bool_)
    finite = np.empty(1, dtype=np.bool_)
    applied, command = np.empty(2), np.empty(2)
    tip = np.empty(2)
    scratch = np.empty(plant.shape[0])
    kf_x_before, kf_P_before = np.empty_like(kf_x), np.empty_like(kf_P)
    while k < steps:
        _plant_tip(plant, plant_rest, plant_origin, tip)
        for j in range(2):
            z[0, j] = tip[j] + noise_std * noise[k, j]
        kf_x_before[:], kf_P_before[:] = kf_x, kf_P
        kf_step(kf_x, kf_P, z, valid, kf_F, kf_Q, kf_R)
        for j in range(4):
            rows[0, j] = kf_x[0, j]
        for j in range(2):
            rows[0, 4 + j] = rest[j] + ref_pos[k, j]
            rows[0, 6 + j] = ref_vel[k, j]
            rows[0, 8 + j] = ref_acc[k, j]
        _copy_sdre_state(state, saved)
        feedforward_step(rows, origin, ff_at_reference, network, hidden, settings, state,
                         outputs, feedforward)
        if not (state[0].warm and feedforward[0].state_finite):
            _copy_sdre_state(saved, state)                 # undone: the caller runs step k
            kf_x[:], kf_P[:] = kf_x_before, kf_P_before
            return k, False
        for j in range(2):
            u[0, j], u_unsat[0, j] = outputs[0].u[j], outputs[0].u_unsat[j]
            saturated[0, j] = u[0, j] != u_unsat[0, j]
        finite[0] = True
        integral_roll_off(xi, integral, rows, finite, u_unsat, u, saturated, alpha,
                          u_prev if has_prev[0] else u, has_prev[0])
        if alpha > 0.0:
            u_prev[:, :] = u
            has_prev[0] = True
        if delay == 0:
            applied[:] = u[0]
        else:
            applied[:] = pending[0]
            for r in range(delay - 1):
                pending[r] = pending[r + 1]
            pending[delay - 1] = u[0]
        if plant_kind == NETWORK_PLANT:
            if gain != 1.0:
                for j in range(2):
                    command[j] = gain * applied[j]
            else:
                command[:] = applied
            network_rk4(plant, command, dt, substeps, w1, b1, w2, b2, w3, b3, 2)
        else:
            if gain != 1.0:
                for j in range(2):
                    command[j] = applied[j] / gain
            else:
                command[:] = applied
            scratch[:] = Ad @ plant + Bd @ command
            plant[:] = scratch
        _plant_tip(plant, plant_rest, plant_origin, tip)
        largest = 0.0
        for j in range(2):
            pos[k, j] = tip[j] - rest[j]
            u_hist[k, j] = u[0, j]
            largest = max(largest, abs(pos[k, j]))
        saturated_hist[k] = saturated[0, 0] or saturated[0, 1]
        k += 1
        if not (np.isfinite(tip[0]) and np.isfinite(tip[1]) and largest < bound):
            return k, True
    return k, False
