"""The control laws (no ROS) and the registry that builds them by name.

Every law has the :class:`~soft_gripper_sdre.control.tracking.Law` protocol (``compute(pos, vel,
ref_pos, ref_vel, ref_acc=None)`` → :class:`~soft_gripper_sdre.control.tracking.LawStep`, and
``reset()``) and works in the model's translated coordinates with the same saturation and
roll-off, so a comparison differs only in the law:

* ``sdre``    — the paper's learned SDRE, u = K(x) x + K_s(x) x_d (:class:`SdreLaw`);
  ``adaptive=True``: the state-dependent Q(x) of :class:`AdaptiveSdreLaw`.
* ``sdre_ff`` — beyond the paper: SDRE feedback on the tracking error plus model-inversion
  feedforward, u = G₂⁻¹(a_d − A₂₁p_d − A₂₂v_d) + K(x)(x − x_d) (:class:`SdreFeedforwardLaw`;
  ``ff_at``: where the feedforward evaluates the model, :data:`FF_AT`; ``integral_gain``,
  ``integral_band``: integral action with anti-windup, :class:`IntegralAction`, gain 0 = off,
  None = :data:`DEFAULT_INTEGRAL`).
* ``lqr``     — fixed gains from the learned model at the origin (:class:`LqrLaw`).
* ``pd``      — a task-space PD through the learned input map at rest (:class:`PdLaw`;
  ``pd_gains=dict(kp=…, kd=…)``, ``feedforward=True`` adds the reference acceleration).
* ``koopman_mpc``, ``koopman_lqr`` — the Koopman baselines: linear MPC (box-constrained QP) and
  LQR on the lifted linear model of :mod:`soft_gripper_sdre.learning.koopman`, not on the SDC
  model (:class:`KoopmanMpcLaw`, :class:`KoopmanLqrLaw`; ``koopman_path``: the model file, None =
  the shipped one).
* ``computed_torque`` — feedback linearisation on the learned model with PD gains on the error,
  u = G₂(x)⁻¹(a_d − A₂(x)x − k_p e − k_d ė) (:class:`ComputedTorqueLaw`;
  ``pd_gains=dict(kp=…, kd=…)``): ``sdre_ff`` without the Riccati equation.

Every law but the Koopman baselines works for any finger shape (d, m) the model has
(:func:`~soft_gripper_sdre.control.tracking.shape_of`) and clips to per-input ``bounds``
(:class:`~soft_gripper_sdre.sim.shape.InputBounds`; None = ±``u_max`` on each input). The hand's
shape with ±u_max bounds runs the hand's code (the compiled kernels with ``method='fast'``), any
other the general numpy/scipy code: the one rule is
:func:`~soft_gripper_sdre.control.tracking.hand_path`. The Koopman baselines are the hand's and
refuse another shape or bounds.

Each law file declares its node parameters (:class:`~.registry.LawParam`) and registers itself
(:func:`~.registry.register_law`, :mod:`~soft_gripper_sdre.control.laws.registry`): importing
this package imports the law files, in the order below, which is the registry's (the controller's
law choices and parameters). docs/design/laws.md "Adding a law" says what a law file
declares.

The oracle laws (``oracle``, ``oracle_exact``, ``oracle_ff``: the SDRE on the simulator's true
dynamics) are evaluation yardsticks that need the plant's ground truth; they live in
:mod:`soft_gripper_sdre.analysis.oracle`, whose ``register_oracle_laws()`` adds them to this
registry.
"""
from __future__ import annotations

# the law files register themselves as they are imported, in this order (the registry's)
# isort: off
from soft_gripper_sdre.control.laws.registry import (
    LAW_REGISTRY,
    WEIGHT_PARAMS,
    LawEntry,
    LawParam,
    LawSettings,
    graph_laws,
    make_law,
    register_law,
)
from soft_gripper_sdre.control.laws.feedback import AdaptiveSdreLaw, SdreLaw
from soft_gripper_sdre.control.laws.feedforward import FF_AT, SdreFeedforwardLaw, model_inversion
from soft_gripper_sdre.control.laws.fixed import DEFAULT_PD, LqrLaw, PdLaw
from soft_gripper_sdre.control.laws.computed_torque import DEFAULT_CT, ComputedTorqueLaw
from soft_gripper_sdre.control.laws.koopman import KoopmanLqrLaw, KoopmanMpcLaw
from soft_gripper_sdre.control.laws import smc  # noqa: F401  (registers the law)
# isort: on
from soft_gripper_sdre.control.laws.integral import DEFAULT_INTEGRAL, IntegralAction
from soft_gripper_sdre.control.tracking import Law

__all__ = ['AdaptiveSdreLaw', 'ComputedTorqueLaw', 'DEFAULT_CT', 'DEFAULT_INTEGRAL', 'DEFAULT_LAW',
           'DEFAULT_PD', 'FF_AT', 'GRAPH_LAWS', 'IntegralAction', 'KoopmanLqrLaw', 'KoopmanMpcLaw',
           'LAW_REGISTRY', 'LawEntry', 'LawParam', 'LawSettings', 'LqrLaw', 'PdLaw',
           'SdreFeedforwardLaw', 'SdreLaw', 'WEIGHT_PARAMS', 'hand_over', 'make_law',
           'model_inversion', 'pd_gains', 'register_law']

#: the laws that run on the node graph, as their files registered them (the oracles need the
#: plant's joint state: in-process only; the Koopman laws load the shipped Koopman model beside
#: the SDC one)
GRAPH_LAWS = graph_laws()
#: the controller node's default: the learned SDRE with model-inversion feedforward (README
#: "Beyond the paper"); 'sdre' is the paper's law
DEFAULT_LAW = 'sdre_ff'


def pd_gains(law: str, kp: float = 0.0, kd: float = 0.0) -> dict:
    """The ``pd_gains`` of ``law`` ('pd' or 'computed_torque'): ``kp`` [1/s²] and ``kd`` [1/s],
    where 0 means the law's own tuned gain (:data:`DEFAULT_PD`, :data:`DEFAULT_CT`)."""
    own = DEFAULT_CT if law == 'computed_torque' else DEFAULT_PD
    return dict(kp=float(kp) or own['kp'], kd=float(kd) or own['kd'])


def _roll_off(law):
    io = getattr(law, 'io', None)
    return io.roll_off if io is not None else getattr(law, 'roll_off', None)


def hand_over(old: Law, new: Law) -> None:
    """Give ``new`` (the law ``old`` is, built again with other gains or weights) the state that
    keeps its command continuous: the roll-off filter's last output, the integral action's torque
    (its integral rescaled to the new gain; none when either law has no integral), and the
    Koopman laws' state history. Warm starts and last valid Riccati gains are not carried: they
    belong to the old weights, and the new law solves afresh as after a reset."""
    if type(old) is not type(new):
        raise ValueError(f'cannot hand a {type(old).__name__} over to a {type(new).__name__}')
    before, after = _roll_off(old), _roll_off(new)
    if before is not None and after is not None and before.alpha > 0.0 and after.alpha > 0.0:
        after._u = None if before._u is None else before._u.copy()
    old_i, new_i = getattr(old, 'integral', None), getattr(new, 'integral', None)
    if old_i is not None and new_i is not None:
        new_i.xi[:] = old_i.xi * (old_i.gain / new_i.gain)         # the same u_I = k_i G₂⁻¹ ξ
    if hasattr(old, 'history') and hasattr(new, 'history'):
        new.history = old.history
