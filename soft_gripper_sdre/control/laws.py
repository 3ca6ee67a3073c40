"""Control laws beside the learned SDRE, all with :class:`~soft_gripper_sdre.control.tracking.TrackingController`'s
interface (no ROS): ``compute(pos, vel, ref_pos, ref_vel)`` → a step with ``u`` (n, 2) [N·m],
``ok``, ``fallback``, ``failed_checks``, ``saturated``, ``residual``; and ``reset()``.

Every law works in the model's translated coordinates x = [p − p₀, ṗ] (p₀ = the model's rest tip),
saturates at ``u_max`` and passes its command through the same first-order roll-off as the SDRE
(``lowpass_hz``), so the comparison differs only in the law:

* ``sdre``   — the learned SDRE (:class:`TrackingController` itself); ``weights='adaptive'`` gives it
  the state-dependent Q(x) of :class:`AdaptiveSdreLaw`.
* ``lqr``    — fixed gains from the learned model at the origin: (A₀, G₀) = (A(0), G(0)),
  u = K₀ x + K_s0 x_d (eq. 22–23 with frozen matrices).
* ``pd``     — a task-space PD through the learned input map at rest,
  u = G₂(0)⁻¹ [k_p (p_d − p) + k_d (ṗ_d − ṗ)].
* ``oracle`` — the SDRE on the *true* dynamics: A(x), G(x) from
  :func:`soft_gripper_sdre.sim.dynamics.oracle_sdc` at the plant's joint state (projected onto the
  chain's static shapes; ``oracle_exact``: the paper's eq. 10–13 with the instantaneous
  G₂ = J M⁻¹ B), which the caller hands
  over each step with :meth:`OracleSdreLaw.observe` (the in-process loop does; the node graph does
  not carry the 10-joint state at the loop rate, see README "Beyond the paper").
* ``sdre_ff`` — beyond the paper: SDRE feedback on the tracking error plus model-inversion
  feedforward from the learned model, u = G₂⁻¹(a_d − A₂₁p_d − A₂₂v_d) + K(x)(x − x_d)
  (:class:`SdreFeedforwardLaw`; ``oracle_ff``: the same on the oracle's pair). These take the
  reference acceleration: ``compute(…, ref_acc=None)`` (:func:`accepts_ref_acc`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, RestFrame, RollOff, TrackingController, Weights
from soft_gripper_sdre.control.sdre import Check, SdreController, _cond2_below, _stack_solve, sdre_gains

LAWS = ('sdre', 'sdre_ff', 'lqr', 'pd', 'oracle', 'oracle_exact', 'oracle_ff')
#: the laws that run on the node graph (the oracles need the plant's joint state: in-process only)
GRAPH_LAWS = ('sdre', 'sdre_ff', 'lqr', 'pd')
#: the controller node's default: the learned SDRE with model-inversion feedforward (README
#: "Beyond the paper"); 'sdre' is the paper's law
DEFAULT_LAW = 'sdre_ff'
#: tuned task-space PD gains (natural frequency² and 2ζω of the error dynamics, 1/s² and 1/s);
#: tools/evaluate.py --tune-pd reproduces the tuning grid
DEFAULT_PD = dict(kp=1.5e4, kd=40.0)


@dataclass
class LawStep:
    """One step of a law for n fingers (the fields the node and the loop read from an SdreStep)."""

    u: np.ndarray                # (n, 2) saturated, rolled-off torques, always finite
    u_unsat: np.ndarray          # (n, 2) before saturation
    ok: np.ndarray               # (n,) the law's own checks passed
    fallback: np.ndarray         # (n,) a fallback was used
    failed_checks: np.ndarray    # (n,) int bitmask (sdre.Check; 0 for laws without checks)
    saturated: np.ndarray        # (n, 2)
    residual: np.ndarray         # (n,) relative Riccati residual (0 for closed-form laws)


class _FixedLaw:
    """Shared plumbing: the model's translated coordinates, saturation, the roll-off
    (:class:`~soft_gripper_sdre.control.tracking.RestFrame` and :class:`~soft_gripper_sdre.control.tracking.RollOff`,
    as in :class:`TrackingController`)."""

    def __init__(self, rest_tip, u_max: float, n_fingers: int, lowpass_hz: float, dt: float) -> None:
        self.frame = RestFrame(rest_tip, n_fingers)
        if not (np.isfinite(u_max) and u_max > 0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max!r}')
        self.u_max = float(u_max)
        self.n_fingers = int(n_fingers)
        self.roll_off = RollOff(lowpass_hz, dt)

    @property
    def origin(self) -> np.ndarray:
        return self.frame.origin

    def reset(self) -> None:
        self.roll_off.reset()

    def _states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, x_d, finite) in translated coordinates; non-finite rows are zeroed."""
        x, xd = self.frame.states(pos, vel, ref_pos, ref_vel)
        finite = np.isfinite(x).all(axis=1) & np.isfinite(xd).all(axis=1)
        if not finite.all():
            x[~finite] = 0.0
            xd[~finite] = 0.0
        return x, xd, finite

    def _finish(self, u_unsat: np.ndarray, finite: np.ndarray) -> LawStep:
        u_unsat = np.where(np.isfinite(u_unsat) & finite[:, None], u_unsat, 0.0)
        u = self.roll_off(np.clip(u_unsat, -self.u_max, self.u_max))
        saturated = np.abs(u_unsat) > self.u_max
        n = self.n_fingers
        return LawStep(u=u, u_unsat=u_unsat, ok=finite.copy(), fallback=~finite,
                       failed_checks=np.where(finite, 0, int(Check.NONFINITE)), saturated=saturated,
                       residual=np.zeros(n))


