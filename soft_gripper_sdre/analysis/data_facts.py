"""What a finger's recordings say about it, for the loop settings derived from them
(:mod:`~soft_gripper_sdre.analysis.loop_settings`): the tip period, the measurement noise, the
input range, the estimator intensity that best explains the tips, and the move a closed-loop
check makes: along the direction the finger moved most, by a share of its reach that way.

The tips are d-dimensional (a planar tip: X, Y; a 3-D tip: X, Y, Z) and the inputs m; a planar
finger's direction is an angle from +X toward +Y (:attr:`DataFacts.direction`), a 3-D finger's
a unit vector (:attr:`DataFacts.axis`).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from soft_gripper_sdre.learning.compiled_labels import cv_loglik_axis
from soft_gripper_sdre.sim.shape import InputBounds, ShapeError

#: the check's move: along the data's principal direction by a share of the data's reach that way
#: (the 99th percentile of the tips projected on it), on the trajectory node's default timing
TRAVEL_SHARE = 0.5
REACH_PERCENTILE = 99.0
#: the torque limit is this many times the largest torque of the excitation
TORQUE_MARGIN = 2.0


def unit_vector(degrees: float) -> np.ndarray:
    """(cos, sin) of an angle from +X toward +Y [deg]."""
    a = math.radians(degrees)
    return np.array([math.cos(a), math.sin(a)])


@dataclass(frozen=True)
class DataFacts:
    """What the recordings say about the finger (SI).

    ``bounds`` None is the hand's rule: ±``torque_limit`` on every input. ``axis`` None is a
    planar move at ``direction``; a 3-D finger's move goes along ``axis`` (a unit vector of
    three). ``path`` (K, d) is the move of a finger that holds still only on a curve (fewer
    inputs than tip coordinates: :func:`~soft_gripper_sdre.analysis.holding.equilibrium_curve`),
    waypoints relative to rest from rest on, ``travel`` its arc length; None is the straight move.

    ``input_delay`` is how much later the finger moves than its model under the same inputs
    (:func:`~soft_gripper_sdre.analysis.loop_settings.unmodelled_delay`); the closed-loop check
    applies its commands that much later.

    ``input_gains`` maps each finger's name to how much more strongly its inputs act than the
    model's (:func:`~soft_gripper_sdre.analysis.finger_fits.input_gains`; none: every finger is
    the model). The law runs in the model's units and finger f receives v / g_f, so the check
    runs the law within the bounds every finger delivers that way
    (:meth:`~soft_gripper_sdre.sim.shape.InputBounds.through_gains`).

    Raises:
        ShapeError: ``axis`` not of 2 or 3 finite values of unit length, ``path`` not of
            waypoints of as many values as the move's direction, ``input_delay`` negative or
            not finite, or an input gain not finite and > 0.
    """

    period: float                 # median tip period [s]
    noise_std: float              # measurement σ [m]
    travel: float                 # length of the move the check makes along ``direction`` [m]
    torque_limit: float           # the loop's largest input magnitude [SI of the input]
    accel_psd_ml: float           # the CV model's likelihood-best intensity [(m/s²)²/Hz]
    # TRAVEL_SHARE of the data's reach that way [m] (None: travel)
    reach_travel: float | None = None
    direction: float = 90.0       # of the move, from +X toward +Y [deg] (90: closing along +Y)
    axis: tuple[float, ...] | None = None          # the move's unit direction, d values
    bounds: InputBounds | None = None              # the loop's per-input bounds
    path: tuple[tuple[float, ...], ...] | None = None   # (K, d) waypoints of a curved move [m]
    # the input-to-motion delay the model lacks [s] (loop_settings.unmodelled_delay; 0: none)
    input_delay: float = 0.0
    # per finger name, its inputs' strength against the model's (finger_fits.input_gains)
    input_gains: dict[str, float] | None = None

    def __post_init__(self) -> None:
        if self.axis is not None:
            a = np.asarray(self.axis, dtype=float).reshape(-1)
            if a.size not in (2, 3) or not np.all(np.isfinite(a)) or \
                    abs(np.linalg.norm(a) - 1.0) > 1e-9:
                raise ShapeError(f'the move\'s axis must be a unit vector of 2 or 3 finite '
                                 f'values, got {self.axis!r}')
            object.__setattr__(self, 'axis', tuple(float(v) for v in a))
        if self.path is not None:
            p = np.asarray(self.path, dtype=float)
            if p.ndim != 2 or p.shape[1] != self.d or len(p) < 2 or \
                    not np.all(np.isfinite(p)):
                raise ShapeError(f'the move\'s path must hold at least two finite waypoints of '
                                 f'{self.d} values, got shape {p.shape}')
            object.__setattr__(self, 'path', tuple(tuple(float(v) for v in q) for q in p))
        if not (isinstance(self.input_delay, (int, float)) and math.isfinite(self.input_delay)
                and self.input_delay >= 0):
            raise ShapeError(f'the input delay must be finite and >= 0 s, got '
                             f'{self.input_delay!r}')
        if self.input_gains is not None:
            gains = dict(self.input_gains)
            bad = {k: v for k, v in gains.items() if not (
                isinstance(k, str) and isinstance(v, (int, float)) and not isinstance(v, bool)
                and math.isfinite(v) and v > 0)}
            if bad or not gains:
                raise ShapeError(f'input gains must map finger names to finite gains > 0, got '
                                 f'{self.input_gains!r}')
            object.__setattr__(self, 'input_gains', {k: float(v) for k, v in gains.items()})

    @property
    def unit(self) -> np.ndarray:
        """The move's direction as a unit vector: (X, Y), or ``axis``. A curved move's is the
        chord from rest to the path's end."""
        if self.path is not None:
            end = np.asarray(self.path[-1])
            n = np.linalg.norm(end)
            return end / n if n > 0 else np.eye(self.d)[0]
        return unit_vector(self.direction) if self.axis is None else np.asarray(self.axis)

    @property
    def d(self) -> int:
        """The task dimension of the move."""
        return 2 if self.axis is None else len(self.axis)

    def move(self) -> tuple[float, float]:
        """The move as the trajectory node's ``(close_distance, side_distance)`` [m]: its Y and X
        parts."""
        x, y = self.travel * self.unit[:2]
        return float(y), float(x)

    def waypoints(self) -> np.ndarray:
        """(K, d) the move from rest [m]: the path, or the straight move's two ends."""
        if self.path is not None:
            return np.asarray(self.path)
        return np.stack([np.zeros(self.d), self.travel * self.unit])


