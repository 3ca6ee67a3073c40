"""Beyond the paper: SDRE feedback on the tracking error plus model-inversion feedforward."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.batched_linalg import batched_solve, well_conditioned_2x2
from soft_gripper_sdre.control.kernels import SdcNetwork, compiled_network, no_integral
from soft_gripper_sdre.control.laws.integral import (
    DEFAULT_INTEGRAL,
    IntegralAction,
    ReachableIntegralAction,
)
from soft_gripper_sdre.control.laws.registry import (
    WEIGHT_PARAMS,
    LawParam,
    LawSettings,
    register_law,
)
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    LawIO,
    LawStep,
    RollOff,
    Weights,
    shape_of,
)
from soft_gripper_sdre.sim.shape import InputBounds

#: where the feedforward's model is evaluated (:class:`SdreFeedforwardLaw`)
FF_AT = ('x', 'ref')


def model_inversion(A2: np.ndarray, G2: np.ndarray, x_d: np.ndarray, a_d: np.ndarray,
                    cond_max: float = 1e8) -> tuple[np.ndarray, np.ndarray]:
    """Feedforward torque that makes the SDC model follow the reference, for n fingers:

        u_ff = G₂⁻¹ (a_d − A₂₁ p_d − A₂₂ v_d) = G₂⁻¹ (a_d − A₂ x_d)

    with A₂ = [A₂₁ A₂₂] (n,2,4) and G₂ (n,2,2) the SDC lower rows wherever the caller evaluated
    them, x_d (n,4) the reference state, a_d (n,2) its acceleration. Returns (u_ff (n,2),
    usable (n,)): fingers whose G₂ is singular (cond ≥ ``cond_max``) or whose inputs are not
    finite get u_ff = 0, usable False.
    """
    rhs = a_d - (A2 @ x_d[:, :, None])[:, :, 0]                       # a_d − A₂₁ p_d − A₂₂ v_d
    with np.errstate(all='ignore'):                                    # NaN where G₂ is singular
        usable = well_conditioned_2x2(G2, cond_max)[0]
        u = batched_solve(G2, rhs)                                     # G₂ u_ff = rhs
    usable &= np.isfinite(u).all(axis=1)
    if not usable.all():
        u[~usable] = 0.0
    return u, usable


def pseudo_inversion(A2: np.ndarray, G2: np.ndarray, x_d: np.ndarray, a_d: np.ndarray,
                     cond_max: float = 1e8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`model_inversion` for any shape: u_ff = G₂⁺ (a_d − A₂ x_d) for n fingers with A₂
    (n, d, 2d), G₂ (n, d, m), x_d (n, 2d), a_d (n, d).

    G₂⁺ is the pseudo-inverse: exact where G₂ is square and regular, the least-squares input where
    m < d (the demand's part outside G₂'s range is not chased), the minimum-norm input where m > d.
    Returns (u_ff (n, m), usable (n,), unreachable (n,)): fingers whose G₂ is ill conditioned
    (σ_max ≥ ``cond_max`` σ_min over its min(d, m) singular values, or zero) or whose inputs are
    not finite get u_ff = 0, usable False; ``unreachable`` [m/s²] is the norm of the demand's part
    outside G₂'s range, ‖(I − G₂G₂⁺)(a_d − A₂ x_d)‖ (singular values below σ_max / ``cond_max``
    counted as zero; 0 where the inputs are not finite).
    """
    n, d, m = G2.shape
    rhs = a_d - (A2 @ x_d[:, :, None])[:, :, 0]                       # a_d − A₂ x_d
    finite = np.isfinite(G2).all(axis=(1, 2)) & np.isfinite(rhs).all(axis=1)
    G = np.where(finite[:, None, None], G2, 0.0)
    r = np.where(finite[:, None], rhs, 0.0)
    U, sv, Vt = np.linalg.svd(G, full_matrices=False)    # (n, d, k), (n, k), (n, k, m), k=min(d,m)
    c = np.einsum('ndk,nd->nk', U, r)                                  # Uᵀ r
    with np.errstate(all='ignore'):
        usable = finite & (sv[:, 0] > 0.0) & (sv[:, 0] < cond_max * sv[:, -1])
        coef = np.where(usable[:, None], c / np.where(sv > 0.0, sv, 1.0), 0.0)
    u = np.einsum('nkm,nk->nm', Vt, coef)                              # V Σ⁻¹ Uᵀ r
    usable &= np.isfinite(u).all(axis=1)
    u[~usable] = 0.0
    in_range = sv > sv[:, :1] / cond_max                               # numerical rank
    reached = np.einsum('ndk,nk->nd', U, np.where(in_range, c, 0.0))   # U Uᵀ r on the range
    unreachable = np.where(finite, np.linalg.norm(r - reached, axis=1), 0.0)
    return u, usable, unreachable


