"""Computed torque on the learned model: feedback linearisation with PD gains on the error."""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control import kernels as compiled
from soft_gripper_sdre.control.laws.feedforward import (
    model_inversion,
    pseudo_inversion,
    reference_acceleration,
)
from soft_gripper_sdre.control.laws.fixed import PD_PARAMS
from soft_gripper_sdre.control.laws.registry import LawSettings, register_law
from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, LawIO, LawStep, shape_of
from soft_gripper_sdre.sim.shape import InputBounds

#: tuned gains (natural frequency² [1/s²] and 2ζω [1/s] of the linearised error dynamics);
#: ``python -m soft_gripper_sdre.tools.judging.evaluate --tune computed_torque`` reproduces the
#: tuning grid
DEFAULT_CT = dict(kp=1.5e4, kd=80.0)
#: largest condition number of G₂(x) the inversion accepts (as the feedforward's)
CT_COND_MAX = 1e8


class ModelInverse:
    """u = G₂(x)⁻¹ (a_des − A₂(x) x) on the learned model for a law's fingers, and the law's step
    from it: the inversion computed torque and sliding-mode control share.

    On the hand's path (``io.hand``) G₂(x)⁻¹, with ``method='fast'`` and a model with
    ``fused_network`` by the compiled network and inversion kernels; on any other shape the
    pseudo-inverse G₂(x)⁺ (:func:`~soft_gripper_sdre.control.laws.feedforward.pseudo_inversion`),
    whose unreachable demand the step reports. A finger whose G₂(x) has a condition number of
    ``cond_max`` or more gets zero and is not ``usable``.
    """

    def __init__(self, model, io: LawIO, method: str, cond_max: float) -> None:
        self.model, self.io, self.cond_max = model, io, cond_max
        n = io.n_fingers
        self.network = compiled.compiled_network(model) if method == 'fast' and io.hand else None
        self._unreachable = None
        self._a2, self._g2 = np.zeros((n, 2, 4)), np.zeros((n, 2, 2))
        self._u, self._usable = np.zeros((n, 2)), np.zeros(n, dtype=np.bool_)

    def __call__(self, x: np.ndarray, a_des: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u (n, m), usable (n,)) for the states x (n, 2d) and the demanded accelerations
        a_des (n, d)."""
        if self.network is not None:
            x = compiled.kernel_array(x)
            compiled.sdc_forward(x, *self.network, self._a2, self._g2)
            compiled.model_inversion(self._a2, self._g2, x, compiled.kernel_array(a_des),
                                     self.cond_max, self._u, self._usable)
            return self._u.copy(), self._usable.copy()
        d = self.io.shape.d
        blocks = getattr(self.model, 'sdc_blocks', None)
        if blocks is not None:
            A2, G2 = blocks(x)
        else:
            A, G = self.model.AG(x)
            A2, G2 = A[:, d:, :], G[:, d:, :]
        if self.io.hand:
            return model_inversion(A2, G2, x, a_des, self.cond_max)
        u, usable, self._unreachable = pseudo_inversion(A2, G2, x, a_des, self.cond_max)
        return u, usable

    def step(self, x: np.ndarray, a_des: np.ndarray, finite: np.ndarray,
             acc_ok: np.ndarray) -> LawStep:
        """The law's step for the demand a_des: the inversion through ``io.finish``, a finger
        not ``usable`` or with an unusable reference acceleration (``acc_ok`` False) flagged
        ``fallback``, the unreachable demand reported where the state is finite."""
        u, usable = self(x, a_des)
        step = self.io.finish(u, finite)
        step.ok &= usable
        step.fallback |= ~usable | ~acc_ok
        if self._unreachable is not None:
            step.unreachable = np.where(finite, self._unreachable, 0.0)
        return step


class ComputedTorqueLaw:
    """Computed torque with the learned SDC model (ẋ = A(x)x + G(x)u, lower rows A₂, G₂):

        u = G₂(x)⁻¹ (a_d − A₂(x) x − k_p (p − p_d) − k_d (ṗ − ṗ_d))

    The model's tip acceleration is then exactly ë = −k_p e − k_d ė (e = p − p_d): the same
    linearisation as :class:`~soft_gripper_sdre.control.laws.feedforward.SdreFeedforwardLaw` with
    ``ff_at='x'``, whose u = G₂(x)⁻¹(a_d − A₂(x)x_d) + K(x)(x − x_d) puts the Riccati gains K(x)
    where this law puts −G₂(x)⁻¹(A₂(x) + [k_p I, k_d I]). It is the same model inversion
    (:func:`~soft_gripper_sdre.control.laws.feedforward.model_inversion` at x with the desired
    acceleration a_d − k_p e − k_d ė), with no Riccati equation.

    Saturation and roll-off are those of every law. A finger whose G₂(x) is singular (cond ≥
    :data:`CT_COND_MAX`) or whose torque is not finite gets zero torque and is flagged ``fallback``
    (``ok`` False); a non-finite ``ref_acc`` counts as zero and is flagged ``fallback``. With
    ``method='fast'`` a model with ``fused_network`` is evaluated by the compiled network kernel.

    Args:
        model: the learned SDC model (``sdc_blocks`` or ``AG``, ``rest_tip``).
        u_max: torque saturation per input [N·m].
        kp, kd: gains on the position [1/s²] and velocity [1/s] error, finite, kp > 0, kd ≥ 0.
        n_fingers, lowpass_hz, dt, method: as for the other laws.
        bounds: per-input [lower, upper] (None: ±``u_max`` on each of the model's inputs).

    Any shape (d, m): off the hand's path (:func:`~soft_gripper_sdre.control.tracking.hand_path`)
    G₂(x)⁻¹ is the pseudo-inverse G₂(x)⁺
    (:func:`~soft_gripper_sdre.control.laws.feedforward.pseudo_inversion`: least squares where an
    input is missing, minimum norm where one is spare), and the part of the demanded acceleration
    no input can reach is the step's ``unreachable``.
    """

    def __init__(self, model, u_max: float, kp: float = DEFAULT_CT['kp'],
                 kd: float = DEFAULT_CT['kd'], n_fingers: int = 4,
                 lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 method: str = 'fast', bounds: InputBounds | None = None) -> None:
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape_of(model), bounds)
        if not (np.isfinite(kp) and kp > 0 and np.isfinite(kd) and kd >= 0):
            raise ValueError(f'kp must be > 0 and kd >= 0 (finite), got kp={kp!r}, kd={kd!r}')
        self.model, self.kp, self.kd = model, float(kp), float(kd)
        self.inverse = ModelInverse(model, self.io, method, CT_COND_MAX)

    @property
    def network(self):
        """The compiled network the inversion evaluates (None off the compiled path)."""
        return self.inverse.network

    def reset(self) -> None:
        self.io.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        d = self.io.shape.d
        a_d, acc_ok = reference_acceleration(ref_acc, self.io.n_fingers, d)
        e = x - xd
        a_des = a_d - self.kp * e[:, :d] - self.kd * e[:, d:]              # a_d − k_p e − k_d ė
        return self.inverse.step(x, a_des, finite, acc_ok)


def _computed_torque(s: LawSettings, pd_gains: dict | None = None) -> ComputedTorqueLaw:
    return ComputedTorqueLaw(s.model, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz,
                             dt=s.dt, method=s.method, bounds=s.bounds,
                             **(pd_gains or DEFAULT_CT))


register_law('computed_torque', _computed_torque, params=PD_PARAMS, graph=True,
             summary='computed torque (feedback linearisation) on the learned model',
             own={'pd_kp': DEFAULT_CT['kp'], 'pd_kd': DEFAULT_CT['kd']})
