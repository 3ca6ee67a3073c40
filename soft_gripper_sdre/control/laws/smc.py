"""Sliding-mode control on the learned model: a task-space sliding surface with a boundary layer,
through the model's inversion (``law:=smc``; this file is the whole law: class, parameters,
registration)."""
from __future__ import annotations

import math

import numpy as np

from soft_gripper_sdre.control.laws.computed_torque import ModelInverse
from soft_gripper_sdre.control.laws.feedforward import reference_acceleration
from soft_gripper_sdre.control.laws.registry import LawParam, LawSettings, register_law
from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, LawIO, LawStep, shape_of
from soft_gripper_sdre.sim.shape import InputBounds

#: the surface's slope λ [1/s], the switching gain k [m/s²] and the boundary layer φ [m/s]:
#: inside the layer the error dynamics have the real poles −λ and −k/φ (both 80 rad/s: k_p =
#: λk/φ = 6400 1/s², k_d = λ + k/φ = 160 1/s), and a model error of up to k is rejected. Tuned on
#: the hand's shipped model in the in-process grasp (0.65 s, 0.05 mm noise): a worst-finger RMS
#: error of 0.04 mm, as computed torque's; a higher k/φ or λ rings through the 40 Hz roll-off.
#: On the whole default grasp it holds the cube (moved 0.05 mm) at a grasping-finger RMS error of
#: 0.048 mm with sdre_ff's effort (sdre_ff: 0.021 mm; computed_torque: 0.035 mm, cube 0.26 mm)
SMC_DEFAULTS = dict(lam=80.0, k=4.0, phi=0.05)
#: largest condition number of G₂(x) the inversion accepts (as computed torque's)
SMC_COND_MAX = 1e8


def _check(lam: float, k: float, phi: float) -> None:
    """ValueError naming the parameter unless λ > 0, k ≥ 0 and φ > 0, all finite."""
    if not (math.isfinite(lam) and lam > 0):
        raise ValueError(f'smc_lambda (the surface slope λ) must be finite and > 0 1/s, '
                         f'got {lam!r}')
    if not (math.isfinite(k) and k >= 0):
        raise ValueError(f'smc_k (the switching gain k) must be finite and >= 0 m/s², got {k!r}')
    if not (math.isfinite(phi) and phi > 0):
        raise ValueError(f'smc_phi (the boundary layer φ) must be finite and > 0 m/s, '
                         f'got {phi!r}')


