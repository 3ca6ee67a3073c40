"""What every tracking law shares (no ROS): weights, the step type, the protocol, and the plumbing
around each law's own arithmetic.

Every law takes each finger's estimated tip position and velocity and its reference in the
finger's base frame (SI, untranslated) and works in the model's translated coordinates (origin at
the settled rest pose, where f(0) = 0),

    x   = [p − p₀, ṗ],    x_d = [p_d − p₀, ṗ_d]       (:class:`RestFrame`),

with p the tip's d coordinates (X, Y or X, Y, Z: the model's
:class:`~soft_gripper_sdre.sim.shape.FingerShape`, :func:`shape_of`), clips its m inputs to their
:class:`~soft_gripper_sdre.sim.shape.InputBounds` and passes them through the same first-order
roll-off (:class:`RollOff`), so laws differ only in their own arithmetic. The laws are in
:mod:`soft_gripper_sdre.control.laws`.

Which arithmetic a law runs is one rule, :func:`hand_path`: the hand's shape (d = 2, m = 2) with
bounds ±u_max on both inputs takes the hand's code (the compiled kernels with ``method='fast'``,
its 2×2 numpy otherwise); every other shape or bounds takes the general code (numpy and scipy for
any d, m and per-input bounds).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from soft_gripper_sdre.control.riccati import Check
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, InputBounds, ShapeError
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE


class WeightMatrix(np.ndarray):
    """A weight matrix of the hand's size that also builds the matrix of another size:
    ``weights.Q`` is the hand's (4, 4) Q and ``weights.Q(d)`` the (2d, 2d) one; ``weights.R`` the
    hand's (2, 2) R and ``weights.R(m)`` the (m, m) one (:class:`Weights`)."""

    def __new__(cls, build, size: int) -> 'WeightMatrix':
        out = np.asarray(build(size), dtype=float).view(cls)
        out._build = build
        return out

    def __array_finalize__(self, obj) -> None:
        self._build = getattr(obj, '_build', None)

    def __call__(self, size: int) -> np.ndarray:
        """The weight matrix for task dimension d (Q) or m inputs (R), a plain array."""
        return np.asarray(self._build(size), dtype=float)


@dataclass(frozen=True)
class Weights:
    """Diagonal SDRE weights in SI: Q = diag(q_pos·I_d, q_vel·I_d), R = r·I_m.

    ``Q`` and ``R`` are the hand's (d = 2, m = 2) matrices, diag(q_pos, q_pos, q_vel, q_vel) and
    diag(r, r); ``Q(d)`` and ``R(m)`` those of another shape (:class:`WeightMatrix`).
    """

    q_pos: float
    q_vel: float
    r: float

    def __post_init__(self) -> None:
        for name in ('q_pos', 'q_vel'):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0.0:
                raise ValueError(f'{name} must be finite and >= 0 (Q positive semi-definite), '
                                 f'got {v!r}')
        if not np.isfinite(self.r) or self.r <= 0.0:
            raise ValueError(f'r must be finite and > 0 (R positive definite), got {self.r!r}')

    def _q(self, d: int) -> np.ndarray:
        d = FingerShape(d, 1).d
        return np.diag([self.q_pos] * d + [self.q_vel] * d)

    def _r(self, m: int) -> np.ndarray:
        m = FingerShape(2, m).m
        return np.diag([self.r] * m)

    @property
    def Q(self) -> WeightMatrix:
        """The hand's (4, 4) state weight; ``Q(d)``: the (2d, 2d) one."""
        return WeightMatrix(self._q, HAND_SHAPE.d)

    @property
    def R(self) -> WeightMatrix:
        """The hand's (2, 2) input weight; ``R(m)``: the (m, m) one."""
        return WeightMatrix(self._r, HAND_SHAPE.m)

    def for_shape(self, shape: FingerShape) -> tuple[np.ndarray, np.ndarray]:
        """(Q (2d, 2d), R (m, m)) for ``shape``; the hand's are :attr:`Q` and :attr:`R`."""
        return self.Q(shape.d), self.R(shape.m)


