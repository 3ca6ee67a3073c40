"""The controller's per-step work compiled with numba: how to call the kernels, what they keep.

The kernels — the SDRE laws' steps (:mod:`~soft_gripper_sdre.control.kernels.sdre`) on
Newton–Kleinman with the checks (:mod:`~soft_gripper_sdre.control.kernels.riccati`), the fused
network (:mod:`~soft_gripper_sdre.control.kernels.sdc_network`) and small dense linear algebra
(:mod:`~soft_gripper_sdre.control.kernels.linalg`); the Kalman filter
(:mod:`~soft_gripper_sdre.control.kernels.kf`), the integral action
(:mod:`~soft_gripper_sdre.control.kernels.integral`) and the plan sample
(:mod:`~soft_gripper_sdre.control.kernels.horizon`) — take float64 / bool / int64 C-contiguous
arrays, record arrays and scalars, write their results into arrays the caller owns and update the
controller's state in place. The SDRE kernels' settings, state and outputs are record arrays
(:class:`KernelRecords`: one record per finger, one for the settings), the network one packed array
(:class:`SdcNetwork`), so a caller passes a few arrays:

    tracking_step(z, origin, *network, settings.records, state.records, outputs.records)

numba types a record array by its dtype, once per call, where it would type a tuple of arrays
field by field (docs/design/compiled_kernel.md, "Data layout").

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

Importing this package (which importing any of its modules does first) holds numba's on-disk cache
of the kernels to the kernel modules' sources as a whole
(:func:`~soft_gripper_sdre.control.kernels.cache.invalidate_stale_cache`): no kernel runs before
the rule.
"""
from __future__ import annotations

from typing import ClassVar, NamedTuple, Self

import numpy as np

from soft_gripper_sdre.control.kernels.cache import invalidate_stale_cache
from soft_gripper_sdre.control.kernels.check_loop import feedforward_check_steps
from soft_gripper_sdre.control.kernels.general import (
    general_feedforward_finish,
    general_feedforward_gains,
    general_step_gains,
    general_torques,
    general_tracking_gains,
    shaped_forward,
)
from soft_gripper_sdre.control.kernels.horizon import plan_sample
from soft_gripper_sdre.control.kernels.integral import (
    integral_roll_off,
    integral_step,
    integral_update,
)
from soft_gripper_sdre.control.kernels.kf import kf_step, kf_step_dt
from soft_gripper_sdre.control.kernels.riccati import sdre_gains
from soft_gripper_sdre.control.kernels.sdc_network import sdc_forward
from soft_gripper_sdre.control.kernels.sdre import (
    feedforward_step,
    model_inversion,
    sdre_step,
    tracking_step,
    tracking_torques,
)

__all__ = ['KernelRecords', 'SdcNetwork', 'SdreSettings', 'SdreState', 'SdreOutputs',
           'FeedforwardOutputs', 'IntegralSettings', 'compiled_network', 'kernel_array', 'warm_up',
           'warm_up_hand', 'warm_up_general',
           'sdc_forward', 'sdre_gains', 'tracking_torques', 'sdre_step', 'tracking_step',
           'model_inversion', 'feedforward_step', 'kf_step', 'kf_step_dt', 'integral_step',
           'integral_update', 'integral_roll_off', 'plan_sample', 'GeneralOutputs',
           'general_step_gains', 'general_tracking_gains', 'general_feedforward_gains',
           'general_feedforward_finish', 'general_torques', 'shaped_forward',
           'feedforward_check_steps', 'warm_up_check_loop']

#: the kernels' float type, in the record dtypes
F8 = np.float64


class SdcNetwork(NamedTuple):
    """The fused SDC network packed for the kernels: x (4) ↦ relu(x w1 + b1) ↦ relu(· w2 + b2) ↦
    · w3 + b3 = [a (8), G2 (4)], with w1 (4, h), b1 (h,), w2 (h, h), b2 (h,), w3 (h, 12), b3 (12,)
    one after the other in ``weights`` and h = ``hidden``."""

    weights: np.ndarray    # (h² + 18 h + 12,) float64
    hidden: int

    @classmethod
    def pack(cls, w1, b1, w2, b2, w3, b3) -> SdcNetwork:
        """The layers' arrays (float64) packed in that order."""
        layers = (w1, b1, w2, b2, w3, b3)
        return cls(np.concatenate([np.asarray(a, dtype=F8).ravel() for a in layers]),
                   int(np.shape(b1)[0]))

    @classmethod
    def of(cls, model) -> SdcNetwork:
        """The network of a model with ``fused_network`` (an SDCModel)."""
        return cls.pack(*model.fused_network)