class SmcLaw:
    """Task-space sliding-mode control with the learned SDC model (ẋ = A(x)x + G(x)u, lower
    rows A₂, G₂), per finger, with e = p − p_d and ė = ṗ − ṗ_d (d coordinates each):

        s = ė + λ e,         u = G₂(x)⁺ (a_d − A₂(x) x − λ ė − k sat(s / φ))

    sat clips each coordinate to [−1, 1]. On the model with G₂(x) square and regular and u
    within its bounds, ṡ = ë + λ ė = −k sat(s/φ): outside the boundary layer (|s_i| > φ) each
    s_i falls at the rate k [m/s²] and reaches the layer within (|s_i| − φ)/k; inside it
    ṡ = −(k/φ) s, so e decays with the real poles −λ and −k/φ (a PD with k_p = λk/φ,
    k_d = λ + k/φ). An acceleration error of the model Δ with |Δ_i| < k is rejected to
    |s_i| ≤ φ|Δ_i|/k, a steady |e_i| ≤ φ|Δ_i|/(kλ). The layer φ [m/s] replaces the switching
    sign(s) by its linear part near s = 0, against chattering (and the 40 Hz roll-off every law
    has smooths the rest).

    The inversion is computed torque's (:class:`~soft_gripper_sdre.control.laws.
    computed_torque.ComputedTorqueLaw`, whose a_d − k_p e − k_d ė is this law's
    a_d − λ ė − k sat(s/φ)): on the hand's path (:func:`~soft_gripper_sdre.control.tracking.
    hand_path`) G₂(x)⁻¹, with ``method='fast'`` and a model with ``fused_network`` the compiled
    network and inversion kernels; on any other shape (d, m) the pseudo-inverse G₂(x)⁺
    (:func:`~soft_gripper_sdre.control.laws.feedforward.pseudo_inversion`: least squares where
    an input is missing, minimum norm where one is spare), and the part of the demanded
    acceleration no input can reach is the step's ``unreachable`` [m/s²]. The command is clipped
    to ``bounds`` (None: ±``u_max`` on each input) and rolled off as every law's. A finger whose
    G₂(x) is singular (cond ≥ :data:`SMC_COND_MAX`) or whose state is not finite gets zero and
    is flagged ``fallback`` (``ok`` False); a non-finite ``ref_acc`` counts as zero and is
    flagged ``fallback``.

    Args:
        model: the learned SDC model (``sdc_blocks`` or ``AG``, ``rest_tip``).
        u_max: saturation per input where ``bounds`` is None [N·m].
        lam: λ [1/s], finite, > 0.
        k: k [m/s²], finite, ≥ 0 (0: the linear law a_d − λė − 0, no reaching).
        phi: φ [m/s], finite, > 0.
        n_fingers, lowpass_hz, dt, method: as for the other laws.
        bounds: per-input [lower, upper] (None: ±``u_max`` on each of the model's inputs).

    Raises:
        ValueError: λ, k or φ out of range (the message names ``smc_lambda``, ``smc_k`` or
            ``smc_phi``), or bounds that do not fit the model.
    """

    def __init__(self, model, u_max: float, lam: float = SMC_DEFAULTS['lam'],
                 k: float = SMC_DEFAULTS['k'], phi: float = SMC_DEFAULTS['phi'],
                 n_fingers: int = 4, lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 method: str = 'fast', bounds: InputBounds | None = None) -> None:
        _check(lam, k, phi)
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape_of(model), bounds)
        self.model, self.lam, self.k, self.phi = model, float(lam), float(k), float(phi)
        self.inverse = ModelInverse(model, self.io, method, SMC_COND_MAX)
        self.surface = np.zeros((self.io.n_fingers, self.io.shape.d))   # s of the last step [m/s]

    @property
    def network(self):
        """The compiled network the inversion evaluates (None off the compiled path)."""
        return self.inverse.network

    def reset(self) -> None:
        self.io.reset()
        self.surface[:] = 0.0

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        d = self.io.shape.d
        a_d, acc_ok = reference_acceleration(ref_acc, self.io.n_fingers, d)
        e = x - xd
        s = e[:, d:] + self.lam * e[:, :d]                                   # s = ė + λ e
        with np.errstate(invalid='ignore'):
            a_des = a_d - self.lam * e[:, d:] - self.k * np.clip(s / self.phi, -1.0, 1.0)
        self.surface = np.where(finite[:, None], s, 0.0)
        return self.inverse.step(x, a_des, finite, acc_ok)


#: the law's node parameters (each feeds the make_law option of its name); runtime-tunable
SMC_PARAMS = (
    LawParam('smc_lambda', SMC_DEFAULTS['lam'], 'slope λ of the sliding surface s = ė + λe on '
             'the tip error e = p − p_d: the rate at which the error decays on the surface',
             '1/s', 1e-3, 1e4, runtime=True, option='smc_lambda', shown=('smc', 'lambda')),
    LawParam('smc_k', SMC_DEFAULTS['k'], 'switching gain k: the tip acceleration that drives s '
             'to the boundary layer, the largest model error rejected; 0 = none', 'm/s²', 0.0,
             1e6, runtime=True, option='smc_k', shown=('smc', 'k')),
    LawParam('smc_phi', SMC_DEFAULTS['phi'], 'boundary layer φ: inside |s| < φ the switching '
             'k·sat(s/φ) is linear (no chattering); the error left by a model error Δ is '
             'about φΔ/(kλ)', 'm/s', 1e-6, 100.0, runtime=True, option='smc_phi',
             shown=('smc', 'phi')),
)


def _smc(s: LawSettings, smc_lambda: float | None = None, smc_k: float | None = None,
         smc_phi: float | None = None) -> SmcLaw:
    own = SMC_DEFAULTS
    return SmcLaw(s.model, s.u_max, lam=own['lam'] if smc_lambda is None else smc_lambda,
                  k=own['k'] if smc_k is None else smc_k,
                  phi=own['phi'] if smc_phi is None else smc_phi, n_fingers=s.n_fingers,
                  lowpass_hz=s.lowpass_hz, dt=s.dt, method=s.method, bounds=s.bounds)


register_law('smc', _smc, params=SMC_PARAMS, graph=True,
             summary='task-space sliding-mode control on the learned model (surface ė + λe, '
             'boundary layer φ)',
             meanings={'smc_lambda': 'the sliding surface\'s slope λ',
                       'smc_k': 'the switching gain k', 'smc_phi': 'the boundary layer φ'})
