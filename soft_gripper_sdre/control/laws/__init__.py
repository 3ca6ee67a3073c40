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

The oracle laws (``oracle``, ``oracle_exact``, ``oracle_ff``: the SDRE on the simulator's true
dynamics) are evaluation yardsticks that need the plant's ground truth; they live in
:mod:`soft_gripper_sdre.analysis.oracle`, whose ``register_oracle_laws()`` adds them to this
registry.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

from soft_gripper_sdre.control.laws.computed_torque import DEFAULT_CT, ComputedTorqueLaw
from soft_gripper_sdre.control.laws.feedback import AdaptiveSdreLaw, SdreLaw
from soft_gripper_sdre.control.laws.feedforward import FF_AT, SdreFeedforwardLaw, model_inversion
from soft_gripper_sdre.control.laws.fixed import DEFAULT_PD, LqrLaw, PdLaw
from soft_gripper_sdre.control.laws.integral import DEFAULT_INTEGRAL, IntegralAction
from soft_gripper_sdre.control.laws.koopman import KoopmanLqrLaw, KoopmanMpcLaw
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    Law,
    Weights,
    hand_path,
    law_bounds,
    shape_of,
)
from soft_gripper_sdre.learning.koopman import KoopmanFileError, KoopmanModel
from soft_gripper_sdre.sim.shape import HAND_SHAPE, InputBounds, ShapeError

__all__ = ['AdaptiveSdreLaw', 'ComputedTorqueLaw', 'DEFAULT_CT', 'DEFAULT_INTEGRAL', 'DEFAULT_LAW',
           'DEFAULT_PD', 'FF_AT', 'GRAPH_LAWS', 'IntegralAction', 'KoopmanLqrLaw', 'KoopmanMpcLaw',
           'LAW_REGISTRY', 'LawEntry', 'LawSettings', 'LqrLaw', 'PdLaw', 'SdreFeedforwardLaw',
           'SdreLaw', 'hand_over', 'make_law', 'model_inversion', 'pd_gains', 'register_law']

#: the laws that run on the node graph (the oracles need the plant's joint state: in-process only;
#: the Koopman laws load the shipped Koopman model beside the SDC one)
GRAPH_LAWS = ('sdre', 'sdre_ff', 'lqr', 'pd', 'computed_torque', 'koopman_mpc', 'koopman_lqr')
#: the controller node's default: the learned SDRE with model-inversion feedforward (README
#: "Beyond the paper"); 'sdre' is the paper's law
DEFAULT_LAW = 'sdre_ff'


@dataclass(frozen=True)
class LawSettings:
    """What every law is built from (:func:`make_law`'s shared arguments)."""

    model: object                 # the learned SDC model (AG, rest_tip, optionally sdc_blocks)
    weights: Weights
    u_max: float                  # torque saturation [N·m] where bounds is None
    n_fingers: int = 4
    method: str = 'fast'          # the SDRE solver: 'fast' or 'reference'
    lowpass_hz: float = DEFAULT_LOWPASS_HZ
    dt: float = 1e-3              # control period [s]
    bounds: InputBounds | None = None   # per-input [lower, upper]; None: ±u_max on each input


class LawEntry(NamedTuple):
    """A registered law: ``build(settings, **options)`` and the names of the options it takes."""

    build: Callable[..., Law]
    options: tuple[str, ...] = ()


def _sdre(s: LawSettings, adaptive: bool = False) -> Law:
    law = AdaptiveSdreLaw if adaptive else SdreLaw
    return law(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, method=s.method,
               lowpass_hz=s.lowpass_hz, dt=s.dt, bounds=s.bounds)


def _sdre_ff(s: LawSettings, ff_at: str = 'x', integral_gain: float | None = None,
             integral_band: float | None = None) -> Law:
    gain = DEFAULT_INTEGRAL['gain'] if integral_gain is None else integral_gain
    band = DEFAULT_INTEGRAL['band'] if integral_band is None else integral_band
    return SdreFeedforwardLaw(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, method=s.method,
                              lowpass_hz=s.lowpass_hz, dt=s.dt, ff_at=ff_at, integral_gain=gain,
                              integral_band=band, bounds=s.bounds)


def _lqr(s: LawSettings) -> Law:
    return LqrLaw(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz,
                  dt=s.dt, bounds=s.bounds)


def _pd(s: LawSettings, pd_gains: dict | None = None, feedforward: bool = False) -> Law:
    return PdLaw(s.model, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz, dt=s.dt,
                 feedforward=feedforward, bounds=s.bounds, **(pd_gains or DEFAULT_PD))