def paper_weights_si() -> tuple[np.ndarray, np.ndarray]:
    """The paper's Q = diag(2,2,2,2), R = diag(0.1,0.1) (sim units) in SI.

    Positions and velocities scale by 20 (x_sim = 20 x_si) and torques by 400, so the cost
    x_simᵀ Q_sim x_sim + u_simᵀ R_sim u_sim equals
    x_siᵀ (400 Q_sim) x_si + u_siᵀ (160000 R_sim) u_si.
    """
    return (LENGTH_SCALE**2 * np.diag([2.0, 2.0, 2.0, 2.0]),
            TORQUE_SCALE**2 * np.diag([0.1, 0.1]))


#: tuned defaults (SI); docs/results.md "Noise, gains and the finger's bending modes" has the sweep
#: behind them
DEFAULT_WEIGHTS = dict(q_pos=1.0e6, q_vel=0.0, r=1.6e4)
#: first-order roll-off of the torque command [Hz]: cuts the loop's feed into the finger's
#: unmodelled ~59 Hz bending mode (README), well above the 3 and 9 Hz modes the model captures
DEFAULT_LOWPASS_HZ = 40.0
#: the roll-off's corner is at most this fraction of the sampling rate 1/Δt
#: (:func:`roll_off_corner_hz`)
ROLL_OFF_RATE_FRACTION = 0.1


def roll_off_corner_hz(hz: float, dt: float) -> float:
    """The corner the roll-off uses at control period ``dt`` [s]: ``hz``, or a tenth of the sampling
    rate where that is lower, min(hz, 0.1 / dt); 0 (off) stays 0.

    The command is held for a whole period, which lags the loop by about Δt/2. With a corner fixed
    in Hz, that lag destabilises the finger's unmodelled ~23 Hz bending mode at long periods, a mode
    the 40 Hz corner hardly attenuates (docs/design/control_period.md). A corner at a tenth of the
    sampling rate cuts that mode harder the longer the period; up to 2.5 ms the cap is above 40 Hz
    and the default corner is the one asked for.

    Raises:
        ValueError: ``hz`` is not finite and >= 0, or ``dt`` is not finite and > 0.
    """
    if not (np.isfinite(hz) and hz >= 0.0):
        raise ValueError(f'lowpass_hz must be finite and >= 0 (0 = off), got {hz!r}')
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f'the control period dt must be finite and > 0 s, got {dt!r}')
    return float(min(hz, ROLL_OFF_RATE_FRACTION / dt)) if hz > 0 else 0.0


