"""The SDRE supervisor: the paper's law u = K(x) x + K_s(x) x_d (eq. 22, saturated) for n fingers.

K, K_s and the checks are those of eq. 23–24 and Remarks 2–3
(:mod:`~soft_gripper_sdre.control.riccati`). Two paths compute them:

* ``method='fast'``: the compiled kernels (:mod:`~soft_gripper_sdre.control.kernels`: warm-started
  Newton–Kleinman on the SDC form with the structure's checks, a warm finger that fails them
  solved again from scratch, the gains and the law in one call); a finger the kernel hands back
  (cold: first step or its last step was rejected; or a check failed after the restart too)
  takes the exact path alone: scipy's solver and the general checks, after which its
  torques are formed again with the gains now in use. Inputs not in SDC form, and weights for
  which the SDC form does not prove detectability, take the reference path.
* ``method='reference'``: scipy and the general checks for every finger, every step.

The hand's kernels serve the hand (d = 2, m = 2, bounds ±u_max:
:func:`~soft_gripper_sdre.control.tracking.hand_path`); a controller of any other shape (a state
of 2d, m inputs, read from the sizes of Q and R) or bounds runs the reference path's checks
whichever ``method`` is asked for. With ``'fast'`` its inputs are taken in SDC form (the
stabilisability test on G2's rank instead of the PBH test where G2 has full row rank) and each
finger with an accepted solution starts from it: Newton–Kleinman (at most ``max_nk_iterations``
Lyapunov solves), scipy's CARE only where that fails a check. The general kernels
(:mod:`~soft_gripper_sdre.control.kernels.general`) do that step, its checks and the torques in
compiled code (``compiled=True``, the default, with weights whose Q or position block is ≻ 0:
``general_kernels``), numpy does it otherwise
(:func:`~soft_gripper_sdre.control.riccati.newton_kleinman`); the two give the same torques to
rounding. ``'reference'`` solves every finger with scipy.

The supervisor owns the state the kernels update (warm starts, the gains in use), the exact path
and the counters: a finger whose step fails any check uses its last valid gains (fallback), or a
nominal model's before it has any, or zero torque, and ``u`` is always finite.
docs/design/compiled_kernel.md has the derivations.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from soft_gripper_sdre.control.kernels import (
    FeedforwardOutputs,
    GeneralOutputs,
    SdcNetwork,
    SdreOutputs,
    SdreSettings,
    SdreState,
    feedforward_step,
    general_feedforward_finish,
    general_feedforward_gains,
    general_step_gains,
    general_torques,
    general_tracking_gains,
    kernel_array,
    sdre_step,
    tracking_step,
    tracking_torques,
)
from soft_gripper_sdre.control.riccati import (
    Check,
    checked_weights,
    full_sdc_matrices,
    in_sdc_form,
    riccati_cost,
    sdre_gains,
    solve_and_check,
)
from soft_gripper_sdre.control.tracking import LawStep, hand_path, law_bounds
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

METHODS = ('fast', 'reference')
_CHECK_BITS = tuple((c.name, int(c)) for c in Check)
#: the kernel's Check bits that are final: the exact path tests these in the same form
_FINAL_BITS = int(Check.NONFINITE | Check.STABILIZABLE)


def _checked(**arrays) -> list[np.ndarray]:
    """Each ``name=(value, shape)`` as a float64 array the kernels take, in order; ValueError
    naming the first of another shape."""
    out = []
    for name, (value, shape) in arrays.items():
        arr = kernel_array(value)
        if arr.shape != shape:
            raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
        out.append(arr)
    return out


def _finite_rows(*arrays: np.ndarray) -> np.ndarray:
    """(n,) every entry of row i of every (n, …) array is finite."""
    finite = np.ones(arrays[0].shape[0], dtype=bool)
    for a in arrays:
        finite &= np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
    return finite


class GeneralState:
    """The state the reference path keeps for ``n`` fingers of any shape: the last accepted P
    (n, 2d, 2d), the gains in use K, K_s (n, m, 2d) and whether P holds an accepted solution."""

    def __init__(self, n: int, shape: FingerShape) -> None:
        k = shape.n_state
        self.P = np.zeros((n, k, k))
        self.K = np.zeros((n, shape.m, k))
        self.Ks = np.zeros((n, shape.m, k))
        self.warm = np.zeros(n, dtype=bool)


def rest_frame_states(z: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, x_d) = ([p − p₀, ṗ], [p_d − p₀, ṗ_d]), each (n, 4), from the rows z = [p, ṗ, p_d, ṗ_d, …]
    as the kernels form them."""
    return (np.concatenate((z[:, 0:2] - origin, z[:, 2:4]), axis=1),
            np.concatenate((z[:, 4:6] - origin, z[:, 6:8]), axis=1))


