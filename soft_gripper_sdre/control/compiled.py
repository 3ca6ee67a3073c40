"""The controller's per-step work compiled with numba: how to call the kernels, what they keep.

The kernels (:mod:`~soft_gripper_sdre.control.compiled_sdre`,
:mod:`~soft_gripper_sdre.control.compiled_kf`, :mod:`~soft_gripper_sdre.control.compiled_integral`,
:mod:`~soft_gripper_sdre.control.compiled_horizon`)
take float64 / bool / int64 C-contiguous arrays and scalars, write their results into arrays the
caller owns and update the controller's state in place. Their parameters come in the groups below,
whose fields are the parameters in order, so a caller holds four tuples and splats them:

    tracking_step(z, origin, *network, *settings, *state, *outputs)

For the SDC form A = [[0, I], [a]], G = [[0], [G2]] (a = [A21 A22]) and each finger:

    W = G2 R⁻¹ G2ᵀ,  A_k = A − S P_k = [[0, I], [a − W P_k,low]]    (S = G R⁻¹ Gᵀ, P_low = P[2:, :])
    A_kᵀ P_k+1 + P_k+1 A_k = −(Q + P_k S P_k)                          (Newton–Kleinman)
    K = −R⁻¹ G2ᵀ P_low,   K_s = −R⁻¹ G2ᵀ C⁻ᵀ Q[:2, :]   (C = A_cl's lower-left block)   (eq. 23)
    u = K x + K_s x_d, saturated to ±u_max                                               (eq. 22)

The warm fingers iterate together until a bound on the next iterate's residual, summed over them,
is below half the accepted one (docs/design/compiled_kernel.md). A finger that is cold (``warm``
False on entry) or fails a check keeps its previous gains (zero before any: zero torque) and comes
back with ``warm`` False and the failed checks' :class:`~soft_gripper_sdre.control.riccati.Check`
bits; the supervisor (:class:`~soft_gripper_sdre.control.sdre.SdreController`) solves it exactly
(scipy) and writes P, K, K_s and ``warm`` into the state. :func:`warm_up` compiles (or loads from
numba's cache) every kernel at these types: a process calls it before its first real-time step.
The kernels are importable from here as well as from their modules.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.compiled_horizon import plan_sample
from soft_gripper_sdre.control.compiled_integral import (
    integral_roll_off,
    integral_step,
    integral_update,
)
from soft_gripper_sdre.control.compiled_kf import kf_step, kf_step_dt
from soft_gripper_sdre.control.compiled_sdre import (
    feedforward_step,
    model_inversion,
    sdc_forward,
    sdre_gains,
    sdre_step,
    tracking_step,
    tracking_torques,
)

__all__ = ['SdcNetwork', 'SdreSettings', 'SdreState', 'SdreOutputs', 'FeedforwardOutputs',
           'compiled_network', 'kernel_array', 'warm_up',
           'sdc_forward', 'sdre_gains', 'tracking_torques', 'sdre_step', 'tracking_step',
           'model_inversion', 'feedforward_step', 'kf_step', 'kf_step_dt', 'integral_step',
           'integral_update', 'integral_roll_off', 'plan_sample']


class SdcNetwork(NamedTuple):
    """The fused SDC network: x (4) ↦ relu(x w1 + b1) ↦ relu(· w2 + b2) ↦ · w3 + b3 =
    [a (8), G2 (4)]."""

    w1: np.ndarray     # (4, h)
    b1: np.ndarray     # (h,)
    w2: np.ndarray     # (h, h)
    b2: np.ndarray     # (h,)
    w3: np.ndarray     # (h, 12)
    b3: np.ndarray     # (12,)

    @classmethod
    def of(cls, model) -> SdcNetwork:
        """The arrays of a model with ``fused_network`` (an SDCModel)."""
        return cls(*model.fused_network)


def kernel_array(a, dtype=np.float64) -> np.ndarray:
    """``a`` as the kernels take it: a C-contiguous, writeable array of ``dtype`` (``a`` itself
    if it is one). numba types a read-only or strided array differently and would compile the
    kernel anew for it."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def compiled_network(model) -> SdcNetwork | None:
    """The model's :class:`SdcNetwork` if it has ``fused_network`` (an SDCModel), else None."""
    return SdcNetwork.of(model) if hasattr(model, 'fused_network') else None


class SdreSettings(NamedTuple):
    """Weights and limits: what SdreController takes, in the types the kernels are compiled for."""

    q: np.ndarray          # (4, 4) Q
    r_inv: np.ndarray      # (2, 2) R⁻¹
    u_max: np.ndarray      # (2,) torque limits [N·m]
    residual_tol: float    # largest accepted ‖Res‖_F / ‖Q‖_F
    cond_max: float        # largest accepted condition number of G2 and of C
    # Newton–Kleinman iterations before the finger is handed to the exact path
    max_iterations: int

    @classmethod
    def of(cls, Q, R, u_max, residual_tol: float = 1e-6, cond_max: float = 1e8,
           max_iterations: int = 5) -> SdreSettings:
        """From SdreController's arguments (Q, R, u_max scalar or (2,), and its defaults)."""
        Q, R = np.array(Q, dtype=np.float64), np.array(R, dtype=np.float64)
        u_max = np.array(np.broadcast_to(np.asarray(u_max, dtype=np.float64), (2,)))
        return cls(Q, np.linalg.inv(R), u_max, float(residual_tol), float(cond_max),
                   int(max_iterations))

    @property
    def riccati(self) -> tuple:
        """The settings :func:`~soft_gripper_sdre.control.compiled_sdre.sdre_gains` takes (all but
        u_max)."""
        return self.q, self.r_inv, self.residual_tol, self.cond_max, self.max_iterations