def kernel_array(a, dtype=np.float64) -> np.ndarray:
    """``a`` as the kernels take it: a C-contiguous, writeable array of ``dtype`` (``a`` itself
    if it is one). numba types a read-only or strided array differently and would compile the
    kernel anew for it."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def compiled_network(model) -> SdcNetwork | None:
    """The model's :class:`SdcNetwork` if it has ``fused_network`` (an SDCModel), else None."""
    return SdcNetwork.of(model) if hasattr(model, 'fused_network') else None


class KernelRecords:
    """``n`` records of the class's ``dtype`` in one array, ``records``, which is what a kernel
    takes; each field is also an attribute, an (n, …) view of ``records`` (strided, sharing its
    memory) for the Python side to read and write. The dtypes are C-aligned, so the compiled code
    reads each field at its natural alignment."""

    dtype: ClassVar[np.dtype]

    def __init__(self, n: int) -> None:
        self.records = np.zeros(n, dtype=self.dtype)
        for name in self.dtype.names:
            setattr(self, name, self.records[name])

    def copy(self) -> Self:
        """Another set of records holding the same values."""
        twin = type(self)(len(self.records))
        twin.records[:] = self.records
        return twin


class SdreSettings(KernelRecords):
    """Weights and limits, one record: what SdreController takes, in the types the kernels are
    compiled for."""

    dtype = np.dtype([('q', F8, (4, 4)),          # Q
                      ('r_inv', F8, (2, 2)),      # R⁻¹
                      ('u_max', F8, (2,)),        # torque limits [N·m]
                      ('residual_tol', F8),       # largest accepted ‖Res‖_F / ‖Q‖_F
                      ('cond_max', F8),           # largest accepted condition number of G2 and C
                      # Newton–Kleinman iterations before the finger is handed to the exact path
                      ('max_iterations', np.int64)], align=True)

    @classmethod
    def of(cls, Q, R, u_max, residual_tol: float = 1e-6, cond_max: float = 1e8,
           max_iterations: int = 5) -> SdreSettings:
        """From SdreController's arguments (Q, R, u_max scalar or (2,), and its defaults)."""
        settings = cls(1)
        settings.q[0], settings.r_inv[0] = Q, np.linalg.inv(np.asarray(R, dtype=F8))
        settings.u_max[0] = np.broadcast_to(np.asarray(u_max, dtype=F8), (2,))
        settings.residual_tol[0], settings.cond_max[0] = float(residual_tol), float(cond_max)
        settings.max_iterations[0] = int(max_iterations)
        return settings


class SdreState(KernelRecords):
    """What the controller carries from one step to the next, per finger (updated in place;
    all zero and cold when made)."""

    dtype = np.dtype([('P', F8, (4, 4)),          # the last solution: the warm start
                      ('K', F8, (2, 4)),          # gains in use: the last accepted, zero before any
                      ('Ks', F8, (2, 4)),
                      ('warm', np.bool_)],        # P holds an accepted solution
                     align=True)


class SdreOutputs(KernelRecords):
    """One step's results per finger (overwritten by every step)."""

    dtype = np.dtype([('a2', F8, (2, 4)),         # the model's [A21 A22] at x
                      ('g2', F8, (2, 2)),         # G2 at x
                      ('u', F8, (2,)),            # saturated torques
                      ('u_unsat', F8, (2,)),
                      ('residual', F8),           # ‖Res‖_F / ‖Q‖_F of the new P (NaN: not solved)
                      ('iterations', np.int64),   # Newton–Kleinman iterations run (0: not here)
                      ('failed', np.int64)],      # Check bits of the checks that failed
                     align=True)


class FeedforwardOutputs(KernelRecords):
    """What :func:`~soft_gripper_sdre.control.kernels.sdre.feedforward_step` adds to
    SdreOutputs, per finger."""

    dtype = np.dtype([('u_ff', F8, (2,)),         # the feedforward part of u_unsat (0: not usable)
                      ('a2_ff', F8, (2, 4)),      # the model's blocks where the feedforward is
                      ('g2_ff', F8, (2, 2)),      # evaluated
                      ('state_finite', np.bool_),  # the finger's state and reference were finite
                      ('ff_usable', np.bool_)],   # G2 there well conditioned, u_ff and a_d finite
                     align=True)