class SdreCounters:
    """What the SDRE supervisor counts over its steps, and the step's record, which counts them.

    ``steps``; ``fallbacks``: finger-steps on which a finger failed a check (non-finite inputs
    included) and kept its last valid gains; ``exact_solves``: the fingers scipy solved;
    ``check_failures``: per :class:`Check`, the finger-steps that failed it.
    """

    n: int    # the number of fingers

    def reset_counters(self) -> None:
        self.steps = self.fallbacks = self.exact_solves = 0
        self.check_failures = {c.name: 0 for c in Check}

    def _record(self, u, u_unsat, K, Ks, P, residual, ok, failed, iterations,
                accepted: int) -> LawStep:
        """The step's :class:`LawStep` (arrays the caller owns), counted. ``accepted``: how many
        fingers are ``ok``."""
        fallbacks = self.n - accepted
        if fallbacks:                     # a finger with a failed check is never ok
            self.fallbacks += fallbacks
            for name, bit in _CHECK_BITS:
                self.check_failures[name] += int(np.count_nonzero(failed & bit))
        # u = clip(u_unsat) with u_unsat finite: u ≠ u_unsat ⇔ |u_unsat| > u_max
        return LawStep(u=u, u_unsat=u_unsat, K=K, Ks=Ks, P=P, residual=residual, ok=ok,
                       fallback=~ok, failed_checks=failed, saturated=u != u_unsat,
                       nk_iterations=iterations)


