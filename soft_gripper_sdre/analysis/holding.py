"""Where the learned model can be held still, and with what input: the closed-loop check's move
(:mod:`~soft_gripper_sdre.analysis.loop_settings`) goes no farther than the model holds with
:data:`HOLD_SHARE` of the input range, the rest being the feedback's.

ẋ = A(x)x + G(x)u is affine in u, so at rest at a displacement p (x = [p, 0]) the input that
holds the model still solves G₂(x) u = −(A(x)x)₂ (d equations, m unknowns), with G₂'s columns
read off the model's ẋ as the change per unit of each input (:func:`hold_torques`).

A finger with fewer inputs than tip coordinates (m < d: one chamber, a planar tip) holds still
only on a curve (m = 1) or a surface of its task space: the equilibria under constant inputs,
p(u) with A₂₁(p) p + G₂(p) u = 0 (:func:`equilibrium_curve`, followed by continuation as u sweeps
the bounds). A move off it cannot be held by any input, so the check's move (and the trajectory
node's ``close_path``) follows the curve.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from soft_gripper_sdre.analysis import model_fitness
from soft_gripper_sdre.analysis.data_facts import DataFacts
from soft_gripper_sdre.sim.shape import InputBounds, ShapeError

#: the check's move holds still with at most this share of the input range (the rest is the
#: feedback's)
HOLD_SHARE = 0.5
#: displacements tried for the holdable travel, as shares of the reach's travel
HOLD_GRID = 40
#: points of the equilibrium curve over the bounds (:func:`equilibrium_curve`)
CURVE_POINTS = 200
#: Newton's iterations and tolerance [m/s²] at each point of the curve
NEWTON_ITERATIONS = 30
NEWTON_TOL = 1e-9
#: halvings of a Newton step that does not lower the residual
NEWTON_HALVINGS = 8
#: halvings of the input's step where the curve's next equilibrium is not found from the last
CONTINUATION_HALVINGS = 4
#: past a fold, Newton starts this many of the curve's last steps ahead (:func:`_past_fold`)
FOLD_STEPS = (2, 4, 8, 16, 32, 64)
#: the snap past a fold is kept when it goes within 45° of the curve's last step and is at most
#: this many times the jump allowed between neighbouring points
FOLD_ALIGN = math.cos(math.radians(45.0))
FOLD_JUMP = 3.0
#: finite-difference step of the curve's Jacobian [m]
JACOBIAN_STEP = 1e-6
#: an input within this share of its range outside a bound still counts as within it (rounding)
AT_BOUND = 1e-9


def input_map(model, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At rest at the displacements ``points`` (N, d): the free acceleration (A(x)x)₂ (N, d) and
    the input map G₂(x) (N, d, m), read off the model's ẋ (affine in u)."""
    shape = model_fitness.model_shape(model)
    d, m = shape.d, shape.m
    points = np.asarray(points, dtype=float).reshape(-1, d)
    n = len(points)
    x = np.zeros((n, shape.n_state))
    x[:, :d] = points
    free = model_fitness.xdot(model, x, np.zeros((n, m)))[:, d:]
    G2 = np.stack([model_fitness.xdot(model, x, np.tile(e, (n, 1)))[:, d:] - free
                   for e in np.eye(m)], axis=2)
    return free, G2


def hold_torques(model, points: np.ndarray) -> np.ndarray:
    """(N, m) inputs that hold the learned model still at the displacements ``points`` (N, d)
    from its rest: u = −G₂(x)⁺ (A(x)x)₂ (the least-squares input: exact where G₂ has rank d, the
    nearest acceleration to zero where m < d), from ẋ = A(x)x + G(x)u being affine in u."""
    free, G2 = input_map(model, points)
    return -np.stack([np.linalg.lstsq(g, f, rcond=None)[0] for g, f in zip(G2, free)])


def actuator_bounds(facts: DataFacts, m: int) -> InputBounds:
    """The bounds the actuators deliver: ``facts.bounds``, else ±``facts.torque_limit`` on each
    of the ``m`` inputs."""
    return facts.bounds if facts.bounds is not None else InputBounds.symmetric(
        facts.torque_limit, m)


def loop_bounds(facts: DataFacts, m: int) -> InputBounds:
    """The bounds the loop's law runs within, in the model's input units: the actuators'
    (:func:`actuator_bounds`), through the fingers' input gains when the facts have them
    (:meth:`~soft_gripper_sdre.sim.shape.InputBounds.through_gains`: the commands every finger
    delivers)."""
    bounds = actuator_bounds(facts, m)
    return bounds if not facts.input_gains else bounds.through_gains(facts.input_gains.values())