class SdreState(NamedTuple):
    """What the controller carries from one step to the next (updated in place)."""

    P: np.ndarray          # (n, 4, 4) the last solution: the warm start
    warm: np.ndarray       # (n,) bool: P holds an accepted solution
    K: np.ndarray          # (n, 2, 4) gains in use: the last accepted ones (zero before any)
    Ks: np.ndarray         # (n, 2, 4)

    @classmethod
    def cold(cls, n: int) -> SdreState:
        return cls(np.zeros((n, 4, 4)), np.zeros(n, dtype=np.bool_), np.zeros((n, 2, 4)),
                   np.zeros((n, 2, 4)))


class SdreOutputs(NamedTuple):
    """One step's results (overwritten by every step)."""

    a2: np.ndarray           # (n, 2, 4) the model's [A21 A22] at x
    g2: np.ndarray           # (n, 2, 2) G2 at x
    u: np.ndarray            # (n, 2) saturated torques
    u_unsat: np.ndarray      # (n, 2)
    residual: np.ndarray     # (n,) ‖Res‖_F / ‖Q‖_F of the new P (NaN where not solved)
    iterations: np.ndarray   # (n,) int64 Newton–Kleinman iterations run (0: not solved here)
    failed: np.ndarray       # (n,) int64 Check bits of the checks that failed

    @classmethod
    def empty(cls, n: int) -> SdreOutputs:
        return cls(np.zeros((n, 2, 4)), np.zeros((n, 2, 2)), np.zeros((n, 2)), np.zeros((n, 2)),
                   np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64))


class FeedforwardOutputs(NamedTuple):
    """What :func:`~soft_gripper_sdre.control.compiled_sdre.feedforward_step` adds to
    SdreOutputs."""

    u_ff: np.ndarray           # (n, 2) the feedforward part of u_unsat (0 where not usable)
    a2_ff: np.ndarray          # (n, 2, 4) the model's blocks where the feedforward evaluates it
    g2_ff: np.ndarray          # (n, 2, 2)
    state_finite: np.ndarray   # (n,) bool: the finger's state and reference were finite
    ff_usable: np.ndarray      # (n,) bool: G2 there was well conditioned, u_ff and a_d finite

    @classmethod
    def empty(cls, n: int) -> FeedforwardOutputs:
        return cls(np.zeros((n, 2)), np.zeros((n, 2, 4)), np.zeros((n, 2, 2)),
                   np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_))


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel at the types the controller uses: call it
    before a node reports ready, so that no step pays for compilation."""
    n = 1
    network = SdcNetwork(np.zeros((4, 2)), np.zeros(2), np.zeros((2, 2)), np.zeros(2),
                         np.zeros((2, 12)), np.zeros(12))
    settings = SdreSettings.of(np.eye(4), np.eye(2), 1.0)
    state, out = SdreState.cold(n), SdreOutputs.empty(n)
    rows, ones = np.zeros((n, 2)), np.ones(n, dtype=np.bool_)
    sdc_forward(np.zeros((n, 4)), *network, out.a2, out.g2)
    sdre_gains(out.a2, out.g2, ones, *settings.riccati, *state, out.residual, out.iterations,
               out.failed)
    tracking_torques(state.K, state.Ks, np.zeros((n, 4)), np.zeros((n, 4)), ones, settings.u_max,
                     out.u, out.u_unsat)
    sdre_step(np.zeros((n, 4)), np.zeros((n, 4)), *settings, *state, *out)
    model_inversion(out.a2, out.g2, np.zeros((n, 4)), rows, settings.cond_max, rows.copy(),
                    ones.copy())
    tracking_step(np.zeros((n, 8)), np.zeros(2), *network, *settings, *state, *out)
    feedforward_step(np.zeros((n, 10)), np.zeros(2), False, *network, *settings, *state, *out,
                     *FeedforwardOutputs.empty(n))
    kf_step(np.zeros((n, 4)), np.zeros((n, 4, 4)), rows, ones, np.eye(4), np.eye(4), np.eye(2))
    kf_step_dt(np.zeros((n, 4)), np.zeros((n, 4, 4)), rows, ones, 1e-3, 1.0, 0.0, np.eye(4),
               np.eye(4), np.eye(2))
    saturated = np.zeros((n, 2), dtype=np.bool_)
    integral_step(rows.copy(), np.eye(2), np.eye(2), 1e-3, 1e-3, 0.9, 1.0, rows, ones, rows.copy(),
                  rows.copy(), saturated)
    integral_update(rows.copy(), np.eye(2), np.eye(2), 1e-3, 1e-3, 0.9, 1.0, rows, saturated, ones)
    integral_roll_off(rows.copy(), np.eye(2), np.eye(2), 1e-3, 1e-3, 0.9, 1.0, np.zeros((n, 10)),
                      ones, rows.copy(), rows.copy(), saturated, 0.5, 0.5, rows.copy(), True)
    plan = np.zeros((2, n, 2))
    plan_sample(np.array([0, 1], dtype=np.int64), plan, plan, plan, 0, rows.copy(), rows.copy(),
                rows.copy())