class IntegralSettings(KernelRecords):
    """The integral action's constants, one record
    (:class:`~soft_gripper_sdre.control.laws.integral.IntegralAction`)."""

    dtype = np.dtype([('to_torque', F8, (2, 2)),  # u_I = to_torque ξ
                      ('from_torque', F8, (2, 2)),  # ξ = from_torque u_I
                      ('dt', F8),                 # control period [s]
                      ('band', F8),               # error norm inside which ξ integrates [m]
                      ('decay', F8),              # ξ's factor per step outside the band
                      ('u_max', F8)], align=True)  # bound on each torque of u_I [N·m]

    @classmethod
    def of(cls, to_torque, from_torque, dt: float, band: float, decay: float,
           u_max: float) -> IntegralSettings:
        """From IntegralAction's constants (u_I = to_torque ξ, ξ = from_torque u_I)."""
        settings = cls(1)
        settings.to_torque[0], settings.from_torque[0] = to_torque, from_torque
        settings.dt[0], settings.band[0], settings.decay[0], settings.u_max[0] = (dt, band, decay,
                                                                                  u_max)
        return settings


class GeneralOutputs:
    """One step's arrays of the general kernels (:mod:`~soft_gripper_sdre.control.kernels.general`)
    for ``n`` fingers of d tip coordinates and m inputs, overwritten by every step: plain
    C-contiguous arrays, each an argument of its own (their sizes vary with the shape, which a
    record dtype would fix).

    a2, a2_ff (n, d, 2d) and g2, g2_ff (n, d, m): the model's blocks at x and where the feedforward
    evaluates it; x, x_d, e (n, 2d): the states and the error; state_finite, finite (n,): the
    finger's state, and the feedback step's blocks and states, were finite; P (n, 2d, 2d), residual,
    iterations, failed (n,): the solve's record; u, u_unsat, u_ff (n, m), saturated (n, m),
    ff_usable, unreachable (n,): the command.
    """

    def __init__(self, n: int, d: int, m: int) -> None:
        k = 2 * d
        self.a2, self.a2_ff = np.zeros((n, d, k)), np.zeros((n, d, k))
        self.g2, self.g2_ff = np.zeros((n, d, m)), np.zeros((n, d, m))
        self.x, self.x_d, self.e = np.zeros((n, k)), np.zeros((n, k)), np.zeros((n, k))
        self.state_finite, self.finite = np.zeros(n, np.bool_), np.zeros(n, np.bool_)
        self.P = np.zeros((n, k, k))
        self.residual = np.zeros(n)
        self.iterations, self.failed = np.zeros(n, np.int64), np.zeros(n, np.int64)
        self.u, self.u_unsat, self.u_ff = np.zeros((n, m)), np.zeros((n, m)), np.zeros((n, m))
        self.saturated = np.zeros((n, m), np.bool_)
        self.ff_usable, self.unreachable = np.zeros(n, np.bool_), np.zeros(n)


def no_integral(n: int, d: int, m: int) -> tuple:
    """The integral arguments of :func:`~soft_gripper_sdre.control.kernels.general.
    general_feedforward_finish` for a law without integral action (``integral`` False; arrays of
    the types the kernel is compiled for)."""
    return (False, np.zeros((n, d)), np.zeros((m, d)), np.zeros((d, m)), np.zeros((d, d)),
            np.zeros(m), 0.0, 0.0, 0.0)


