"""Beyond the paper: SDRE feedback on the tracking error plus model-inversion feedforward."""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.batched_linalg import batched_solve, well_conditioned_2x2
from soft_gripper_sdre.control.compiled import compiled_network
from soft_gripper_sdre.control.laws.integral import DEFAULT_INTEGRAL, IntegralAction
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, LawIO, LawStep, Weights

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


def reference_acceleration(ref_acc, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(a_d (n,2), finite (n,)) from a law's ``ref_acc``: None = zero acceleration; non-finite
    rows become zero.

    Raises:
        ValueError: ``ref_acc`` is not (n, 2).
    """
    if ref_acc is None:
        return np.zeros((n, 2)), np.ones(n, dtype=bool)
    a = np.array(ref_acc, dtype=float)
    if a.shape != (n, 2):
        raise ValueError(f'ref_acc must have shape ({n}, 2), got {a.shape}')
    finite = np.all(np.isfinite(a), axis=1)
    a[~finite] = 0.0
    return a, finite


def combine_feedforward(io: LawIO, feedback: LawStep, A2: np.ndarray, G2: np.ndarray,
                        x_d: np.ndarray, finite: np.ndarray, ref_acc,
                        u_extra: np.ndarray | None = None) -> LawStep:
    """u = u_ff + K e (+ ``u_extra``, e.g. an integral term, before saturation): ``feedback`` is
    the SDRE's step on (e = x − x_d, x_d = 0), whose u_unsat = K(x) e; (A2, G2) the SDC lower rows
    the feedforward inverts (:func:`model_inversion`). A finger without feedforward (singular G₂,
    non-finite ``ref_acc``) is flagged ``fallback``."""
    a_d, acc_ok = reference_acceleration(ref_acc, io.n_fingers)
    u_ff, ff_ok = model_inversion(A2, G2, x_d, a_d)
    ff_ok &= acc_ok
    u_unsat = u_ff + feedback.u_unsat                                 # u = u_ff + K(x) e
    if u_extra is not None:
        u_unsat += u_extra
    out = io.finish(u_unsat, finite)
    out.ok, out.fallback = feedback.ok & finite, feedback.fallback | ~finite | ~ff_ok
    out.failed_checks, out.residual = feedback.failed_checks, feedback.residual
    out.K, out.Ks, out.P, out.nk_iterations = (feedback.K, feedback.Ks, feedback.P,
                                               feedback.nk_iterations)
    return out


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
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 ff_at: str = 'x', integral_gain: float = DEFAULT_INTEGRAL['gain'],
                 integral_band: float = DEFAULT_INTEGRAL['band']) -> None:
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        if ff_at not in FF_AT:
            raise ValueError(f'ff_at must be one of {FF_AT}, got {ff_at!r}')
        self.model, self.weights, self.ff_at = model, weights, ff_at
        self.n_fingers = self.io.n_fingers
        self.sdre = SdreController(weights.Q, weights.R, u_max, n=self.n_fingers, method=method)
        self._zero = np.zeros((self.n_fingers, 4))          # x_d of the feedback step: K e only
        self._zero.flags.writeable = False
        self.network = compiled_network(model) if self.sdre.fast else None
        self._no_acc = np.zeros((self.n_fingers, 2))
        if not (np.isfinite(integral_gain) and integral_gain >= 0):
            raise ValueError('integral_gain must be finite and >= 0 (0 = off), '
                             f'got {integral_gain!r}')
        self.integral = None
        if integral_gain > 0:
            _, G0 = model.AG(np.zeros(4))
            self.integral = IntegralAction(G0[0, 2:, :], integral_gain, integral_band, u_max,
                                           self.n_fingers, dt)

    def reset(self) -> None:
        self.io.reset()
        self.sdre.reset()
        if self.integral is not None:
            self.integral.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        if self.network is not None:
            return self._compiled_step(pos, vel, ref_pos, ref_vel, ref_acc)
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        n = self.n_fingers
        # the model's SDC lower rows at x (the gains) and where the feedforward evaluates it:
        # one batched call for x and x_d with ff_at='ref'
        z = x if self.ff_at == 'x' else np.concatenate([x, xd])
        blocks = getattr(self.model, 'sdc_blocks', None)
        if blocks is not None:
            A2, G2 = blocks(z)
            step = self.sdre.step_sdc(A2[:n], G2[:n], x - xd, self._zero)      # u_unsat = K(x) e
        else:                                       # a model with AG only (any structure)
            A, G = self.model.AG(z)
            A2, G2 = A[:, 2:, :], G[:, 2:, :]
            step = self.sdre.step(A[:n], G[:n], x - xd, self._zero)
        if self.ff_at == 'ref':
            A2, G2 = A2[n:], G2[n:]
        if self.integral is None:
            return combine_feedforward(self.io, step, A2, G2, xd, finite, ref_acc)
        u_i = np.where(finite[:, None], self.integral.torque(), 0.0)
        out = combine_feedforward(self.io, step, A2, G2, xd, finite, ref_acc, u_extra=u_i)
        self.integral.update(x[:, :2] - xd[:, :2], out.saturated, finite)
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
