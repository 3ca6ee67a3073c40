"""A finger's shape as a value: how many inputs it has, what each can deliver, and how many
coordinates its tip has.

Every layer takes the shape from here instead of assuming the hand's:

* :class:`FingerShape` — the task dimension d (2: a planar tip (X, Y); 3: a tip (X, Y, Z)) and
  the number of inputs m (1 to 4). The state is x = [p; ṗ] ∈ R^2d, the learned blocks are
  A21, A22 ∈ R^{d×d} and G2 ∈ R^{d×m}, and the torque command names ``<finger>/ax<k>`` for k < m.
* :class:`InputBounds` — per input the interval [lower, upper] the actuator can deliver: a motor
  −τ..τ, a pneumatic chamber 0..p_max, a tendon 0..T_max. Every law, the excitation and the
  drivers clip to it; one-sided inputs (lower ≥ 0 or upper ≤ 0) are what the laws, the excitation
  signals and the derived settings must not chatter against.

The hand of this package is :data:`HAND_SHAPE` (d = 2, m = 2) with the symmetric bounds of its
controller's ``torque_limit`` (:meth:`InputBounds.symmetric`). A checkpoint carries its shape and
the bounds its data were recorded under; one without them is the hand's
(:func:`shape_from_record`).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

#: task dimensions a finger may have: a planar tip or a 3-D tip
TASK_DIMENSIONS = (2, 3)
#: the number of inputs a finger may have
MIN_INPUTS, MAX_INPUTS = 1, 4
#: the names of the task-space axes, in order
AXIS_NAMES = ('X', 'Y', 'Z')


class ShapeError(ValueError):
    """A finger shape or input bounds that cannot be used; the message names what is wrong."""


def _whole(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            return int(value)
        raise ShapeError(f'{what} must be a whole number, got {value!r}')
    return int(value)


@dataclass(frozen=True)
class FingerShape:
    """The task dimension ``d`` (2 or 3) and the number of inputs ``m`` (1 to 4) of a finger.

    Raises:
        ShapeError: ``d`` or ``m`` out of range or not whole numbers.
    """

    d: int
    m: int

    def __post_init__(self) -> None:
        d = _whole(self.d, 'the task dimension d')
        m = _whole(self.m, 'the number of inputs m')
        if d not in TASK_DIMENSIONS:
            raise ShapeError(f'the task dimension d must be one of {TASK_DIMENSIONS} (a planar or '
                             f'a 3-D tip), got {self.d!r}')
        if not MIN_INPUTS <= m <= MAX_INPUTS:
            raise ShapeError(f'the number of inputs m must be {MIN_INPUTS} to {MAX_INPUTS}, '
                             f'got {self.m!r}')
        object.__setattr__(self, 'd', d)
        object.__setattr__(self, 'm', m)

    @property
    def n_state(self) -> int:
        """Length of the state x = [p; ṗ]: 2d."""
        return 2 * self.d

    @property
    def axes(self) -> tuple[str, ...]:
        """The task-space axes' names: ('X', 'Y') or ('X', 'Y', 'Z')."""
        return AXIS_NAMES[:self.d]

    @property
    def square(self) -> bool:
        """G2 is square (m = d): the model can be inverted exactly wherever G2 is regular."""
        return self.m == self.d

    @property
    def network_outputs(self) -> tuple[int, int]:
        """Outputs of the two SDC networks: vec([A21 A22]) (2d²) and vec(G2) (dm)."""
        return 2 * self.d * self.d, self.d * self.m

    def input_names(self, finger: str) -> list[str]:
        """The command's joint names of one finger: ``<finger>/ax0`` … ``<finger>/ax<m−1>``."""
        return [f'{finger}/ax{k}' for k in range(self.m)]

    def to_record(self) -> dict:
        """Plain data for a checkpoint or a parameter file."""
        return {'d': self.d, 'm': self.m}

    def __str__(self) -> str:
        return f'd={self.d}, m={self.m}'