class LqrLaw(_FixedLaw):
    """LQR with the gains of the learned model frozen at the origin: u = K₀ x + K_s0 x_d.

    K₀ = −R⁻¹ G₀ᵀ P₀ with P₀ the CARE solution for (A(0), G(0)), K_s0 = −R⁻¹ G₀ᵀ A_cl⁻ᵀ Q (eq. 23).
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3) -> None:
        super().__init__(model.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        A0, G0 = model.AG(np.zeros(4))
        self.K, self.Ks, self.P = sdre_gains(A0[0], G0[0], weights.Q, weights.R)

    def compute(self, pos, vel, ref_pos, ref_vel) -> LawStep:
        x, xd, finite = self._states(pos, vel, ref_pos, ref_vel)
        return self._finish(x @ self.K.T + xd @ self.Ks.T, finite)          # u = K₀ x + K_s0 x_d


class PdLaw(_FixedLaw):
    """Task-space PD: u = G₂(0)⁻¹ [k_p (p_d − p) + k_d (ṗ_d − ṗ)], G₂(0) the learned input map at rest.

    The inverse input map turns the desired tip acceleration into torques (so one pair of gains
    serves both axes, whose torque-to-tip gains differ by 40×); no model of the drift is used.
    ``feedforward=True`` adds the reference acceleration (a fair partner for
    :class:`SdreFeedforwardLaw`): u = G₂(0)⁻¹ [a_d + k_p (p_d − p) + k_d (ṗ_d − ṗ)], still no drift.
    """

    def __init__(self, model, u_max: float, kp: float = DEFAULT_PD['kp'], kd: float = DEFAULT_PD['kd'],
                 n_fingers: int = 4, lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 feedforward: bool = False) -> None:
        super().__init__(model.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        self.takes_ref_acc = bool(feedforward)
        if not (np.isfinite(kp) and kp > 0 and np.isfinite(kd) and kd >= 0):
            raise ValueError(f'kp must be > 0 and kd >= 0 (finite), got kp={kp!r}, kd={kd!r}')
        _, G0 = model.AG(np.zeros(4))
        self.Ginv = np.linalg.inv(G0[0, 2:, :])
        self.kp, self.kd = float(kp), float(kd)

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        x, xd, finite = self._states(pos, vel, ref_pos, ref_vel)
        a_des = self.kp * (xd[:, :2] - x[:, :2]) + self.kd * (xd[:, 2:] - x[:, 2:])
        acc_ok = np.ones(self.n_fingers, dtype=bool)
        if self.takes_ref_acc:
            a_d, acc_ok = _reference_acc(ref_acc, self.n_fingers)
            a_des += a_d                                                      # + p̈_d
        step = self._finish(a_des @ self.Ginv.T, finite)                      # u = G₂(0)⁻¹ a_des
        step.fallback |= ~acc_ok
        return step


class OracleSdreLaw(_FixedLaw):
    """The SDRE tracking law with A(x), G(x) from the simulator's exact dynamics.

    Call :meth:`observe` with the plant's joint state (``SimTruth``: q, q̇ (n, 10)) before each
    :meth:`compute`; the gains then come from :func:`~soft_gripper_sdre.sim.dynamics.oracle_sdc` there.
    The state fed back is the same estimate the other laws get.
    """

    def __init__(self, rest_tip, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 reduced: bool = True) -> None:
        from soft_gripper_sdre.sim.dynamics import FingerDynamics
        super().__init__(rest_tip, u_max, n_fingers, lowpass_hz, dt)
        self.reduced = bool(reduced)
        self.dynamics = FingerDynamics()
        self.sdre = SdreController(weights.Q, weights.R, u_max, n=self.n_fingers, method=method)
        self._AG = None

    def reset(self) -> None:
        super().reset()
        self.sdre.reset()
        self._AG = None

    def observe(self, truth) -> None:
        """Evaluate the true SDC pair at the plant's joint state (``truth.q``, ``truth.qd``)."""
        from soft_gripper_sdre.sim.dynamics import oracle_sdc
        A = np.zeros((self.n_fingers, 4, 4))
        G = np.zeros((self.n_fingers, 4, 2))
        for i in range(self.n_fingers):
            A[i], G[i] = oracle_sdc(self.dynamics.evaluate(truth.q[i], truth.qd[i]), self.origin,
                                      reduced=self.reduced)
        self._AG = (A, G)

    def compute(self, pos, vel, ref_pos, ref_vel) -> LawStep:
        if self._AG is None:
            raise RuntimeError('OracleSdreLaw.compute needs observe(truth) first (the plant state)')
        x, xd, finite = self._states(pos, vel, ref_pos, ref_vel)
        out = self.sdre.step(*self._AG, x, xd)
        step = self._finish(out.u_unsat, finite)
        step.ok, step.fallback = out.ok & finite, out.fallback | ~finite
        step.failed_checks, step.residual = out.failed_checks, out.residual
        return step

    def close(self) -> None:
        self.dynamics.close()