def hold_bounds(bounds: InputBounds, share: float = HOLD_SHARE) -> InputBounds:
    """``share`` of each input's range about its rest value (:attr:`InputBounds.rest`): the
    inputs the check's move may take to hold still."""
    rest = bounds.rest
    lo, hi = rest + share * (bounds.lower - rest), rest + share * (bounds.upper - rest)
    # an input whose rest is its bound keeps the bound itself on that side
    return InputBounds(np.where(lo < hi, lo, bounds.lower), np.where(lo < hi, hi, bounds.upper))


def holdable_travel(model, facts: DataFacts) -> float:
    """The largest displacement along ``facts.unit``, up to ``facts.travel``, that every smaller
    one included the model holds with :data:`HOLD_SHARE` of the loop's input range
    (:func:`loop_bounds`: ±``facts.torque_limit`` when ``facts.bounds`` is None)."""
    lengths = facts.travel * np.arange(1, HOLD_GRID + 1) / HOLD_GRID
    u = hold_torques(model, np.outer(lengths, facts.unit))
    bounds = loop_bounds(facts, u.shape[1])
    if facts.bounds is None:
        need = np.abs(u).max(axis=1)
        over = np.flatnonzero(~(need <= HOLD_SHARE * bounds.upper[0]))   # NaN counts as over
    else:
        box = hold_bounds(bounds)
        tol = AT_BOUND * (box.upper - box.lower)          # rounding at a one-sided input's rest
        inside = np.all((u >= box.lower - tol) & (u <= box.upper + tol), axis=1)   # NaN: over
        over = np.flatnonzero(~inside)
    if not over.size:
        return facts.travel
    return float(lengths[over[0] - 1]) if over[0] > 0 else 0.0


@dataclass(frozen=True)
class EquilibriumCurve:
    """The model's equilibria p(u) under constant inputs u swept from their rest value toward
    ``u_end`` within the bounds (:func:`equilibrium_curve`)."""

    inputs: np.ndarray            # (K, m) the inputs, from the rest value on
    points: np.ndarray            # (K, d) the equilibria relative to the model's rest [m]

    @property
    def arc(self) -> np.ndarray:
        """(K,) arc length along the curve from rest [m]."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points, axis=0),
                                                               axis=1))])

    def cut(self, length: float, n: int) -> np.ndarray:
        """(n, d) points evenly spaced by arc length from rest up to ``length`` along the curve
        (at most its whole length) [m]."""
        arc = self.arc
        s = np.linspace(0.0, min(length, float(arc[-1])), n)
        return np.stack([np.interp(s, arc, self.points[:, i])
                         for i in range(self.points.shape[1])], axis=1)

    def holdable_length(self, box: InputBounds) -> float:
        """The arc length [m] up to which every input of the curve lies within ``box``."""
        tol = AT_BOUND * (box.upper - box.lower)
        inside = np.all((self.inputs >= box.lower - tol) & (self.inputs <= box.upper + tol),
                        axis=1)
        out = np.flatnonzero(~inside)
        return float(self.arc[out[0] - 1] if out.size and out[0] > 0 else
                     (0.0 if out.size else self.arc[-1]))


def _equilibrium(model, u: np.ndarray, p0: np.ndarray) -> np.ndarray | None:
    """The equilibrium p near ``p0`` under the constant input ``u``: Newton on
    (A(x)x + G(x)u)₂ = 0 at x = [p, 0] with a finite-difference Jacobian, each step halved until
    the residual falls (the learned networks are piecewise linear, and a full step across a
    kink can cycle); None when it does not converge."""
    d = len(p0)
    p = np.array(p0, dtype=float)

    def f(points):
        free, G2 = input_map(model, points)
        return free + np.einsum('nij,j->ni', G2, u)

    r = f(p[None])[0]
    for _ in range(NEWTON_ITERATIONS):
        if not np.all(np.isfinite(r)):
            return None
        norm = np.linalg.norm(r)
        if norm < NEWTON_TOL:
            return p
        J = (f(p + JACOBIAN_STEP * np.eye(d)) - r).T / JACOBIAN_STEP
        try:
            step = np.linalg.solve(J, r)
        except np.linalg.LinAlgError:
            return None
        for _ in range(NEWTON_HALVINGS):
            trial = p - step
            r_trial = f(trial[None])[0]
            if np.linalg.norm(r_trial) < norm:
                break
            step = 0.5 * step
        else:
            break                               # no step lowers the residual: stuck
        p, r = trial, r_trial
    return p if np.linalg.norm(r) < 1e3 * NEWTON_TOL else None


def _continued(model, u0: np.ndarray, u1: np.ndarray, p0: np.ndarray,
               halvings: int = CONTINUATION_HALVINGS) -> np.ndarray | None:
    """The equilibrium under ``u1`` continued from ``p0``, the one under ``u0``: Newton from
    ``p0``, or through the input halfway when that fails (a steep stretch of the curve, where
    the equilibrium moves far for a small change of input), ``halvings`` deep; None when lost."""
    p = _equilibrium(model, u1, p0)
    if p is not None or halvings == 0:
        return p
    mid = 0.5 * (u0 + u1)
    p = _continued(model, u0, mid, p0, halvings - 1)
    return None if p is None else _continued(model, mid, u1, p, halvings - 1)


def _past_fold(model, u: np.ndarray, p: np.ndarray, tangent: np.ndarray) -> np.ndarray | None:
    """The equilibrium under ``u`` past a fold of the learned statics (the one near ``p`` is
    lost and the curve goes on farther along): Newton from points ahead of ``p`` along the
    curve's last step ``tangent``, 2 to 64 steps out; None when none converges."""
    for k in FOLD_STEPS:
        found = _equilibrium(model, u, p + k * tangent)
        if found is not None:
            return found
    return None