def reference_acceleration(ref_acc, n: int, d: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(a_d (n,d), finite (n,)) from a law's ``ref_acc``: None = zero acceleration; non-finite
    rows become zero.

    Raises:
        ValueError: ``ref_acc`` is not (n, d).
    """
    if ref_acc is None:
        return np.zeros((n, d)), np.ones(n, dtype=bool)
    a = np.array(ref_acc, dtype=float)
    if a.shape != (n, d):
        raise ValueError(f'ref_acc must have shape ({n}, {d}), got {a.shape}')
    finite = np.all(np.isfinite(a), axis=1)
    a[~finite] = 0.0
    return a, finite


def combine_feedforward(io: LawIO, feedback: LawStep, A2: np.ndarray, G2: np.ndarray,
                        x_d: np.ndarray, finite: np.ndarray, ref_acc,
                        u_extra: np.ndarray | None = None) -> LawStep:
    """u = u_ff + K e (+ ``u_extra``, e.g. an integral term, before clipping): ``feedback`` is
    the SDRE's step on (e = x − x_d, x_d = 0), whose u_unsat = K(x) e; (A2, G2) the SDC lower rows
    the feedforward inverts (:func:`model_inversion` on the hand's path, ``io.hand``, else
    :func:`pseudo_inversion`, whose unreachable demand the step reports). A finger without
    feedforward (singular G₂, non-finite ``ref_acc``) is flagged ``fallback``."""
    a_d, acc_ok = reference_acceleration(ref_acc, io.n_fingers, io.shape.d)
    unreachable = None
    if io.hand:
        u_ff, ff_ok = model_inversion(A2, G2, x_d, a_d)
    else:
        u_ff, ff_ok, unreachable = pseudo_inversion(A2, G2, x_d, a_d)
        unreachable = np.where(finite & acc_ok, unreachable, 0.0)
    ff_ok &= acc_ok
    u_unsat = u_ff + feedback.u_unsat                                 # u = u_ff + K(x) e
    if u_extra is not None:
        u_unsat += u_extra
    out = io.finish(u_unsat, finite)
    out.ok, out.fallback = feedback.ok & finite, feedback.fallback | ~finite | ~ff_ok
    out.failed_checks, out.residual = feedback.failed_checks, feedback.residual
    out.K, out.Ks, out.P, out.nk_iterations = (feedback.K, feedback.Ks, feedback.P,
                                               feedback.nk_iterations)
    if unreachable is not None:
        out.unreachable = unreachable
    return out


class HandKernelParts(NamedTuple):
    """What a compiled loop of :class:`SdreFeedforwardLaw`'s steps takes of the law
    (:meth:`SdreFeedforwardLaw.hand_kernel_parts`): its own arrays, updated in place there."""

    origin: np.ndarray          # p₀ (2,): the rest frame's origin
    ff_at_reference: bool       # the feedforward evaluates the model at x_d
    network: SdcNetwork
    settings: np.ndarray        # the SDRE's records: settings, state, outputs, feedforward
    state: np.ndarray
    outputs: np.ndarray
    feedforward: np.ndarray
    xi: np.ndarray              # the integral's ξ (1, 2) and its settings record
    integral: np.ndarray
    roll_off: RollOff


class SdreFeedforwardLaw:
    """SDRE feedback on the tracking error plus model-inversion feedforward.

    The learned SDC model is ẋ = A(x)x + G(x)u with A = [[0, I], [A₂₁, A₂₂]], G = [[0], [G₂]].
    With e = x − x_d and the reference's ẋ_d = [v_d, a_d]:

        u    = u_ff + K(x) e,                   K(x) = −R⁻¹ G(x)ᵀ P(x)  (CARE at x, eq. 24)
        u_ff = G₂(z)⁻¹ (a_d − A₂₁(z) p_d − A₂₂(z) v_d),   z = x (``ff_at='x'``) or x_d (``'ref'``)

    * ``ff_at='x'``: the model's error dynamics are then exactly linear,
      ė = ẋ − ẋ_d = [e_v; A₂(x)x + G₂(x)(u_ff + K e) − a_d] = (A(x) + G(x)K(x)) e = A_cl(x) e,
      Hurwitz by the SDRE's checks at every x (the same factorisation A(x) serves x and x_d).
    * ``ff_at='ref'``: u_ff inverts the model on the reference, G₂(x_d)u_ff = a_d − f₂(x_d); exact
      on the reference manifold (x = x_d ⇒ ė = 0), independent of the noisy estimate, one more
      model call per step.

    Unlike eq. 22–23 (u = K x + K_s x_d, a static map of a constant set-point), the reference's
    velocity and acceleration enter through the model, so a moving reference is not lagged. The
    gains are the SDRE's at x; the saturation, 40 Hz roll-off, Riccati checks and fallback rules
    are those of the other laws (a finger that falls back keeps its last valid K). A finger whose
    ``ref_acc`` is not finite, or whose G₂(z) is singular, gets no feedforward and is flagged
    ``fallback`` (the feedback still acts); ``ref_acc=None`` means a_d = 0. On the fast path a
    model with ``fused_network`` is evaluated inside the compiled step
    (:meth:`~soft_gripper_sdre.control.sdre.SdreController.track_feedforward`).

    ``integral_gain`` k_i > 0 adds integral action on the position error before saturation,
    u += k_i G₂(0)⁻¹ ∫(p_d − p)dt, integrating only while the finger is unsaturated and its error
    is within ``integral_band`` [m]
    (:class:`~soft_gripper_sdre.control.laws.integral.IntegralAction`); 0 leaves the law without
    it, arithmetic unchanged.

    Any shape and bounds (``bounds``; None = ±``u_max`` on each input): off the hand's path
    (:func:`~soft_gripper_sdre.control.tracking.hand_path`) the feedforward is u_ff = G₂⁺(a_d −
    A₂ x_d) (:func:`pseudo_inversion`: least squares where an input is missing, minimum norm where
    one is spare), the part of the demand no input can reach is reported in the step's
    ``unreachable`` and not chased, and the integral acts on what the inputs can reach
    (:class:`~soft_gripper_sdre.control.laws.integral.ReachableIntegralAction`, anti-windup per
    input and per direction, one-sided bounds included). With ``method='fast'`` and a model with
    ``fused_network`` that step runs in the general kernels, network included
    (:meth:`~soft_gripper_sdre.control.sdre.SdreController.track_feedforward_general`), unless
    ``compiled`` is False (numpy).
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 ff_at: str = 'x', integral_gain: float = DEFAULT_INTEGRAL['gain'],
                 integral_band: float = DEFAULT_INTEGRAL['band'],
                 bounds: InputBounds | None = None, compiled: bool = True) -> None:
        shape = shape_of(model)
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape, bounds)
        if ff_at not in FF_AT:
            raise ValueError(f'ff_at must be one of {FF_AT}, got {ff_at!r}')
        self.model, self.weights, self.ff_at = model, weights, ff_at
        self.n_fingers = self.io.n_fingers
        if self.io.hand:
            self.sdre = SdreController(weights.Q, weights.R, self.io.u_max, n=self.n_fingers,
                                       method=method)
        else:
            self.sdre = SdreController(*weights.for_shape(shape), u_max, n=self.n_fingers,
                                       method=method, bounds=self.io.bounds, compiled=compiled)
        self._zero = np.zeros((self.n_fingers, shape.n_state))  # x_d of the feedback step: K e
        self._zero.flags.writeable = False
        self.network = (compiled_network(model) if self.sdre.fast or self.sdre.general_kernels
                        else None)
        self._no_acc = np.zeros((self.n_fingers, shape.d))
        self._no_integral = no_integral(self.n_fingers, shape.d, shape.m)
        if not (np.isfinite(integral_gain) and integral_gain >= 0):
            raise ValueError('integral_gain must be finite and >= 0 (0 = off), '
                             f'got {integral_gain!r}')
        self.integral = None
        if integral_gain > 0:
            d = shape.d
            _, G0 = model.AG(np.zeros(shape.n_state))
            if self.io.hand:
                self.integral = IntegralAction(G0[0, 2:, :], integral_gain, integral_band,
                                               self.io.u_max, self.n_fingers, dt)
            else:
                self.integral = ReachableIntegralAction(G0[0, d:, :], integral_gain,
                                                        integral_band, self.io.bounds,
                                                        self.n_fingers, dt)

    def reset(self) -> None:
        self.io.reset()
        self.sdre.reset()
        if self.integral is not None:
            self.integral.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        if self.network is not None:
            if not self.io.hand:
                return self._general_compiled_step(pos, vel, ref_pos, ref_vel, ref_acc)
            return self._compiled_step(pos, vel, ref_pos, ref_vel, ref_acc)
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        n = self.n_fingers
        # the model's SDC lower rows at x (the gains) and where the feedforward evaluates it:
        # one batched call for x and x_d with ff_at='ref'
        z = x if self.ff_at == 'x' else np.concatenate([x, xd])
        d = self.io.shape.d
        blocks = getattr(self.model, 'sdc_blocks', None)
        if blocks is not None:
            A2, G2 = blocks(z)
            step = self.sdre.step_sdc(A2[:n], G2[:n], x - xd, self._zero)      # u_unsat = K(x) e
        else:                                       # a model with AG only (any structure)
            A, G = self.model.AG(z)
            A2, G2 = A[:, d:, :], G[:, d:, :]
            step = self.sdre.step(A[:n], G[:n], x - xd, self._zero)
        if self.ff_at == 'ref':
            A2, G2 = A2[n:], G2[n:]
        if self.integral is None:
            return combine_feedforward(self.io, step, A2, G2, xd, finite, ref_acc)
        u_i = np.where(finite[:, None], self.integral.torque(), 0.0)
        out = combine_feedforward(self.io, step, A2, G2, xd, finite, ref_acc, u_extra=u_i)
        if self.io.hand:
            self.integral.update(x[:, :2] - xd[:, :2], out.saturated, finite)
        else:
            self.integral.update(x[:, :d] - xd[:, :d], out.u_unsat, finite)
        return out

    def hand_kernel_parts(self) -> HandKernelParts | None:
        """This law's own arrays and roll-off for a compiled loop of its steps on one finger
        (:func:`~soft_gripper_sdre.control.kernels.check_loop.feedforward_check_steps`), which
        updates them as :meth:`compute` does; None unless the law steps compiled on the hand's
        path with integral action, for one finger."""
        if (self.network is None or not self.io.hand or self.integral is None
                or self.n_fingers != 1):
            return None
        s = self.sdre
        return HandKernelParts(self.io.origin, self.ff_at == 'ref', self.network,
                               s.settings.records, s.state.records, s.outputs.records,
                               s.feedforward.records, self.integral.xi, self.integral.settings,
                               self.io.roll_off)

    def _general_compiled_step(self, pos, vel, ref_pos, ref_vel, ref_acc) -> LawStep:
        """:meth:`compute` off the hand's path in the general kernels (the same law, flags and
        integral as the numpy general path), then the roll-off."""
        n, d = self.n_fingers, self.io.shape.d
        if ref_acc is None:
            ref_acc = self._no_acc
        elif np.shape(ref_acc) != (n, d):
            raise ValueError(f'ref_acc must have shape ({n}, {d}), got {np.shape(ref_acc)}')
        z = self.io.frame.stacked(pos, vel, ref_pos, ref_vel, ref_acc)
        integral = (self._no_integral if self.integral is None
                    else self.integral.kernel_args())
        out = self.sdre.track_feedforward_general(self.network, self.io.origin,
                                                  self.ff_at == 'ref', z, integral)
        out.u = self.io.roll_off(out.u)
        return out

    def _compiled_step(self, pos, vel, ref_pos, ref_vel, ref_acc) -> LawStep:
        """:meth:`compute` in one compiled call (the same law and flags)."""
        if ref_acc is None:
            ref_acc = self._no_acc
        elif np.shape(ref_acc) != (self.n_fingers, 2):
            raise ValueError(f'ref_acc must have shape ({self.n_fingers}, 2), '
                             f'got {np.shape(ref_acc)}')
        z = self.io.frame.stacked(pos, vel, ref_pos, ref_vel, ref_acc)
        out = self.sdre.track_feedforward(self.network, self.io.origin, self.ff_at == 'ref', z)
        if self.integral is not None:       # the integral and the roll-off in one compiled call
            self.integral.apply_and_roll_off(out, z, self.sdre.feedforward.state_finite,
                                             self.io.roll_off)
        else:
            out.u = self.io.roll_off(out.u)
        return out