class AdaptiveSdreLaw(_FixedLaw):
    """The learned SDRE with a state-dependent position weight (the paper's future work):

        Q(x) = diag(q(e), q(e), q_vel, q_vel),   q(e) = q_pos · (1 + (‖e‖ / e_ref)²),  e = p_d − p,

    capped at ``gain_max`` · q_pos. A large tracking error (the fast phases, where the model's
    errors show up as lag) raises the gain; near the reference the loop stays at the default,
    noise-friendly weight. R stays fixed (only the ratio Q/R matters). All fingers share one Q per
    step: the largest finger error sets it. The gain is quantised to 1/8 octaves, one
    :class:`TrackingController` (roll-off off) per level, so each level keeps its own warm start;
    the roll-off is applied here, once, to whichever level answered.
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 e_ref: float = 1e-3, gain_max: float = 4.0) -> None:
        super().__init__(model.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        if not (np.isfinite(e_ref) and e_ref > 0 and np.isfinite(gain_max) and gain_max >= 1):
            raise ValueError(f'e_ref must be > 0 and gain_max >= 1, got {e_ref!r}, {gain_max!r}')
        self.model, self.weights, self.method = model, weights, method
        self.e_ref, self.gain_max = float(e_ref), float(gain_max)
        self._levels: dict[float, TrackingController] = {}
        self.gain = 1.0

    def _controller(self, gain: float) -> TrackingController:
        level = round(float(np.log2(gain)) * 8) / 8
        if level not in self._levels:
            w = Weights(self.weights.q_pos * 2 ** level, self.weights.q_vel, self.weights.r)
            self._levels[level] = TrackingController(self.model, w, self.u_max, n_fingers=self.n_fingers,
                                                     method=self.method, lowpass_hz=0.0)
        return self._levels[level]

    def reset(self) -> None:
        super().reset()
        for c in self._levels.values():
            c.reset()

    def compute(self, pos, vel, ref_pos, ref_vel):
        e = np.linalg.norm(np.asarray(ref_pos, float) - np.asarray(pos, float), axis=1)
        e_max = float(np.max(np.where(np.isfinite(e), e, 0.0)))
        self.gain = min(1.0 + (e_max / self.e_ref) ** 2, self.gain_max)     # q(e) / q_pos
        out = self._controller(self.gain).compute(pos, vel, ref_pos, ref_vel)
        out.u = self.roll_off(out.u)
        return out

#: where the feedforward's model is evaluated (:class:`SdreFeedforwardLaw`)
FF_AT = ('x', 'ref')


def accepts_ref_acc(law) -> bool:
    """True when ``law.compute`` takes the reference acceleration (keyword ``ref_acc``)."""
    return bool(getattr(law, 'takes_ref_acc', False))


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
        usable = _cond2_below(G2, cond_max)[0]
        u = _stack_solve(G2, rhs)                                      # G₂ u_ff = rhs
    usable &= np.isfinite(u).all(axis=1)
    if not usable.all():
        u[~usable] = 0.0
    return u, usable


def _reference_acc(ref_acc, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(a_d (n,2), finite (n,)): None = zero acceleration; non-finite rows become zero."""
    if ref_acc is None:
        return np.zeros((n, 2)), np.ones(n, dtype=bool)
    a = np.array(ref_acc, dtype=float)
    if a.shape != (n, 2):
        raise ValueError(f'ref_acc must have shape ({n}, 2), got {a.shape}')
    finite = np.all(np.isfinite(a), axis=1)
    a[~finite] = 0.0
    return a, finite