def cv_loglik(t: np.ndarray, pos: np.ndarray, accel_psd: float, meas_std: float) -> float:
    """Innovation log-likelihood of tips ``pos`` (N, d) at times ``t`` under the estimator's
    constant-velocity model (each axis on its own; compiled:
    :func:`~soft_gripper_sdre.learning.compiled_labels.cv_loglik_axis`)."""
    t = np.ascontiguousarray(t, dtype=float)
    pos = np.asarray(pos, dtype=float)
    return float(sum(cv_loglik_axis(t, np.ascontiguousarray(pos[:, axis]), float(accel_psd),
                                    float(meas_std) ** 2) for axis in range(pos.shape[1])))


def tune_accel_psd(t: np.ndarray, pos: np.ndarray, meas_std: float,
                   grid: np.ndarray | None = None) -> float:
    """The estimator's intensity that best explains the tips (:func:`cv_loglik` on a log grid)."""
    grid = np.logspace(-3, 5, 17) if grid is None else grid
    sigma = max(meas_std, 1e-7)
    return float(max(grid, key=lambda q: cv_loglik(t, pos, q, sigma)))


def principal_axis(positions: np.ndarray) -> np.ndarray:
    """(d,) the unit direction the tips ``positions`` (N, d), as displacements from the rest
    pose, moved most: the principal axis of their second moment about the rest, turned toward +Y
    (the closing side; where it has no Y part, toward +X, then +Z)."""
    p = np.asarray(positions, dtype=float)
    _, vecs = np.linalg.eigh(p.T @ p)
    v = vecs[:, -1]
    for k in (1, 0, 2)[:len(v)]:
        if v[k] != 0:
            return v if v[k] > 0 else -v
    return v


def closing_direction(positions: np.ndarray) -> float:
    """The direction [deg from +X toward +Y, in [0, 180)] the tips ``positions`` (N, 2), as
    displacements from the rest pose, moved most: the principal axis of their second moment about
    the rest, turned toward +Y (the closing side; toward +X when it lies along X)."""
    p = np.asarray(positions, dtype=float)
    _, vecs = np.linalg.eigh(p.T @ p)
    x, y = vecs[:, -1]
    if y < 0 or (y == 0 and x < 0):
        x, y = -x, -y
    return float(math.degrees(math.atan2(y, x)))