class RollOff:
    """First-order roll-off of a command, the same for every law:

        u_k = a u_{k−1} + (1 − a) v_k,    a = e^{−2π f Δt},    u_0 = v_0,

    with v_k the law's saturated command and f the corner asked for, capped at a tenth of the
    sampling rate (:func:`roll_off_corner_hz`). f = 0 turns it off (u_k = v_k).

    Args:
        hz: corner frequency asked for [Hz], finite and >= 0.
        dt: control period Δt [s], finite and > 0.

    ``hz`` is the corner in use [Hz].
    """

    def __init__(self, hz: float, dt: float) -> None:
        self.hz = roll_off_corner_hz(hz, dt)
        self.alpha = float(np.exp(-2.0 * np.pi * self.hz * dt)) if self.hz > 0 else 0.0
        self._beta = 1.0 - self.alpha
        self._u = None

    def reset(self) -> None:
        """Forget the filter state: the next output is the next input."""
        self._u = None

    def __call__(self, v: np.ndarray) -> np.ndarray:
        if self.alpha > 0.0:
            v = v if self._u is None else self.alpha * self._u + self._beta * v
            self._u = v
        return v

    def kernel_args(self, v: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """(α, the previous output, whether there is one) for a compiled step that rolls off ``v``
        in place as :meth:`__call__` would, with 1 − α formed as here (before the first output the
        previous one is ``v`` itself, unused); then :meth:`keep` the result."""
        return self.alpha, v if self._u is None else self._u, self._u is not None

    def keep(self, u: np.ndarray) -> None:
        """``u`` was rolled off in place (:meth:`kernel_args`): it is the filter's last output."""
        if self.alpha > 0.0:
            self._u = u


def shape_of(model) -> FingerShape:
    """The finger shape a model controls: ``model.shape`` where it has one (an
    :class:`~soft_gripper_sdre.learning.model.SDCModel`), else inferred on a zero state from
    ``model.AG`` (the d, 2 then 3, for which AG(0 (1, 2d)) answers A (1, 2d, 2d) and G (1, 2d, m))
    or, for a model with only ``sdc_blocks``, from its lower rows (A2 (1, d, 2d), G2 (1, d, m)).

    Raises:
        ShapeError: the model has no shape and neither AG nor sdc_blocks answering like that, or
            the shape it has is not a :class:`~soft_gripper_sdre.sim.shape.FingerShape`.
    """
    shape = getattr(model, 'shape', None)
    if shape is not None:
        if not isinstance(shape, FingerShape):
            raise ShapeError(f'model.shape must be a FingerShape, got {shape!r}')
        return shape
    AG = getattr(model, 'AG', None)
    blocks = getattr(model, 'sdc_blocks', None)
    if AG is None and blocks is None:
        raise ShapeError(f'the model ({type(model).__name__}) has neither a shape nor AG(x) or '
                         'sdc_blocks(x)')
    answers = []
    for d in (2, 3):
        n = 2 * d
        try:
            A, G = (AG if AG is not None else blocks)(np.zeros((1, n)))
            a_shape, g_shape = np.shape(A), np.shape(G)
        except Exception as exc:        # a model of another d may fail on this state in any way
            answers.append(f'd={d}: {type(exc).__name__}')
            continue
        rows = n if AG is not None else d
        if (len(a_shape) == 3 and a_shape == (1, rows, n) and len(g_shape) == 3
                and g_shape[:2] == (1, rows)):
            return FingerShape(d, g_shape[2])
        answers.append(f'd={d}: {a_shape}, {g_shape}')
    raise ShapeError(f'cannot tell the shape of the model ({type(model).__name__}): on a zero '
                     f'state it gave {"; ".join(answers)}')


def hand_path(shape: FingerShape, bounds: InputBounds) -> bool:
    """The one rule that picks a law's arithmetic: True for the hand's shape (d = 2, m = 2) with
    the same limit ±u_max on both inputs, whose laws run the hand's code (the compiled kernels with
    ``method='fast'``, its 2×2 numpy with ``'reference'``); False for every other shape or bounds,
    whose laws run the general code (numpy and scipy for any d, m and per-input bounds)."""
    return shape == HAND_SHAPE and bounds.symmetric_limit is not None


def law_bounds(shape: FingerShape, u_max: float, bounds: InputBounds | None) -> InputBounds:
    """The bounds a law clips its inputs to: ``bounds``, or ±``u_max`` on each of the shape's m
    inputs when None.

    Raises:
        ShapeError: ``bounds`` is not an InputBounds of m inputs, or (None) ``u_max`` is not
            finite and > 0.
    """
    if bounds is None:
        if not (isinstance(u_max, (int, float, np.integer, np.floating))
                and np.isfinite(u_max) and u_max > 0):
            raise ShapeError(f'u_max must be finite and > 0, got {u_max!r}')
        return InputBounds.symmetric(u_max, shape.m)
    if not isinstance(bounds, InputBounds):
        raise ShapeError(f'bounds must be InputBounds (lower, upper per input), got {bounds!r}')
    if bounds.m != shape.m:
        raise ShapeError(f'bounds: the model has {shape.m} input(s) ({shape}), the bounds have '
                         f'{bounds.m} ({bounds})')
    return bounds


class RestFrame:
    """The model's translated coordinates: origin at the settled rest tip p₀, where f(0) = 0.

        x = [p − p₀, ṗ],    x_d = [p_d − p₀, ṗ_d]

    Args:
        rest_tip: the model's rest tip position (at least its first d coordinates) [m].
        n: number of fingers.
        d: the tip's dimension (2: X, Y; 3: X, Y, Z).
    """

    def __init__(self, rest_tip, n: int, d: int = 2) -> None:
        d = FingerShape(d, 1).d
        rest = np.asarray(rest_tip, dtype=float).reshape(-1)
        if rest.size < d or not np.all(np.isfinite(rest[:d])):
            raise ValueError(f'rest_tip must hold a finite rest position of {d} coordinates, '
                             f'got {rest_tip!r}')
        self.d = d
        self.origin = rest[:d].copy()
        self.n = int(n)
        # [p₀, 0, p₀, 0] for every finger (an array of z's shape: no broadcasting in z −= shift)
        self._shift = np.tile(np.concatenate([self.origin, np.zeros(d)] * 2), (self.n, 1))

    def states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray]:
        """(x, x_d), each (n, 2d), from (n, d) positions and velocities in the base frames.

        Raises:
            ValueError: when an input is not (n, d).
        """
        z = self.stacked(pos, vel, ref_pos, ref_vel)
        z -= self._shift
        n_state = 2 * self.d
        return z[:, :n_state], z[:, n_state:]

    def stacked(self, *arrays) -> np.ndarray:
        """The (n, d) arrays side by side as one new (n, dk) float64 array: [pos, vel, ref_pos,
        ref_vel, …] in the order given (the rows the compiled kernels take).

        Raises:
            ValueError: when one is not (n, d) (named as the law's inputs pos, vel, ref_pos,
                ref_vel).
        """
        z = None
        shape = (self.n, self.d)
        if all(np.shape(a) == shape for a in arrays):
            try:
                z = np.concatenate(arrays, axis=1, dtype=float)
            except (ValueError, TypeError):
                pass
        if z is None:
            raise ValueError(f'pos, vel, ref_pos, ref_vel must each have shape {shape}, got '
                             f'{[np.shape(a) for a in arrays]}')
        return z


