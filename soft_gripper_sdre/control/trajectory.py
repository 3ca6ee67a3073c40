"""The grasp reference: two opposite fingers close on the cube along a smooth sinusoid and open
again.

Every finger's reference lives in its own base frame (SI, untranslated): it starts at the finger's
rest tip position and moves by a scalar profile ``s(t) ∈ [0, 1]`` along a fixed direction,

    p_d(t) = p_rest + s(t) · d,        ṗ_d = ṡ d,        p̈_d = s̈ d,

with ``d = [side, close]`` for the grasping fingers (+Y points at the palm centre, so a positive
``close`` distance moves the tip toward the cube). ``s`` is a raised cosine on each moving phase,

    closing:  s = (1 − cos(π τ / T_c)) / 2,   τ = t − t_start ∈ [0, T_c]
    holding:  s = 1                            for T_h
    opening:  s = (1 + cos(π τ / T_o)) / 2,   τ ∈ [0, T_o]

so position and velocity are continuous everywhere; the acceleration steps by ±π²/(2T²)·|d| where
a moving phase starts and ends (a half-cosine, as in the paper's sinusoidal grasp). The controller
tracks position and velocity only, so the steps reach it as a kink in the reference velocity.

**Any finger's shape.** A tip of task dimension 3 (``dim=3``) plans in (X, Y, Z). The grasping
fingers close along ``direction`` (a unit vector of ``dim`` values; None = +Y):
``d = side · e_X + travel · direction`` (the hand's ``[side, close]`` for +Y), and the others
open along −``direction``. A finger that cannot move its tip along a straight line (one input
reaches a curve) closes along ``close_path`` instead: waypoints relative to rest, through which a
natural cubic spline P(σ) runs, σ ∈ [0, 1] its normalised chord length (P(0) = 0, the rest), so

    p_d = p_rest + P(s),        ṗ_d = P'(s) ṡ,        p̈_d = P''(s) ṡ² + P'(s) s̈.

The grasping fingers are meant to make contact with the cube partway through the closing phase
(the reference continues a little "into" the cube so that the fingers squeeze it);
:meth:`GraspTrajectory.free_space` tells where the reference stays a margin clear of the cube
face, which is where free-space tracking is scored.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np
from scipy.interpolate import CubicSpline

#: what the non-grasping fingers do
OTHERS_MODES = ('hold', 'open')


@dataclass(frozen=True)
class GraspProfile:
    """Timing and geometry of the grasp (SI).

    Attributes:
        t_start: hold at rest before the fingers move [s].
        t_close: duration of the closing motion [s].
        t_hold: time spent closed [s].
        t_open: duration of the opening motion [s].
        close_distance: travel of the grasping fingers along +Y (toward the cube) [m].
        side_distance: travel of the grasping fingers along X during the same motion [m].
        contact_distance: travel along +Y at which a grasping tip touches the cube face [m]
            (used only to tell free-space phases from contact phases).
        contact_margin: clearance from the cube face below which a phase no longer counts as
            free space [m].
        grasp_fingers: indices of the two opposite fingers that grasp.
        others: ``'hold'`` (stay at rest) or ``'open'`` (move away from the cube by
            ``open_distance`` while the others close).
        open_distance: travel of the non-grasping fingers along −Y in ``'open'`` mode [m].
        close_to: where the grasping fingers close to along Y in their base frames [m], anchoring
            the closed pose to the hand (and the cube on it) rather than to the rest pose: each
            grasping finger then travels ``close_to − rest_y``, and meets the cube face that much
            minus the squeeze ``close_distance − contact_distance``. None: ``close_distance``
            from the rest pose.
        direction: the unit direction the grasping fingers close along, 2 or 3 values (the tip's
            task dimension; normalised here); None: +Y.
        close_path: waypoints the grasping fingers close through, relative to rest, as a flat
            tuple of the tip's task dimension values per point (the last is the closed pose);
            None: the straight move of ``direction``, ``close_distance`` and ``side_distance``.
    """

    t_start: float = 0.5
    t_close: float = 2.0
    t_hold: float = 1.0
    t_open: float = 2.0
    close_distance: float = 0.030
    side_distance: float = 0.0
    contact_distance: float = 0.024
    contact_margin: float = 0.002
    grasp_fingers: tuple[int, ...] = (0, 2)
    others: str = 'hold'
    open_distance: float = 0.005
    close_to: float | None = None
    direction: tuple[float, ...] | None = None
    close_path: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.direction is not None:
            u = np.asarray(self.direction, dtype=float).reshape(-1)
            norm = float(np.linalg.norm(u)) if np.all(np.isfinite(u)) else math.nan
            if u.size not in (2, 3) or not (math.isfinite(norm) and norm > 1e-12):
                raise ValueError(f'direction must be 2 or 3 finite values, not all zero, got '
                                 f'{self.direction!r}')
            object.__setattr__(self, 'direction', tuple((u / norm).tolist()))
        if self.close_path is not None:
            path = np.asarray(self.close_path, dtype=float).reshape(-1)
            if path.size == 0 or not np.all(np.isfinite(path)):
                raise ValueError(f'close_path must be finite values, d per waypoint, got '
                                 f'{self.close_path!r}')
            object.__setattr__(self, 'close_path', tuple(path.tolist()))
        if self.close_to is not None and not math.isfinite(self.close_to):
            raise ValueError(f'close_to must be finite or None, got {self.close_to!r}')
        for name in ('t_start', 't_hold'):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) < 0.0:
                raise ValueError(f'{name} must be finite and >= 0, got {getattr(self, name)!r}')
        for name in ('t_close', 't_open'):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) <= 0.0:
                raise ValueError(f'{name} must be finite and > 0, got {getattr(self, name)!r}')
        for name in ('close_distance', 'side_distance', 'contact_distance', 'contact_margin',
                     'open_distance'):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f'{name} must be finite, got {getattr(self, name)!r}')
        if self.others not in OTHERS_MODES:
            raise ValueError(f'others must be one of {OTHERS_MODES}, got {self.others!r}')
        if len(set(self.grasp_fingers)) != len(self.grasp_fingers) or any(
                not 0 <= i < 4 for i in self.grasp_fingers):
            raise ValueError('grasp_fingers must be distinct indices in 0..3, '
                             f'got {self.grasp_fingers!r}')

    @property
    def duration(self) -> float:
        """Time at which the fingers are back at rest [s]."""
        return self.t_start + self.t_close + self.t_hold + self.t_open


def _profile(t: np.ndarray, p: GraspProfile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scalar profile s(t) and its first two time derivatives, vectorised over t."""
    t = np.asarray(t, dtype=float)
    s = np.zeros_like(t)
    sd = np.zeros_like(t)
    sdd = np.zeros_like(t)
    t1 = p.t_start
    t2 = t1 + p.t_close
    t3 = t2 + p.t_hold
    t4 = t3 + p.t_open

    closing = (t >= t1) & (t < t2)
    w = math.pi / p.t_close
    tau = t[closing] - t1
    s[closing] = 0.5 * (1.0 - np.cos(w * tau))          # s = (1 − cos ωτ)/2
    sd[closing] = 0.5 * w * np.sin(w * tau)              # ṡ = ω sin(ωτ)/2
    sdd[closing] = 0.5 * w * w * np.cos(w * tau)         # s̈ = ω² cos(ωτ)/2

    s[(t >= t2) & (t < t3)] = 1.0

    opening = (t >= t3) & (t < t4)
    w = math.pi / p.t_open
    tau = t[opening] - t3
    s[opening] = 0.5 * (1.0 + np.cos(w * tau))          # s = (1 + cos ωτ)/2
    sd[opening] = -0.5 * w * np.sin(w * tau)
    sdd[opening] = -0.5 * w * w * np.cos(w * tau)
    return s, sd, sdd