def _feedforward_step(law, step, ff_blocks, x, xd, finite, ref_acc) -> LawStep:
    """u = u_ff + K e for a law with _FixedLaw's plumbing: ``step`` the SDRE's step on
    (e = x − x_d, x_d = 0), whose u_unsat = K(x) e; ``ff_blocks`` the (A₂, G₂) of u_ff."""
    a_d, acc_ok = _reference_acc(ref_acc, law.n_fingers)
    u_ff, ff_ok = model_inversion(*ff_blocks, xd, a_d)
    ff_ok &= acc_ok
    out = law._finish(u_ff + step.u_unsat, finite)                 # u = u_ff + K(x) e
    out.ok, out.fallback = step.ok & finite, step.fallback | ~finite | ~ff_ok
    out.failed_checks, out.residual = step.failed_checks, step.residual
    return out


class SdreFeedforwardLaw(_FixedLaw):
    """Beyond the paper: SDRE feedback on the tracking error plus model-inversion feedforward.

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
    ``fallback`` (the feedback still acts); ``ref_acc=None`` means a_d = 0.
    """

    takes_ref_acc = True

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 ff_at: str = 'x') -> None:
        super().__init__(model.rest_tip, u_max, n_fingers, lowpass_hz, dt)
        if ff_at not in FF_AT:
            raise ValueError(f'ff_at must be one of {FF_AT}, got {ff_at!r}')
        self.model, self.weights, self.ff_at = model, weights, ff_at
        self.sdre = SdreController(weights.Q, weights.R, u_max, n=self.n_fingers, method=method)
        self._zero = np.zeros((self.n_fingers, 4))          # x_d of the feedback step: K e only
        self._zero.flags.writeable = False

    def reset(self) -> None:
        super().reset()
        self.sdre.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        x, xd, finite = self._states(pos, vel, ref_pos, ref_vel)
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
        return _feedforward_step(self, step, (A2[n:], G2[n:]) if self.ff_at == 'ref' else (A2, G2),
                                 x, xd, finite, ref_acc)