#: the ``sdre_ff`` law's node parameters besides the weights
FF_PARAMS = (
    LawParam('feedforward_at', 'x', "where the feedforward evaluates the learned model: 'x' the "
             "estimated state (its error dynamics exactly linear), 'ref' the reference (no "
             'measurement noise reaches the model; what settings derived by training use)',
             choices=FF_AT, option='ff_at'),
    LawParam('integral_gain', DEFAULT_INTEGRAL['gain'], 'integral action on the tip position '
             'error against the steady offset of joint friction, as a tip acceleration k_i '
             '∫(p_d − p)dt through the learned input map at rest; frozen while saturated, '
             'decaying while the error is outside integral_band (pressing on the cube); 0 = off',
             '1/s³', 0.0, 1e8, runtime=True, option='integral_gain', shown=('integral', 'gain')),
    LawParam('integral_band', DEFAULT_INTEGRAL['band'], 'tip error beyond which the integral '
             'stops integrating and decays (the reference is not reachable, e.g. inside the '
             'cube)', 'm', 1e-6, 0.1, runtime=True, option='integral_band',
             shown=('integral', 'band')),
)


def _sdre_ff(s: LawSettings, ff_at: str = 'x', integral_gain: float | None = None,
             integral_band: float | None = None) -> SdreFeedforwardLaw:
    gain = DEFAULT_INTEGRAL['gain'] if integral_gain is None else integral_gain
    band = DEFAULT_INTEGRAL['band'] if integral_band is None else integral_band
    return SdreFeedforwardLaw(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, method=s.method,
                              lowpass_hz=s.lowpass_hz, dt=s.dt, ff_at=ff_at, integral_gain=gain,
                              integral_band=band, bounds=s.bounds)


register_law('sdre_ff', _sdre_ff, params=(*WEIGHT_PARAMS, *FF_PARAMS), graph=True,
             summary='SDRE + model-inversion feedforward (docs/results.md "Beyond the paper")',
             meanings={'ff_at': 'where the feedforward evaluates the model',
                       'integral_gain': 'the integral action\'s gain',
                       'integral_band': 'the integral action\'s error band'})