@dataclass(frozen=True)
class ReferenceSample:
    """Reference positions, velocities, accelerations: arrays (..., n_fingers, d) in SI."""

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray


@dataclass(frozen=True)
class GraspTrajectory:
    """The grasp reference for every finger, in each finger's base frame (X side, Y grasp).

    Args:
        rest: (n_fingers, 2) or (n_fingers, 3) rest tip positions [m]; the first ``dim`` are used.
        profile: timing and geometry.
        dim: the tips' task dimension d: 2 plans in (X, Y), 3 in (X, Y, Z).

    Raises:
        ValueError: a rest of the wrong shape or not finite, grasp fingers out of range, or a
            ``direction`` / ``close_path`` whose values are not ``dim`` per point.
    """

    rest: np.ndarray
    profile: GraspProfile = field(default_factory=GraspProfile)
    dim: int = 2

    def __post_init__(self) -> None:
        rest = np.asarray(self.rest, dtype=float)
        if self.dim not in (2, 3):
            raise ValueError(f'dim must be 2 or 3, got {self.dim!r}')
        if rest.ndim != 2 or rest.shape[1] not in (2, 3) or rest.shape[0] < 1 or (
                rest.shape[1] < self.dim):
            raise ValueError(f'rest must have shape (n_fingers, 2 or 3) with at least dim = '
                             f'{self.dim} columns, got {rest.shape}')
        if not np.all(np.isfinite(rest)):
            raise ValueError('rest contains non-finite values')
        if any(i >= rest.shape[0] for i in self.profile.grasp_fingers):
            raise ValueError(
                f'grasp_fingers {self.profile.grasp_fingers} out of range for '
                f'{rest.shape[0]} fingers')
        p = self.profile
        if p.direction is not None and len(p.direction) != self.dim:
            raise ValueError(f'direction must have {self.dim} values (the task dimension), got '
                             f'{len(p.direction)}')
        path = None
        if p.close_path is not None:
            if len(p.close_path) % self.dim:
                raise ValueError(f'close_path must hold {self.dim} values per waypoint (the task '
                                 f'dimension), got {len(p.close_path)} values')
            path = _path_spline(np.reshape(p.close_path, (-1, self.dim)))
        object.__setattr__(self, 'rest', rest[:, :self.dim].copy())
        object.__setattr__(self, '_path', path)

    @property
    def direction(self) -> np.ndarray:
        """(d,) the unit direction the grasping fingers close along (+Y unless given)."""
        if self.profile.direction is not None:
            return np.asarray(self.profile.direction)
        u = np.zeros(self.dim)
        u[1] = 1.0
        return u

    @property
    def n_fingers(self) -> int:
        return self.rest.shape[0]

    @property
    def directions(self) -> np.ndarray:
        """(n_fingers, d) displacement of each finger at s = 1 [m] (along ``close_path``: its
        last waypoint)."""
        p = self.profile
        d = np.zeros((self.n_fingers, self.dim))
        if p.direction is None:                 # +Y: the hand's arithmetic
            if p.others == 'open':
                d[:, 1] = -p.open_distance
            for i in p.grasp_fingers:
                d[i, :2] = (p.side_distance, self.travel(i))
        else:
            u = self.direction
            if p.others == 'open':
                d[:] = -p.open_distance * u
            for i in p.grasp_fingers:
                d[i] = self.travel(i) * u
                d[i, 0] += p.side_distance
        if self._path is not None:
            for i in p.grasp_fingers:
                d[i] = self._path(1.0)
        return d

    def travel(self, finger: int) -> float:
        """How far grasping finger ``finger`` closes along ``direction`` (+Y unless given) [m]."""
        p = self.profile
        if p.close_to is None:
            return p.close_distance
        if p.direction is None:
            return p.close_to - float(self.rest[finger, 1])
        return p.close_to - float(self.rest[finger] @ self.direction)

    def sample(self, t) -> ReferenceSample:
        """Reference at time(s) t [s] (scalar or (T,)); arrays (n, 2) or (T, n, 2)."""
        t_arr = np.asarray(t, dtype=float)
        if not np.all(np.isfinite(t_arr)):
            raise ValueError('t contains non-finite values')
        s, sd, sdd = _profile(np.atleast_1d(t_arr), self.profile)
        d = self.directions
        pos = self.rest + s[:, None, None] * d          # p_d = p_rest + s d
        vel = sd[:, None, None] * d                     # ṗ_d = ṡ d
        acc = sdd[:, None, None] * d                    # p̈_d = s̈ d
        if self._path is not None:                      # the grasping fingers along P(s)
            path, slope, bend = self._path(s), self._path(s, 1), self._path(s, 2)
            for i in self.profile.grasp_fingers:
                pos[:, i] = self.rest[i] + path                                 # p_rest + P(s)
                vel[:, i] = slope * sd[:, None]                                 # P'(s) ṡ
                acc[:, i] = bend * (sd * sd)[:, None] + slope * sdd[:, None]    # P'' ṡ² + P' s̈
        if t_arr.ndim == 0:
            pos, vel, acc = pos[0], vel[0], acc[0]
        return ReferenceSample(pos, vel, acc)

    def peak_excursion(self) -> np.ndarray:
        """(n_fingers,) largest distance of the reference from the rest pose [m]."""
        if self._path is None:
            return np.linalg.norm(self.directions, axis=1)
        out = np.linalg.norm(self.directions, axis=1)
        far = float(np.linalg.norm(self._path(np.linspace(0.0, 1.0, 201)), axis=1).max())
        out[list(self.profile.grasp_fingers)] = far
        return out

    def free_space(self, t) -> np.ndarray:
        """(T, n_fingers) bool: True where the reference keeps a finger clear of the cube.

        A grasping finger is in free space while its reference travel along +Y (``direction``)
        stays below its travel to the cube face less ``contact_margin`` (the face:
        ``contact_distance`` from rest, or with ``close_to`` the squeeze before the end); the other
        fingers never touch the cube. Along ``close_path`` the travel is the path's projection on
        ``direction``.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s, _, _ = _profile(t, self.profile)
        p = self.profile
        mask = np.ones((t.size, self.n_fingers), dtype=bool)
        for i in p.grasp_fingers:
            travel = self.travel(i)
            face = (p.contact_distance if p.close_to is None
                    else p.contact_distance + travel - p.close_distance)
            along = s * travel if self._path is None else self._path(s) @ self.direction
            mask[:, i] = along < face - p.contact_margin
        return mask


def _path_spline(points: np.ndarray) -> CubicSpline:
    """P(σ), σ ∈ [0, 1]: the natural cubic spline from the rest (0) through ``points`` (k, d),
    parameterised by normalised chord length.

    Raises:
        ValueError: two consecutive waypoints coincide (no chord to parameterise by).
    """
    knots = np.vstack([np.zeros((1, points.shape[1])), points])
    chords = np.linalg.norm(np.diff(knots, axis=0), axis=1)
    if np.any(chords <= 1e-9):
        raise ValueError('close_path: consecutive waypoints (the rest, 0, first) must differ')
    sigma = np.concatenate([[0.0], np.cumsum(chords)]) / chords.sum()
    return CubicSpline(sigma, knots, bc_type='natural' if len(knots) > 2 else 'not-a-knot')