def warm_up_general(d: int = 3, m: int = 2) -> None:
    """Compile (or load) the general kernels: one compilation serves every (d, m), the sizes
    being the arrays' (the types are the same)."""
    n, k = 1, 2 * d
    h = 2
    network = SdcNetwork.pack(np.zeros((k, h)), np.zeros(h), np.zeros((h, h)), np.zeros(h),
                              np.zeros((h, 2 * d * d + d * m)), np.zeros(2 * d * d + d * m))
    o = GeneralOutputs(n, d, m)
    settings = (np.eye(k), np.eye(m), np.eye(m), 1e-6, 1e8, 5)
    state = (np.zeros((n, k, k)), np.zeros((n, m, k)), np.zeros((n, m, k)), np.ones(n, np.bool_))
    record = (o.finite, o.P, o.residual, o.iterations, o.failed)
    shaped_forward(o.x, *network, o.a2, o.g2)
    general_step_gains(o.x, o.x_d, o.a2, o.g2, *settings, *state, *record)
    general_tracking_gains(np.zeros((n, 4 * d)), np.zeros(d), *network, *settings, *state, o.a2,
                           o.g2, o.x, o.x_d, *record)
    general_feedforward_gains(np.zeros((n, 5 * d)), np.zeros(d), False, *network, *settings,
                              *state, o.a2, o.g2, o.a2_ff, o.g2_ff, o.x, o.x_d, o.e,
                              o.state_finite, *record)
    bounds = (-np.ones(m), np.ones(m))
    general_torques(o.x, o.x_d, o.finite, state[1], state[2], *bounds, o.u_unsat, o.u)
    general_feedforward_finish(np.zeros((n, 5 * d)), o.x_d, o.e, o.state_finite, o.finite,
                               state[1], o.a2_ff, o.g2_ff, 1e8, *bounds, *no_integral(n, d, m),
                               o.u_ff, o.ff_usable, o.unreachable, o.u_unsat, o.u, o.saturated)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel at the types the controller uses: call it
    before a node reports ready, so that no step pays for compilation."""
    warm_up_hand()
    warm_up_general()


def warm_up_hand() -> None:
    """Compile (or load) the kernels of the hand's shape (d = 2, m = 2): :func:`warm_up` without
    :func:`warm_up_general`, which another process can compile meanwhile (``make kernels``)."""
    n = 1
    network = SdcNetwork.pack(np.zeros((4, 2)), np.zeros(2), np.zeros((2, 2)), np.zeros(2),
                              np.zeros((2, 12)), np.zeros(12))
    records = (SdreSettings.of(np.eye(4), np.eye(2), 1.0).records, SdreState(n).records,
               SdreOutputs(n).records)
    x, rows, ones = np.zeros((n, 4)), np.zeros((n, 2)), np.ones(n, dtype=np.bool_)
    sdc_forward(x, *network, np.zeros((n, 2, 4)), np.zeros((n, 2, 2)))
    sdre_gains(ones, *records)
    tracking_torques(x, x.copy(), ones, *records)
    sdre_step(x, x.copy(), *records)
    model_inversion(np.zeros((n, 2, 4)), np.zeros((n, 2, 2)), x, rows, 1e8, rows.copy(),
                    ones.copy())
    tracking_step(np.zeros((n, 8)), np.zeros(2), *network, *records)
    feedforward_step(np.zeros((n, 10)), np.zeros(2), False, *network, *records,
                     FeedforwardOutputs(n).records)
    kf_step(x, np.zeros((n, 4, 4)), rows, ones, np.eye(4), np.eye(4), np.eye(2))
    kf_step_dt(x, np.zeros((n, 4, 4)), rows, ones, 1e-3, 1.0, 0.0, np.eye(4), np.eye(4), np.eye(2))
    integral = IntegralSettings.of(np.eye(2), np.eye(2), 1e-3, 1e-3, 0.9, 1.0).records
    saturated = np.zeros((n, 2), dtype=np.bool_)
    integral_step(rows.copy(), integral, rows, ones, rows.copy(), rows.copy(), saturated)
    integral_update(rows.copy(), integral, rows, saturated, ones)
    integral_roll_off(rows.copy(), integral, np.zeros((n, 10)), ones, rows.copy(), rows.copy(),
                      saturated, 0.5, rows.copy(), True)
    plan = np.zeros((2, n, 2))
    plan_sample(np.array([0, 1], dtype=np.int64), plan, plan, plan, 0, rows.copy(), rows.copy(),
                rows.copy())


def warm_up_check_loop() -> None:
    """Compile (or load from numba's cache) the closed-loop check's kernel
    (:func:`~soft_gripper_sdre.control.kernels.check_loop.feedforward_check_steps`) at the types
    the training's checks call it with: a process calls it before it forks the checks' workers,
    which then inherit it. Not part of :func:`warm_up`: no node runs it."""
    network = SdcNetwork.pack(np.zeros((4, 2)), np.zeros(2), np.zeros((2, 2)), np.zeros(2),
                              np.zeros((2, 12)), np.zeros(12))
    state = SdreState(1).records
    integral = IntegralSettings.of(np.eye(2), np.eye(2), 1e-3, 1e-3, 0.9, 1.0).records
    none = np.zeros((0, 2))
    layers = (np.zeros((4, 2)), np.zeros(2), np.zeros((2, 2)), np.zeros(2), np.zeros((2, 12)),
              np.zeros(12))
    feedforward_check_steps(
        0, none, 0.0, np.zeros(2), none, none, none, np.zeros((1, 4)), np.zeros((1, 4, 4)),
        np.eye(4), np.eye(4), np.eye(2), np.zeros(2), False, *network,
        SdreSettings.of(np.eye(4), np.eye(2), 1.0).records, state, SdreOutputs(1).records,
        FeedforwardOutputs(1).records, state.copy(), np.zeros((1, 2)), integral, 0.0,
        np.zeros((1, 2)), np.zeros(1, dtype=np.bool_), np.zeros((1, 2)), np.zeros(4), 0,
        np.zeros(2), np.zeros(2), 1.0, 1e-3, 1, *layers, np.zeros((1, 1)), np.zeros((1, 1)), 1.0,
        none.copy(), none.copy(), np.zeros(0, dtype=np.bool_))


# before any kernel runs: numba's cache of them held to the kernel modules' sources as a whole
invalidate_stale_cache()
