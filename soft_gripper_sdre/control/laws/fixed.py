"""Laws with fixed gains from the learned model at rest: LQR and a task-space PD."""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.laws.feedforward import reference_acceleration
from soft_gripper_sdre.control.laws.registry import (
    WEIGHT_PARAMS,
    LawParam,
    LawSettings,
    register_law,
)
from soft_gripper_sdre.control.riccati import sdre_gains
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    LawIO,
    LawStep,
    Weights,
    shape_of,
)
from soft_gripper_sdre.sim.shape import InputBounds

#: tuned task-space PD gains (natural frequency² and 2ζω of the error dynamics, 1/s² and 1/s);
#: tools/judging/evaluate.py --tune-pd reproduces the tuning grid
DEFAULT_PD = dict(kp=1.5e4, kd=40.0)


class LqrLaw:
    """LQR with the gains of the learned model frozen at the origin: u = K₀ x + K_s0 x_d.

    K₀ = −R⁻¹ G₀ᵀ P₀ with P₀ the CARE solution for (A(0), G(0)), K_s0 = −R⁻¹ G₀ᵀ A_cl⁻ᵀ Q (eq. 23),
    for any shape (d, m) with ``weights.Q(d)``, ``weights.R(m)``; ``bounds`` (None: ±``u_max`` on
    each input) are what the command is clipped to.

    Raises:
        ValueError: the model at rest has no stabilising CARE solution (e.g. an input map at rest
            that cannot reach an unstable mode).
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 bounds: InputBounds | None = None) -> None:
        shape = shape_of(model)
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape, bounds)
        A0, G0 = model.AG(np.zeros(shape.n_state))
        if self.io.hand:
            self.K, self.Ks, self.P = sdre_gains(A0[0], G0[0], weights.Q, weights.R)
        else:
            try:
                self.K, self.Ks, self.P = sdre_gains(A0[0], G0[0], *weights.for_shape(shape))
            except (np.linalg.LinAlgError, ValueError) as exc:
                raise ValueError(f'lqr: the model at rest ({shape}) has no stabilising Riccati '
                                 f'solution: {exc}') from None

    def reset(self) -> None:
        self.io.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        """Torques for every finger (the law does not use ``ref_acc``)."""
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        return self.io.finish(x @ self.K.T + xd @ self.Ks.T, finite)          # u = K₀ x + K_s0 x_d


class PdLaw:
    """Task-space PD: u = G₂(0)⁻¹ [k_p (p_d − p) + k_d (ṗ_d − ṗ)], G₂(0) the learned input map
    at rest.

    The inverse input map turns the desired tip acceleration into torques (so one pair of gains
    serves both axes, whose torque-to-tip gains differ by 40×); no model of the drift is used.
    ``feedforward=True`` adds the reference acceleration (a fair partner for
    :class:`~soft_gripper_sdre.control.laws.feedforward.SdreFeedforwardLaw`):
    u = G₂(0)⁻¹ [a_d + k_p (p_d − p) + k_d (ṗ_d − ṗ)], still no drift.

    Any shape (d, m): off the hand's path G₂(0)⁻¹ is the pseudo-inverse G₂(0)⁺ (least squares
    where an input is missing, minimum norm where one is spare); ``bounds`` (None: ±``u_max`` on
    each input) are what the command is clipped to.

    Raises:
        ValueError: gains out of range, or G₂(0) not finite or zero.
    """

    def __init__(self, model, u_max: float, kp: float = DEFAULT_PD['kp'],
                 kd: float = DEFAULT_PD['kd'], n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 feedforward: bool = False, bounds: InputBounds | None = None) -> None:
        shape = shape_of(model)
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape, bounds)
        self.feedforward = bool(feedforward)
        if not (np.isfinite(kp) and kp > 0 and np.isfinite(kd) and kd >= 0):
            raise ValueError(f'kp must be > 0 and kd >= 0 (finite), got kp={kp!r}, kd={kd!r}')
        _, G0 = model.AG(np.zeros(shape.n_state))
        if self.io.hand:
            self.Ginv = np.linalg.inv(G0[0, 2:, :])
        else:
            g2 = G0[0, shape.d:, :]
            if not (np.all(np.isfinite(g2)) and np.any(g2)):
                raise ValueError(f'pd: the input map at rest G2(0) must be finite and not zero, '
                                 f'got {g2!r}')
            self.Ginv = np.linalg.pinv(g2, rcond=1e-8)
        self.kp, self.kd = float(kp), float(kd)

    def reset(self) -> None:
        self.io.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        """Torques for every finger; ``ref_acc`` is used with ``feedforward`` only."""
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        d = self.io.shape.d
        a_des = self.kp * (xd[:, :d] - x[:, :d]) + self.kd * (xd[:, d:] - x[:, d:])
        acc_ok = np.ones(self.io.n_fingers, dtype=bool)
        if self.feedforward:
            a_d, acc_ok = reference_acceleration(ref_acc, self.io.n_fingers, d)
            a_des += a_d                                                      # + p̈_d
        step = self.io.finish(a_des @ self.Ginv.T, finite)                    # u = G₂(0)⁻¹ a_des
        step.fallback |= ~acc_ok
        return step


#: the task-space PD gains of ``pd`` and ``computed_torque`` (their ``pd_gains`` option; 0 = the
#: law's own tuned gain)
PD_PARAMS = (
    LawParam('pd_kp', 0.0, "the task-space gain on the tip position error, the error dynamics' "
             "natural frequency squared; 0 = the law's own tuned gain", '1/s²', 0.0, 1e9,
             runtime=True, option='pd_gains', key='kp', zero_is_own=True,
             shown=('pd_gains', 'kp')),
    LawParam('pd_kd', 0.0, "the gain on the tip velocity error, 2ζω; 0 = the law's own", '1/s',
             0.0, 1e6, runtime=True, option='pd_gains', key='kd', zero_is_own=True,
             shown=('pd_gains', 'kd')),
)


def _lqr(s: LawSettings) -> LqrLaw:
    return LqrLaw(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz,
                  dt=s.dt, bounds=s.bounds)


def _pd(s: LawSettings, pd_gains: dict | None = None, feedforward: bool = False) -> PdLaw:
    return PdLaw(s.model, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz, dt=s.dt,
                 feedforward=feedforward, bounds=s.bounds, **(pd_gains or DEFAULT_PD))


register_law('lqr', _lqr, params=WEIGHT_PARAMS, graph=True,
             summary='LQR frozen at the origin of the learned model')
register_law('pd', _pd, ('feedforward',), params=PD_PARAMS, graph=True,
             summary='task-space PD through the learned input map at rest',
             own={'pd_kp': DEFAULT_PD['kp'], 'pd_kd': DEFAULT_PD['kd']},
             meanings={'pd_gains': 'the PD gains',
                       'feedforward': 'the reference acceleration added to the PD'})