_NO_DEMAND: dict[int, np.ndarray] = {}


def no_unreachable(n: int) -> np.ndarray:
    """(n,) read-only zeros: the :attr:`LawStep.unreachable` of a law without feedforward."""
    z = _NO_DEMAND.get(n)
    if z is None:
        z = np.zeros(n)
        z.flags.writeable = False
        _NO_DEMAND[n] = z
    return z


@dataclass
class LawStep:
    """One step of a law for n fingers with m inputs each. The SDRE laws also fill K, Ks, P and
    nk_iterations; the laws that invert the model fill ``unreachable`` (zeros otherwise)."""

    u: np.ndarray                # (n, m) clipped, rolled-off inputs [N·m, N, Pa, …], always finite
    u_unsat: np.ndarray          # (n, m) before clipping to the bounds
    ok: np.ndarray               # (n,) the law's own checks passed
    fallback: np.ndarray         # (n,) a fallback was used (last valid gains, zero, no feedforward)
    failed_checks: np.ndarray    # (n,) int bitmask of :class:`Check` (0 for laws without checks)
    saturated: np.ndarray        # (n, m) u_unsat outside the input's bounds
    residual: np.ndarray         # (n,) relative Riccati residual (0 for closed-form laws)
    K: np.ndarray | None = None              # (n, m, 2d) SDRE gains in use
    Ks: np.ndarray | None = None             # (n, m, 2d)
    P: np.ndarray | None = None              # (n, 2d, 2d) Riccati solution (NaN where it failed)
    nk_iterations: np.ndarray | None = None  # (n,) Newton–Kleinman iterations (0 = exact solve)
    #: (n,) [m/s²] the norm of the part of the model inversion's acceleration demand no input can
    #: reach, ‖(I − G₂G₂⁺) d‖ (0 where G₂ has full row rank, and for laws without an inversion)
    unreachable: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.unreachable is None:
            self.unreachable = no_unreachable(len(self.ok))