class SdreController(SdreCounters):
    """The SDRE tracking law for ``n`` fingers with fallbacks and counters.

    Args:
        Q: (2d, 2d) state weight, symmetric PSD (SI); d = 2 or 3 (the hand: 4 × 4).
        R: (m, m) input weight, symmetric PD (SI); m = 1 to 4 inputs (the hand: 2 × 2).
        u_max: saturation ±u_max per input [N·m] (scalar or (m,)) where ``bounds`` is None.
        n: number of fingers.
        method: ``'fast'`` or ``'reference'``.
        residual_tol: largest accepted relative Riccati residual.
        cond_max: largest accepted condition number of G2 and of A_cl (``'fast'``: of A_cl's
            lower-left block, the only part of A_cl whose inverse the law uses).
        max_nk_iterations: most Newton–Kleinman iterations per step before the exact path.
        nominal: optional (A0, G0) whose gains serve as the fallback before any valid step.
        bounds: per-input [lower, upper] the torques are clipped to (None: ±``u_max``).
        compiled: off the hand's path with ``'fast'``, whether the general kernels run the
            warm-started step (True) or numpy does (False, the yardstick of the tests and the
            benchmark).

    ``shape`` is the finger's (from Q and R), ``bounds`` what the torques are clipped to, ``hand``
    whether the hand's code serves it (:func:`~soft_gripper_sdre.control.tracking.hand_path`),
    ``fast`` whether the hand's compiled kernels do and ``general_kernels`` whether the general
    ones do; the counters are those of :class:`SdreCounters`.
    """

    def __init__(self, Q, R, u_max, n: int = 4, method: str = 'fast', residual_tol: float = 1e-6,
                 cond_max: float = 1e8, max_nk_iterations: int = 5, nominal=None,
                 bounds: InputBounds | None = None, compiled: bool = True) -> None:
        self.Q, self.R, self.u_max = checked_weights(Q, R, 1.0 if bounds is not None else u_max)
        self.shape = FingerShape(self.Q.shape[0] // 2, self.R.shape[0])
        if bounds is not None:
            bounds = law_bounds(self.shape, 0.0, bounds)
            self.u_max = np.maximum(-bounds.lower, bounds.upper)
        self.bounds = InputBounds(-self.u_max, self.u_max) if bounds is None else bounds
        self.hand = hand_path(self.shape, self.bounds)
        self._lower, self._upper = (-self.u_max, self.u_max) if self.hand else (
            kernel_array(self.bounds.lower), kernel_array(self.bounds.upper))
        if method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {method!r}')
        self.n, self.method = int(n), method
        self.residual_tol, self.cond_max = float(residual_tol), float(cond_max)
        if int(max_nk_iterations) < 1:
            raise ValueError(f'max_nk_iterations must be >= 1, got {max_nk_iterations!r}')
        self.max_nk_iterations = int(max_nk_iterations)
        self._cost = riccati_cost(self.Q, self.R)
        # the kernel's detectability argument needs Q ≻ 0 or Q's position block ≻ 0
        if not isinstance(compiled, (bool, np.bool_)):
            raise ValueError(f'compiled must be True or False, got {compiled!r}')
        detectable = self._cost.q_definite or self._cost.q_position_definite
        self.fast = method == 'fast' and self.hand and detectable
        self.general_kernels = (method == 'fast' and not self.hand and bool(compiled)
                                and detectable)
        if self.hand:
            self.settings = SdreSettings.of(self.Q, self.R, self.u_max, self.residual_tol,
                                            self.cond_max, int(max_nk_iterations))
            self.state, self.outputs = SdreState(self.n), SdreOutputs(self.n)
            self.feedforward = FeedforwardOutputs(self.n)
        else:                                   # the reference path's state alone
            self.settings = self.outputs = self.feedforward = None
            self.state = GeneralState(self.n, self.shape)
        self.general = (GeneralOutputs(self.n, self.shape.d, self.shape.m)
                        if self.general_kernels else None)
        # the general kernels' settings: Q, R, R⁻¹, residual_tol, cond_max, max_iterations
        self._general_settings = (self.Q.copy(), self.R.copy(), kernel_array(self._cost.R_inv),
                                  self.residual_tol, self.cond_max, self.max_nk_iterations)
        self._nominal = None
        if nominal is not None:
            K0, Ks0, _ = sdre_gains(np.asarray(nominal[0], float), np.asarray(nominal[1], float),
                                    self.Q, self.R)
            self._nominal = (K0, Ks0)
        self.reset()

    def reset(self) -> None:
        """Forget warm starts and last valid gains; zero the counters."""
        s = self.state
        s.P[:], s.warm[:] = 0.0, False
        s.K[:], s.Ks[:] = (0.0, 0.0) if self._nominal is None else self._nominal
        self.reset_counters()

    def warm_start(self, P) -> None:
        """Start every finger's next fast step from P (n, 2d, 2d) instead of its last solution (the
        kernel's checks still decide whether the result is used)."""
        self.state.P[:] = _checked(P=(P, self.state.P.shape))[0]
        self.state.warm[:] = True

    # -- the steps ---------------------------------------------------------------------------
    def step(self, A, G, x, x_d) -> LawStep:
        """Torques for every finger: A (n,2d,2d), G (n,2d,m), x (n,2d), x_d (n,2d), translated SI
        (the hand: 2d = 4, m = 2)."""
        n, k, m = self.n, self.shape.n_state, self.shape.m
        A, G, x, x_d = _checked(A=(A, (n, k, k)), G=(G, (n, k, m)), x=(x, (n, k)),
                                x_d=(x_d, (n, k)))
        sdc = self.method == 'fast' and in_sdc_form(A, G)
        if self.fast and sdc:
            return self.step_sdc(A[:, 2:, :], G[:, 2:, :], x, x_d)
        if self.general_kernels and sdc:
            d = self.shape.d
            return self.step_sdc(A[:, d:, :], G[:, d:, :], x, x_d)
        return self._reference_step(A, G, x, x_d, sdc)

    def step_sdc(self, A2, G2, x, x_d) -> LawStep:
        """:meth:`step` for a model in SDC form, given only its lower rows:
        A2 = [A21 A22] (n,d,2d) and G2 (n,d,m), so that A = [[0, I], A2] and G = [[0], G2]."""
        n, d, m = self.n, self.shape.d, self.shape.m
        A2, G2, x, x_d = _checked(A2=(A2, (n, d, 2 * d)), G2=(G2, (n, d, m)), x=(x, (n, 2 * d)),
                                  x_d=(x_d, (n, 2 * d)))
        if self.general_kernels:
            o = self.general
            o.a2[:], o.g2[:] = A2, G2
            general_step_gains(x, x_d, o.a2, o.g2, *self._general_settings, *self._state_arrays(),
                               o.finite, o.P, o.residual, o.iterations, o.failed)
            return self._settle_general(x, x_d)
        if not self.fast:
            return self._reference_step(*full_sdc_matrices(A2, G2), x, x_d, self.method == 'fast')
        out = self.outputs
        out.a2[:], out.g2[:] = A2, G2
        sdre_step(x, x_d, self.settings.records, self.state.records, out.records)
        return self._settle(lambda: (x, x_d))

    def track(self, network: SdcNetwork, origin: np.ndarray, z: np.ndarray) -> LawStep:
        """:meth:`step_sdc` on the fused network's blocks at the states x = [p − p₀, ṗ],
        x_d = [p_d − p₀, ṗ_d] (``fast`` only): z (n, 8) = [p, ṗ, p_d, ṗ_d], a C-contiguous float64
        array of base-frame positions and velocities (:meth:`RestFrame.stacked
        <soft_gripper_sdre.control.tracking.RestFrame.stacked>`), ``origin`` p₀ (2,)."""
        tracking_step(z, origin, *network, self.settings.records, self.state.records,
                      self.outputs.records)
        return self._settle(lambda: rest_frame_states(z, origin))

    def track_feedforward(self, network: SdcNetwork, origin: np.ndarray, ff_at_reference: bool,
                          z: np.ndarray) -> LawStep:
        """The feedforward law's step (``fast`` only; as :meth:`track` with z (n, 10) =
        [p, ṗ, p_d, ṗ_d, a_d]): u = u_ff + K(x) e, e = x − x_d, u_ff = G2⁻¹ (a_d − A2 x_d) with the
        model at x or (``ff_at_reference``) at x_d. :attr:`feedforward` holds u_ff and which fingers
        had a finite state and a usable feedforward; the step's ``ok`` also needs the first, its
        ``fallback`` is set without either (``fallbacks`` counts the feedback's alone)."""
        ff = self.feedforward
        feedforward_step(z, origin, ff_at_reference, *network, self.settings.records,
                         self.state.records, self.outputs.records, ff.records)

        def error_states():
            x, x_d = rest_frame_states(z, origin)
            x -= x_d
            x[~ff.state_finite] = 0.0                         # solved at x = x_d = 0
            return x, np.zeros_like(x)
        step = self._settle(error_states, feedforward=True)
        if np.count_nonzero(ff.state_finite) + np.count_nonzero(ff.ff_usable) != 2 * self.n:
            step.ok &= ff.state_finite
            step.fallback |= ~ff.state_finite | ~ff.ff_usable
        return step

    # -- the general kernels (any shape and bounds) --------------------------------------------
    def _state_arrays(self) -> tuple:
        s = self.state
        return s.P, s.K, s.Ks, s.warm

    def track_general(self, network: SdcNetwork, origin: np.ndarray, z: np.ndarray) -> LawStep:
        """:meth:`track` for any shape (``general_kernels`` only): z (n, 4d) = [p, ṗ, p_d, ṗ_d],
        ``origin`` p₀ (d,), the fused network of the model's shape."""
        o = self.general
        general_tracking_gains(z, origin, *network, *self._general_settings,
                               *self._state_arrays(), o.a2, o.g2, o.x, o.x_d, o.finite, o.P,
                               o.residual, o.iterations, o.failed)
        return self._settle_general(o.x, o.x_d)

    def track_feedforward_general(self, network: SdcNetwork, origin: np.ndarray,
                                  ff_at_reference: bool, z: np.ndarray,
                                  integral: tuple) -> LawStep:
        """The feedforward law's step before its roll-off for any shape (``general_kernels``
        only; :func:`~soft_gripper_sdre.control.laws.feedforward.combine_feedforward` on the
        general path): z (n, 5d) = [p, ṗ, p_d, ṗ_d, a_d], u = G₂⁺(a_d − A₂ x_d) + K(x) e (+ the
        reachable integral's u_I), clipped to the bounds. ``integral``: the integral's kernel
        arguments (:meth:`ReachableIntegralAction.kernel_args
        <soft_gripper_sdre.control.laws.integral.ReachableIntegralAction.kernel_args>`, or
        :func:`~soft_gripper_sdre.control.kernels.no_integral`), whose ξ is updated in place.
        The step's ``ok`` needs a finite state too; ``fallback`` is set without one or without a
        usable feedforward; ``unreachable`` is the demand no input reaches."""
        o = self.general
        general_feedforward_gains(z, origin, ff_at_reference, *network, *self._general_settings,
                                  *self._state_arrays(), o.a2, o.g2, o.a2_ff, o.g2_ff, o.x,
                                  o.x_d, o.e, o.state_finite, o.finite, o.P, o.residual,
                                  o.iterations, o.failed)
        failed, iterations, P, residual, accepted = self._exact_general()
        s = self.state
        general_feedforward_finish(z, o.x_d, o.e, o.state_finite, o.finite, s.K, o.a2_ff,
                                   o.g2_ff, self.cond_max, self._lower, self._upper, *integral,
                                   o.u_ff, o.ff_usable, o.unreachable, o.u_unsat, o.u,
                                   o.saturated)
        step = self._record(o.u.copy(), o.u_unsat.copy(), s.K.copy(), s.Ks.copy(), P, residual,
                            s.warm.copy(), failed, iterations, accepted)
        step.saturated = o.saturated.copy()
        step.ok &= o.state_finite
        step.fallback |= ~o.state_finite | ~o.ff_usable
        step.unreachable = o.unreachable.copy()
        return step

    def _exact_general(self):
        """After a general kernel's gains: scipy and the general checks for every finger it
        handed back (cold, failed or not finite); an accepted solution becomes its state. Counts
        the step; returns the step's (failed, iterations, P, residual) and how many fingers hold
        accepted gains."""
        s, o = self.state, self.general
        self.steps += 1
        failed, iterations = o.failed.copy(), o.iterations.copy()
        P, residual = o.P.copy(), o.residual.copy()
        accepted = np.count_nonzero(s.warm)
        if accepted != self.n:
            idx = np.flatnonzero(~s.warm)
            A, G = full_sdc_matrices(o.a2[idx], o.g2[idx])
            P_exact, checked, solves = solve_and_check(A, G, o.finite[idx], True, self._cost,
                                                       self.residual_tol, self.cond_max)
            self.exact_solves += solves
            failed[idx], iterations[idx], P[idx], residual[idx] = (checked.failed, 0, P_exact,
                                                                   checked.residual)
            ok = checked.ok
            good = idx[ok]
            s.P[good], s.K[good], s.Ks[good], s.warm[good] = (P_exact[ok], checked.K[ok],
                                                              checked.Ks[ok], True)
            accepted = np.count_nonzero(s.warm)
        return failed, iterations, P, residual, accepted

    def _settle_general(self, x: np.ndarray, x_d: np.ndarray) -> LawStep:
        """The step's record after a general kernel's gains at (x, x_d): the exact path for the
        fingers it handed back, then every finger's torques with the gains in use."""
        failed, iterations, P, residual, accepted = self._exact_general()
        s, o = self.state, self.general
        general_torques(x, x_d, o.finite, s.K, s.Ks, self._lower, self._upper, o.u_unsat, o.u)
        return self._record(o.u.copy(), o.u_unsat.copy(), s.K.copy(), s.Ks.copy(), P, residual,
                            s.warm.copy(), failed, iterations, accepted)

    # -- after a kernel ----------------------------------------------------------------------
    def _settle(self, feedback_states: Callable[[], tuple[np.ndarray, np.ndarray]],
                feedforward: bool = False) -> LawStep:
        """The step's record after a kernel call; first the exact path for the fingers it handed
        back, given the (x, x_d) its SDRE step used."""
        s, out = self.state, self.outputs
        self.steps += 1
        failed, iterations, P = out.failed.copy(), out.iterations.copy(), s.P.copy()
        accepted = np.count_nonzero(s.warm)
        if accepted != self.n:
            x, x_d = feedback_states()
            self._exact_path(x, x_d, failed, iterations, P)
            if feedforward:  # u = u_ff + K e, as the kernel composes it
                ff = self.feedforward
                v = ff.u_ff + out.u_unsat
                v[~(np.isfinite(v) & ff.state_finite[:, None])] = 0.0
                out.u_unsat[:] = v
                np.clip(v, -self.u_max, self.u_max, out=out.u)
            accepted = np.count_nonzero(s.warm)
        return self._record(out.u.copy(), out.u_unsat.copy(), s.K.copy(), s.Ks.copy(), P,
                            out.residual.copy(), s.warm.copy(), failed, iterations, accepted)

    def _exact_path(self, x, x_d, failed, iterations, P) -> None:
        """scipy and the general checks for each finger the kernel handed back with usable inputs;
        an accepted solution becomes its state (gains, warm start); then every finger's torques
        with the gains in use. ``failed``, ``iterations`` and ``P`` (the step's record) are
        updated in place."""
        s, out = self.state, self.outputs
        P[~s.warm] = np.nan
        idx = np.flatnonzero(~s.warm & ((failed & _FINAL_BITS) == 0))
        if idx.size:
            A, G = full_sdc_matrices(out.a2[idx], out.g2[idx])
            P_exact, checked, solves = solve_and_check(A, G, np.ones(idx.size, dtype=bool), True,
                                                       self._cost, self.residual_tol, self.cond_max)
            self.exact_solves += solves
            (failed[idx], iterations[idx], P[idx],
             out.residual[idx]) = checked.failed, 0, P_exact, checked.residual
            ok = checked.ok
            accepted = idx[ok]
            (s.P[accepted], s.K[accepted], s.Ks[accepted],
             s.warm[accepted]) = P_exact[ok], checked.K[ok], checked.Ks[ok], True
        finite = _finite_rows(out.a2, out.g2, x, x_d)
        tracking_torques(x, x_d, finite, self.settings.records, s.records, out.records)

    # -- the reference path ------------------------------------------------------------------
    def _reference_step(self, A, G, x, x_d, sdc: bool) -> LawStep:
        """scipy and the general checks for every finger; a finger that fails keeps its last gains.
        ``sdc``: test stabilisability in the SDC form (cond(G2)) instead of by PBH."""
        self.steps += 1
        finite = _finite_rows(A, G, x, x_d)
        # off the hand's path 'fast' warm-starts each finger from its last accepted solution
        warm = (None if self.hand or self.method != 'fast'
                else (self.state.P, self.state.warm, self.max_nk_iterations))
        P, checked, solves = solve_and_check(A, G, finite, sdc, self._cost, self.residual_tol,
                                             self.cond_max, warm)
        self.exact_solves += solves
        ok, s = checked.ok, self.state
        s.K[ok], s.Ks[ok], s.P[ok], s.warm[:] = checked.K[ok], checked.Ks[ok], P[ok], ok
        K, Ks = s.K.copy(), s.Ks.copy()
        xs = np.where(finite[:, None], x, 0.0)
        xds = np.where(finite[:, None], x_d, 0.0)
        u_unsat = np.einsum('nij,nj->ni', K, xs) + np.einsum('nij,nj->ni', Ks, xds)   # eq. 22
        u_unsat = np.where(np.isfinite(u_unsat), u_unsat, 0.0)
        u_unsat[~finite] = 0.0            # no torque from a state we cannot read
        u = np.clip(u_unsat, self._lower, self._upper)
        return self._record(u, u_unsat, K, Ks, P, checked.residual, ok, checked.failed,
                            np.zeros(self.n, dtype=np.int64), np.count_nonzero(ok))
