"""Sample a reference horizon (points at absolute times) at any time inside it. No ROS.

The trajectory node publishes the grasp reference as points on an absolute time grid with
positions p, velocities v and accelerations a. Between the bracketing points t₀ ≤ t ≤ t₁
(h = t₁ − t₀, s = (t − t₀)/h) position and velocity are cubic Hermite interpolants,

    p(t) = h₀₀(s) p₀ + h₁₀(s) h v₀ + h₀₁(s) p₁ + h₁₁(s) h v₁
    v(t) = h₀₀(s) v₀ + h₁₀(s) h a₀ + h₀₁(s) v₁ + h₁₁(s) h a₁

    h₀₀ = 2s³ − 3s² + 1,  h₁₀ = s³ − 2s² + s,  h₀₁ = −2s³ + 3s²,  h₁₁ = s³ − s²

so each matches its value and slope at both points (velocity is the Hermite of v with slopes a,
one order more accurate than differentiating the position interpolant). The acceleration (on
request) is the time derivative of that velocity interpolant,

    a(t) = [h₀₀'(s) v₀ + h₀₁'(s) v₁] / h + h₁₀'(s) a₀ + h₁₁'(s) a₁
    h₀₀' = 6s² − 6s,  h₁₀' = 3s² − 4s + 1,  h₀₁' = −6s² + 6s,  h₁₁' = 3s² − 2s

(the Hermite's slopes are a₀, a₁ at the ends, so it is consistent with the sampled velocity). At a
grid point the sample is that point exactly.
"""
from __future__ import annotations

import numpy as np

NS = 1_000_000_000


def sample_horizon(times_ns: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                   t_ns: int, with_acc: bool = False) -> tuple[np.ndarray, ...]:
    """Reference position and velocity (and, with ``with_acc``, acceleration) at ``t_ns``.

    Args:
        times_ns: (h,) strictly increasing absolute point times [ns] (as
            :func:`~soft_gripper_sdre.nodes.conversions.msg_to_reference` guarantees; not
            re-checked).
        pos, vel, acc: (h, n, d) positions [m], velocities [m/s], accelerations [m/s²] of tips
            of task dimension d (2 or 3).
        t_ns: the sample time [ns], within ``[times_ns[0], times_ns[-1]]``.
        with_acc: also return the acceleration (the feedforward laws of
            :mod:`soft_gripper_sdre.control.laws`).

    Returns:
        (pos (n, d), vel (n, d)) at ``t_ns``; (pos, vel, acc (n, d)) with ``with_acc``.

    Raises:
        ValueError: ``t_ns`` is outside the horizon, or the arrays' shapes do not agree.
    """
    times_ns = np.asarray(times_ns)
    h = len(times_ns) if times_ns.ndim == 1 else 0
    pos, vel, acc = (np.asarray(a, dtype=float) for a in (pos, vel, acc))
    shapes = {a.shape for a in (pos, vel, acc)}
    if (h == 0 or len(shapes) != 1 or len(shape := shapes.pop()) != 3 or shape[0] != h
            or shape[2] not in (2, 3)):
        raise ValueError(f'times_ns must be (h,) and pos, vel, acc (h, n, 2) or (h, n, 3) alike; '
                         f'got {times_ns.shape}, {pos.shape}, {vel.shape}, {acc.shape}')
    t_ns = int(t_ns)
    t_first, t_last = int(times_ns[0]), int(times_ns[-1])
    if not t_first <= t_ns <= t_last:
        raise ValueError(f't_ns = {t_ns} is outside the horizon [{t_first}, {t_last}] ns')
    # interval j: times[j] <= t <= times[j+1]; the last point belongs to the last interval
    j = min(int(np.searchsorted(times_ns, t_ns, side='right')) - 1, h - 2)
    if j < 0:                                  # a one-point horizon sampled at its only point
        return (pos[0].copy(), vel[0].copy()) + ((acc[0].copy(),) if with_acc else ())
    t0, t1 = int(times_ns[j]), int(times_ns[j + 1])
    dt = (t1 - t0) / NS
    s = (t_ns - t0) / (t1 - t0)
    s2, s3 = s * s, s * s * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = (s3 - 2.0 * s2 + s) * dt
    h01 = -2.0 * s3 + 3.0 * s2
    h11 = (s3 - s2) * dt
    p = h00 * pos[j] + h10 * vel[j] + h01 * pos[j + 1] + h11 * vel[j + 1]
    v = h00 * vel[j] + h10 * acc[j] + h01 * vel[j + 1] + h11 * acc[j + 1]
    if not with_acc:
        return p, v
    d00, d10 = 6.0 * s2 - 6.0 * s, 3.0 * s2 - 4.0 * s + 1.0
    d01, d11 = -6.0 * s2 + 6.0 * s, 3.0 * s2 - 2.0 * s
    a = (d00 * vel[j] + d01 * vel[j + 1]) / dt + d10 * acc[j] + d11 * acc[j + 1]   # a = dv/dt
    return p, v, a


def sample_plan(times_ns: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                t_ns: int, with_acc: bool = False) -> tuple[np.ndarray, ...]:
    """:func:`sample_horizon` of a plan that holds its last point after its end.

    A plan ends at rest, and a run may go on beyond it: after the last point the reference is
    that point repeated on the plan's grid (the spacing of its last two points), sampled with the
    same Hermite formulas, so a sample there is exactly what a plan with those repeated points
    would give. Before the first point it raises as :func:`sample_horizon` does.
    """
    times_ns = np.asarray(times_ns)
    last = int(times_ns[-1]) if times_ns.ndim == 1 and len(times_ns) else None
    if last is None or int(t_ns) <= last:
        return sample_horizon(times_ns, pos, vel, acc, t_ns, with_acc)
    step = last - int(times_ns[-2]) if len(times_ns) > 1 else 1
    t0 = last + (int(t_ns) - last) // step * step
    rest = [np.repeat(np.asarray(a, dtype=float)[-1:], 2, axis=0) for a in (pos, vel, acc)]
    return sample_horizon(np.array([t0, t0 + step], dtype=np.int64), *rest, t_ns, with_acc)