def _model_shape(model):
    """The model's shape; no model (the Koopman laws need none) is the hand's."""
    return HAND_SHAPE if model is None else shape_of(model)


def _koopman(s: LawSettings, law=KoopmanMpcLaw, koopman_path=None) -> Law:
    shape = _model_shape(s.model)
    if not hand_path(shape, law_bounds(shape, s.u_max, s.bounds)):
        raise ShapeError(f'the Koopman laws are the hand\'s ({HAND_SHAPE}, bounds ±u_max on both '
                         f'inputs); this model has {shape}'
                         + ('' if s.bounds is None else f' and bounds {s.bounds}'))
    try:
        koopman = KoopmanModel.load(koopman_path)
    except KoopmanFileError as exc:
        raise ValueError(f'koopman_path: {exc}') from None
    u_max = s.u_max if s.bounds is None else s.bounds.symmetric_limit
    return law(koopman, s.weights, u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz, dt=s.dt)


def _computed_torque(s: LawSettings, pd_gains: dict | None = None) -> Law:
    return ComputedTorqueLaw(s.model, s.u_max, n_fingers=s.n_fingers, lowpass_hz=s.lowpass_hz,
                             dt=s.dt, method=s.method, bounds=s.bounds,
                             **(pd_gains or DEFAULT_CT))


#: what the options of the laws below mean (for error messages)
_OPTION_MEANINGS = {'adaptive': 'state-dependent weights Q(x)',
                    'ff_at': 'where the feedforward evaluates the model',
                    'integral_gain': 'the integral action\'s gain',
                    'integral_band': 'the integral action\'s error band',
                    'pd_gains': 'the PD gains',
                    'feedforward': 'the reference acceleration added to the PD',
                    'koopman_path': 'the Koopman model file'}

#: law name → how to build it; :func:`register_law` adds to it
LAW_REGISTRY: dict[str, LawEntry] = {
    'sdre': LawEntry(_sdre, ('adaptive',)),
    'sdre_ff': LawEntry(_sdre_ff, ('ff_at', 'integral_gain', 'integral_band')),
    'lqr': LawEntry(_lqr),
    'pd': LawEntry(_pd, ('pd_gains', 'feedforward')),
    'koopman_mpc': LawEntry(_koopman, ('koopman_path',)),
    'koopman_lqr': LawEntry(lambda s, koopman_path=None: _koopman(s, KoopmanLqrLaw, koopman_path),
                            ('koopman_path',)),
    'computed_torque': LawEntry(_computed_torque, ('pd_gains',)),
}


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


def register_law(name: str, build: Callable[..., Law], options: tuple[str, ...] = ()) -> None:
    """Make ``make_law(name, …)`` build ``build(settings, **options)`` (replacing an earlier
    entry)."""
    LAW_REGISTRY[name] = LawEntry(build, tuple(options))


def make_law(name: str, model, weights: Weights, u_max: float, n_fingers: int = 4,
             method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
             bounds: InputBounds | None = None, **options) -> Law:
    """The law registered as ``name`` with the shared settings and its own ``options``.

    ``bounds``: per-input [lower, upper] the law clips to, one per input of the model (None: ±u_max
    on each). An option the law does not take is refused unless it is off (None or False), so
    callers can pass e.g. ``adaptive=False`` to any law.

    Raises:
        ValueError: unknown law, or an option the law does not take, or a bad setting
            (:class:`~soft_gripper_sdre.sim.shape.ShapeError`, a ValueError, for a model whose
            shape cannot be told, bounds of another number of inputs, or a shape the law does
            not take).
    """
    entry = LAW_REGISTRY.get(name)
    if entry is None:
        raise ValueError(f'unknown law {name!r}; known: {tuple(LAW_REGISTRY)} (the oracle laws '
                         'are known after analysis.oracle.register_oracle_laws())')
    taken = {}
    for key, value in options.items():
        if key in entry.options:
            taken[key] = value
        elif value is not None and value is not False:
            owners = [n for n, e in LAW_REGISTRY.items() if key in e.options]
            meaning = f' ({_OPTION_MEANINGS[key]})' if key in _OPTION_MEANINGS else ''
            raise ValueError(f'{key}={value!r}{meaning} is not an option of the {name!r} law; '
                             f'laws that take it: {owners or "none"}')
    if bounds is not None:
        law_bounds(_model_shape(model), u_max, bounds)      # the bounds fit the model's inputs
    return entry.build(LawSettings(model, weights, u_max, n_fingers, method, lowpass_hz, dt,
                                   bounds), **taken)