class OracleFeedforwardLaw(OracleSdreLaw):
    """:class:`SdreFeedforwardLaw` on the oracle's true (projected) SDC pair, which exists only at
    the plant's state: u = G₂(q)⁻¹ (a_d − [A(q) x_d]₃,₄) + K(q)(x − x_d) (``ff_at='x'``)."""

    takes_ref_acc = True

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        if self._AG is None:
            raise RuntimeError('OracleFeedforwardLaw.compute needs observe(truth) first (the plant state)')
        x, xd, finite = self._states(pos, vel, ref_pos, ref_vel)
        A, G = self._AG
        step = self.sdre.step(A, G, x - xd, np.zeros_like(xd))           # u_unsat = K(q) e
        return _feedforward_step(self, step, (A[:, 2:, :], G[:, 2:, :]), x, xd, finite, ref_acc)


def make_law(name: str, model, weights: Weights, u_max: float, n_fingers: int = 4,
             method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
             adaptive: bool = False, pd_gains: dict | None = None, ff_at: str = 'x',
             feedforward: bool = False):
    """The named law (one of :data:`LAWS`) with the shared settings.

    Args:
        adaptive: ``sdre`` only: the state-dependent Q(x) of :class:`AdaptiveSdreLaw`.
        pd_gains: ``pd`` only: ``dict(kp=…, kd=…)`` (default :data:`DEFAULT_PD`).
        ff_at: ``sdre_ff`` only: where the feedforward evaluates the model (:data:`FF_AT`).
        feedforward: ``pd`` only: add the reference acceleration.
    """
    if feedforward and name != 'pd':
        raise ValueError(f'feedforward is an option of the pd law, not of {name!r} (use sdre_ff)')
    if name == 'sdre':
        cls = AdaptiveSdreLaw if adaptive else TrackingController
        return cls(model, weights, u_max, n_fingers=n_fingers, method=method, lowpass_hz=lowpass_hz, dt=dt)
    if adaptive:
        raise ValueError(f'state-dependent weights are an option of the sdre law, not of {name!r}')
    if name == 'sdre_ff':
        return SdreFeedforwardLaw(model, weights, u_max, n_fingers=n_fingers, method=method,
                                  lowpass_hz=lowpass_hz, dt=dt, ff_at=ff_at)
    if name == 'oracle_ff':
        return OracleFeedforwardLaw(model.rest_tip, weights, u_max, n_fingers=n_fingers, method=method,
                                    lowpass_hz=lowpass_hz, dt=dt)
    if name == 'lqr':
        return LqrLaw(model, weights, u_max, n_fingers=n_fingers, lowpass_hz=lowpass_hz, dt=dt)
    if name == 'pd':
        return PdLaw(model, u_max, n_fingers=n_fingers, lowpass_hz=lowpass_hz, dt=dt,
                     feedforward=feedforward, **(pd_gains or DEFAULT_PD))
    if name in ('oracle', 'oracle_exact'):
        return OracleSdreLaw(model.rest_tip, weights, u_max, n_fingers=n_fingers, method=method,
                             lowpass_hz=lowpass_hz, dt=dt, reduced=name == 'oracle')
    raise ValueError(f'unknown law {name!r}; known: {LAWS}')