#: the hand of this package: a planar tip, two bidirectional torques
HAND_SHAPE = FingerShape(2, 2)
#: the input gains a finger of a shared model may have against it (how much more strongly its
#: inputs act); beyond, it is not that model's finger
INPUT_GAIN_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class InputBounds:
    """Per input the interval [lower, upper] the actuator can deliver (SI: N·m, N, Pa, …).

    ``lower`` and ``upper`` are (m,) float arrays with lower < upper, both finite.

    Raises:
        ShapeError: arrays of different lengths, a length out of 1..4, a bound not finite, or an
            interval that is empty.
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        lo = np.array(self.lower, dtype=float).reshape(-1)
        hi = np.array(self.upper, dtype=float).reshape(-1)
        if lo.shape != hi.shape:
            raise ShapeError(f'input bounds: {lo.size} lower and {hi.size} upper bounds; '
                             'give one of each per input')
        if not MIN_INPUTS <= lo.size <= MAX_INPUTS:
            raise ShapeError(f'input bounds: {lo.size} inputs; a finger has {MIN_INPUTS} to '
                             f'{MAX_INPUTS}')
        for k in range(lo.size):
            if not (math.isfinite(lo[k]) and math.isfinite(hi[k])):
                raise ShapeError(f'input ax{k}: bounds must be finite, got [{lo[k]}, {hi[k]}]')
            if not lo[k] < hi[k]:
                raise ShapeError(f'input ax{k}: the lower bound must be below the upper one, '
                                 f'got [{lo[k]}, {hi[k]}]')
        lo.flags.writeable = False
        hi.flags.writeable = False
        object.__setattr__(self, 'lower', lo)
        object.__setattr__(self, 'upper', hi)

    @classmethod
    def symmetric(cls, limit: float, m: int = 2) -> 'InputBounds':
        """±``limit`` on each of ``m`` inputs (the hand: ±``torque_limit``)."""
        limit = float(limit)
        if not (math.isfinite(limit) and limit > 0):
            raise ShapeError(f'the input limit must be finite and > 0, got {limit!r}')
        return cls(np.full(int(m), -limit), np.full(int(m), limit))

    @classmethod
    def parse(cls, lower: Sequence[float], upper: Sequence[float], m: int,
              what: str = 'input bounds') -> 'InputBounds':
        """Bounds from two lists given by a user (parameters, a file), checked against ``m``
        inputs; the error names ``what``."""
        lo, hi = list(lower), list(upper)
        if len(lo) != m or len(hi) != m:
            raise ShapeError(f'{what}: the finger has {m} input(s); got {len(lo)} lower and '
                             f'{len(hi)} upper bound(s)')
        try:
            return cls(np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
        except (TypeError, ValueError) as exc:
            raise ShapeError(f'{what}: {exc}') from None

    @classmethod
    def from_record(cls, record: dict, what: str = 'input bounds') -> 'InputBounds':
        """Bounds from :meth:`to_record`'s plain data; ShapeError naming ``what``."""
        if not isinstance(record, dict) or not {'lower', 'upper'} <= set(record):
            raise ShapeError(f'{what}: expected a mapping with lower and upper, got {record!r}')
        lo, hi = record['lower'], record['upper']
        if not isinstance(lo, (list, tuple)) or not isinstance(hi, (list, tuple)):
            raise ShapeError(f'{what}: lower and upper must be lists, got {lo!r}, {hi!r}')
        return cls.parse(lo, hi, len(lo), what)

    def to_record(self) -> dict:
        return {'lower': [float(v) for v in self.lower], 'upper': [float(v) for v in self.upper]}

    @property
    def m(self) -> int:
        return int(self.lower.size)

    @property
    def symmetric_limit(self) -> float | None:
        """The common limit when every input is ±the same value, else None."""
        u = self.upper[0]
        if np.all(self.upper == u) and np.all(self.lower == -u):
            return float(u)
        return None

    @property
    def mid(self) -> np.ndarray:
        """(m,) the middle of each interval."""
        return 0.5 * (self.lower + self.upper)

    @property
    def half_span(self) -> np.ndarray:
        """(m,) half of each interval's width."""
        return 0.5 * (self.upper - self.lower)

    @property
    def one_sided(self) -> np.ndarray:
        """(m,) bool: the input acts one way only (lower ≥ 0 or upper ≤ 0), e.g. a chamber or a
        tendon."""
        return (self.lower >= 0.0) | (self.upper <= 0.0)

    @property
    def rest(self) -> np.ndarray:
        """(m,) the input nearest zero each actuator can deliver: what it holds when told nothing
        (0 where the interval contains 0; a one-sided input's bound nearest 0)."""
        return np.clip(0.0, self.lower, self.upper)

    def clip(self, u: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``u`` (…, m) clipped into the bounds."""
        return np.clip(u, self.lower, self.upper, out=out)

    def saturated(self, u: np.ndarray) -> np.ndarray:
        """(…, m) bool: where ``u`` lies outside the bounds."""
        return (u < self.lower) | (u > self.upper)

    def contains(self, u: np.ndarray, tol: float = 0.0) -> bool:
        """Every entry of ``u`` (…, m) lies within the bounds (by ``tol``)."""
        u = np.asarray(u, dtype=float)
        return bool(np.all(u >= self.lower - tol) & np.all(u <= self.upper + tol))

    def through_gains(self, gains: Sequence[float]) -> 'InputBounds':
        """The commands v, in a shared model's input units, that every finger can deliver when
        finger f, whose inputs act ``gains[f]`` times as strongly as the model's, receives
        v / g_f: per input [max_f g_f lower, min_f g_f upper] (bounds about zero: the bounds
        times the smallest gain). For bounds away from zero the fingers' rest values differ in
        the model's units, and the loop rests at the shared lower bound: the weaker finger then
        holds a little above its own rest.

        Raises:
            ShapeError: no gains, a gain not finite and > 0, or no command every finger can
                deliver (one-sided bounds away from zero, gains far apart).
        """
        g = np.asarray(list(gains), dtype=float).reshape(-1)
        if g.size == 0 or not np.all(np.isfinite(g) & (g > 0)):
            raise ShapeError(f'input gains must be finite and > 0, one per finger, got '
                             f'{list(gains)!r}')
        lo = np.max(g[:, None] * self.lower[None], axis=0)
        hi = np.min(g[:, None] * self.upper[None], axis=0)
        if not np.all(lo < hi):
            k = int(np.flatnonzero(lo >= hi)[0])
            raise ShapeError(f'input ax{k}: no command within [{self.lower[k]:g}, '
                             f'{self.upper[k]:g}] reaches every finger through the input gains '
                             f'{[float(v) for v in g]}')
        return InputBounds(lo, hi)

    def __str__(self) -> str:
        return ', '.join(f'ax{k} [{lo:g}, {hi:g}]'
                         for k, (lo, hi) in enumerate(zip(self.lower, self.upper)))

    def __eq__(self, other) -> bool:
        return (isinstance(other, InputBounds) and np.array_equal(self.lower, other.lower)
                and np.array_equal(self.upper, other.upper))

    def __hash__(self) -> int:
        return hash((tuple(self.lower), tuple(self.upper)))


def shape_from_record(record: dict | None, what: str = 'shape') -> FingerShape:
    """The shape in a checkpoint's or a parameter file's record; None (no record, as in the
    hand's checkpoints) is :data:`HAND_SHAPE`."""
    if record is None:
        return HAND_SHAPE
    if not isinstance(record, dict) or not {'d', 'm'} <= set(record):
        raise ShapeError(f'{what}: expected a mapping with d and m, got {record!r}')
    try:
        return FingerShape(record['d'], record['m'])
    except ShapeError as exc:
        raise ShapeError(f'{what}: {exc}') from None