def equilibrium_curve(model, bounds: InputBounds, axis: np.ndarray,
                      points: int = CURVE_POINTS) -> EquilibriumCurve:
    """The curve of the learned model's equilibria under constant inputs within ``bounds``: the
    inputs swept along a straight line from their rest value (:attr:`InputBounds.rest`) to the
    bounds, in the input direction whose static displacement at rest, −A₂₁(0)⁻¹ G₂(0) w, points
    most along ``axis`` (d,) (the way the data moved most; for one input: toward the bound on
    ``axis``' side, the only side a one-sided input has). Each equilibrium solves
    A₂₁(p) p + G₂(p) u = 0 by Newton from the one before (through smaller input steps where the
    curve is steep, and from points ahead along it past a fold of the learned statics); the
    curve ends where an equilibrium is lost (no convergence, a jump of more than a tenth of the
    curve so far plus 1 mm; past a fold, a snap that leaves the curve's way or is longer than
    :data:`FOLD_JUMP` times that).

    Raises:
        ShapeError: ``bounds`` has another number of inputs than the model, or ``axis`` another
            length than its task dimension.
    """
    shape = model_fitness.model_shape(model)
    d, m = shape.d, shape.m
    axis = np.asarray(axis, dtype=float).reshape(-1)
    if bounds.m != m:
        raise ShapeError(f'input bounds: {bounds.m} input(s) for a model of {m}')
    if axis.size != d:
        raise ShapeError(f'the curve\'s axis has {axis.size} values for a {d}-D tip')
    A = model.AG(np.zeros((1, shape.n_state)))[0][0]
    _, G2 = input_map(model, np.zeros((1, d)))
    compliance = -np.linalg.solve(A[d:, :d], G2[0])           # (d, m) static dp per unit input
    w = np.linalg.lstsq(compliance, axis, rcond=None)[0]
    rest = bounds.rest
    ends = []
    for sign in (1.0, -1.0):
        direction = sign * w
        # the longest step from rest along the direction that stays within the bounds
        with np.errstate(divide='ignore', invalid='ignore'):
            reach = np.where(direction > 0, (bounds.upper - rest) / direction,
                             np.where(direction < 0, (bounds.lower - rest) / direction, np.inf))
        t = float(np.min(reach))
        if np.isfinite(t) and t > 0:
            ends.append((float(axis @ (compliance @ direction)) * t, rest + t * direction))
    if not ends:
        return EquilibriumCurve(rest[None].copy(), np.zeros((1, d)))
    u_end = max(ends, key=lambda e: e[0])[1]
    us = rest + np.linspace(0.0, 1.0, points)[:, None] * (u_end - rest)
    p = np.zeros(d)
    start = _equilibrium(model, us[0], p)
    kept_u, kept_p = [us[0]], [start if start is not None else p]
    p = kept_p[0]
    for u in us[1:]:
        nxt, fold = _continued(model, kept_u[-1], u, p), False
        if nxt is None and len(kept_p) > 1:
            nxt, fold = _past_fold(model, u, p, p - kept_p[-2]), True
        if nxt is None:
            break
        so_far = float(np.linalg.norm(np.diff(np.array(kept_p), axis=0), axis=1).sum())
        jump, allowed = nxt - p, 0.1 * so_far + 1e-3
        if fold:
            # a snap past a fold goes on the way the curve went: a jump along it, however far
            # within FOLD_JUMP times the usual bound, is the same curve
            tangent = p - kept_p[-2]
            along = float(jump @ tangent) >= FOLD_ALIGN * float(np.linalg.norm(jump)
                                                                * np.linalg.norm(tangent))
            if not along or np.linalg.norm(jump) > FOLD_JUMP * allowed:
                break
        elif np.linalg.norm(jump) > allowed:
            break
        kept_u.append(u)
        kept_p.append(nxt)
        p = nxt
    return EquilibriumCurve(np.array(kept_u), np.array(kept_p) - kept_p[0])