class Law(Protocol):
    """A control law for n fingers: what the controller node, the in-process loop and the tools
    call.

    A law that needs the plant's ground truth (the oracles,
    :mod:`soft_gripper_sdre.analysis.oracle`) also has ``observe(truth)``, which the in-process
    loop calls before each :meth:`compute`.
    """

    def compute(self, pos: np.ndarray, vel: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray,
                ref_acc: np.ndarray | None = None) -> LawStep:
        """Inputs for every finger from (n, d) tip positions [m] and velocities [m/s], their
        references, and the reference acceleration [m/s²] (used by the feedforward laws;
        None = 0)."""

    def reset(self) -> None:
        """Forget all state (warm starts, last valid gains, the filter), e.g. after a clock jump."""


class LawIO:
    """The plumbing a law composes around its own arithmetic: the translated states in (non-finite
    rows zeroed), clipping to the input bounds and the :class:`RollOff` out.

    Args:
        rest_tip: the model's rest tip position (at least its first d coordinates) [m].
        u_max: the inputs' limit ±u_max [N·m] where ``bounds`` is None, finite and > 0.
        n_fingers: number of fingers.
        lowpass_hz, dt: the roll-off's corner frequency [Hz] (0 = off) and the control period [s].
        shape: the finger's shape (None: the hand's, d = 2, m = 2).
        bounds: per-input [lower, upper] (None: ±``u_max`` on each input, :func:`law_bounds`).

    ``bounds`` is what the law clips to; ``hand`` says whether it runs the hand's code
    (:func:`hand_path`); ``u_max`` is the largest magnitude any input may take.
    """

    def __init__(self, rest_tip, u_max: float, n_fingers: int, lowpass_hz: float,
                 dt: float, shape: FingerShape | None = None,
                 bounds: InputBounds | None = None) -> None:
        self.shape = HAND_SHAPE if shape is None else shape
        self.frame = RestFrame(rest_tip, n_fingers, self.shape.d)
        if bounds is None and not (np.isfinite(u_max) and u_max > 0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max!r}')
        self.bounds = law_bounds(self.shape, u_max, bounds)
        self.hand = hand_path(self.shape, self.bounds)
        self.u_max = (float(u_max) if bounds is None
                      else float(np.max(np.maximum(-self.bounds.lower, self.bounds.upper))))
        self.n_fingers = int(n_fingers)
        self.roll_off = RollOff(lowpass_hz, dt)

    @property
    def origin(self) -> np.ndarray:
        """(d,) rest tip position the model's coordinates are translated by [m]."""
        return self.frame.origin

    def reset(self) -> None:
        self.roll_off.reset()

    def states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, x_d, finite) in translated coordinates; non-finite rows are zeroed."""
        x, xd = self.frame.states(pos, vel, ref_pos, ref_vel)
        finite = np.isfinite(x).all(axis=1) & np.isfinite(xd).all(axis=1)
        if not finite.all():
            x[~finite] = 0.0
            xd[~finite] = 0.0
        return x, xd, finite

    def clip(self, u_unsat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, saturated): ``u_unsat`` (n, m) clipped to the bounds, and where it was outside."""
        b = self.bounds
        return np.clip(u_unsat, b.lower, b.upper), (u_unsat < b.lower) | (u_unsat > b.upper)

    def finish(self, u_unsat: np.ndarray, finite: np.ndarray) -> LawStep:
        """The step of a law without Riccati checks: u_unsat zeroed where not finite, clipped to
        the bounds, rolled off; a non-finite finger is flagged (NONFINITE) and counts as a
        fallback. A zeroed input lies at the input's :attr:`InputBounds.rest` once clipped."""
        u_unsat = np.where(np.isfinite(u_unsat) & finite[:, None], u_unsat, 0.0)
        u, saturated = self.clip(u_unsat)
        u = self.roll_off(u)
        return LawStep(u=u, u_unsat=u_unsat, ok=finite.copy(), fallback=~finite,
                       failed_checks=np.where(finite, 0, int(Check.NONFINITE)), saturated=saturated,
                       residual=np.zeros(self.n_fingers))