def input_range(torques: np.ndarray, recorded: InputBounds | None,
                given: bool = False) -> tuple[float, InputBounds | None]:
    """The loop's input range from the held inputs ``torques`` (N, m) and the bounds the data
    were recorded under (``recorded``; None: the hand's checkpoints): (the largest magnitude,
    the per-input bounds or None).

    Every input acting both ways (the hand, a motor): ±:data:`TORQUE_MARGIN` × the largest
    input of the data on every input (bounds None: the symmetric limit). A one-sided input
    (a chamber 0..p_max, a tendon 0..T_max): from its rest bound to :data:`TORQUE_MARGIN` × the
    data's largest excursion from it, within the recorded bounds (it cannot deliver past them);
    its two-sided neighbours keep ±:data:`TORQUE_MARGIN` × their own largest input.

    ``given``: ``recorded`` are the bounds the actuators deliver (the user gave them, e.g. the
    driver's), not the range the commands spanned: every two-sided interval above is cut to them
    too, so the loop never counts on more than the actuator delivers (symmetric and alike on
    every input: the symmetric limit, no bounds).
    """
    u = np.asarray(torques, dtype=float)
    limit = TORQUE_MARGIN * float(np.percentile(np.abs(u).max(axis=1), 99.9))
    if recorded is None:
        return limit, None
    if u.ndim != 2 or recorded.m != u.shape[1]:
        raise ShapeError(f'input bounds: {recorded.m} input(s) recorded, the data hold '
                         f'{u.shape[1]}')
    if not recorded.one_sided.any():
        if not given:
            return limit, None
        lo, hi = np.maximum(recorded.lower, -limit), np.minimum(recorded.upper, limit)
        if np.allclose(lo, -hi, rtol=1e-12, atol=0.0) and np.allclose(hi, hi[0], rtol=1e-12,
                                                                       atol=0.0):
            return float(hi[0]), None
        bounds = InputBounds(lo, hi)
        return float(np.max(np.maximum(np.abs(lo), np.abs(hi)))), bounds
    rest = recorded.rest
    span = TORQUE_MARGIN * np.percentile(np.abs(u - rest), 99.9, axis=0)
    span = np.where(span > 0, span, recorded.half_span)          # an input the data never moved
    push = recorded.lower >= 0.0                 # acts toward + only: rest is its lower bound
    pull = recorded.upper <= 0.0                 # acts toward − only: rest is its upper bound
    lo = np.where(push, recorded.lower, np.where(pull, np.maximum(recorded.lower, rest - span),
                                                 -span))
    hi = np.where(pull, recorded.upper, np.where(push, np.minimum(recorded.upper, rest + span),
                                                 span))
    if given:
        lo, hi = np.maximum(lo, recorded.lower), np.minimum(hi, recorded.upper)
    bounds = InputBounds(lo, hi)
    return float(np.max(np.maximum(np.abs(bounds.lower), np.abs(bounds.upper)))), bounds


def data_facts(positions: np.ndarray, torques: np.ndarray, period: float, noise_std: float,
               tune: list[tuple[np.ndarray, np.ndarray]],
               bounds: InputBounds | None = None, given: bool = False) -> DataFacts:
    """:class:`DataFacts` from the training samples: translated positions (N, d), held inputs
    (N, m), the tip period, the measured σ, (t, tips) of stretches to tune the estimator on
    (the largest intensity any of them asks for: the loop must follow the fastest motion), and
    the bounds the data were recorded under (:func:`input_range`).

    Raises:
        ShapeError: tips of another task dimension than 2 or 3, or bounds of another number of
            inputs than the data.
    """
    positions = np.asarray(positions, dtype=float)
    if positions.ndim != 2 or positions.shape[1] not in (2, 3):
        raise ShapeError(f'the tips must be (N, 2) or (N, 3), got {positions.shape}')
    limit, loop = input_range(torques, bounds, given)
    psd = max(tune_accel_psd(t, tips, noise_std) for t, tips in tune)
    if positions.shape[1] == 2:
        direction = closing_direction(positions)
        along = positions @ unit_vector(direction)
        axis = None
    else:
        axis = principal_axis(positions)
        along = positions @ axis
        direction = float(math.degrees(math.atan2(axis[1], axis[0])))
        axis = tuple(float(v) for v in axis)
    travel = TRAVEL_SHARE * max(float(np.percentile(along, REACH_PERCENTILE)), 0.0)
    return DataFacts(period=float(period), noise_std=float(noise_std), travel=float(travel),
                     torque_limit=limit, accel_psd_ml=psd, reach_travel=float(travel),
                     direction=direction, axis=axis, bounds=loop)
