"""The controller's plan sample compiled with numba:
:func:`~soft_gripper_sdre.control.horizon.sample_plan` with the acceleration, the same arithmetic
in the same order, so its results are the same bits.
"""
from __future__ import annotations

from soft_gripper_sdre.control.kernels.cache import kernel

NS = 1_000_000_000


@kernel
def plan_sample(times_ns, pos, vel, acc, t_ns, p, v, a):
    """Reference position, velocity and acceleration (n, 2) of a plan at ``t_ns`` into ``p``,
    ``v``, ``a``: times_ns (h,) int64 strictly increasing, pos, vel, acc (h, n, 2) float64 (the
    plan as :func:`~soft_gripper_sdre.control.horizon.sample_plan` takes it; after its last point
    the plan holds that point on its last spacing). Returns False, writing nothing, when ``t_ns``
    is before the plan or the plan has fewer than two points (the Python function's cases)."""
    h = times_ns.shape[0]
    if h < 2 or t_ns < times_ns[0]:
        return False
    last = times_ns[h - 1]
    if t_ns <= last:
        j = min(_right(times_ns, t_ns) - 1, h - 2)
        k = j + 1
        t0, t1 = times_ns[j], times_ns[k]
    else:                                       # past the end: the last point, repeated
        step = last - times_ns[h - 2]
        t0 = last + (t_ns - last) // step * step
        t1 = t0 + step
        j = k = h - 1
    dt = (t1 - t0) / NS
    s = (t_ns - t0) / (t1 - t0)
    s2, s3 = s * s, s * s * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = (s3 - 2.0 * s2 + s) * dt
    h01 = -2.0 * s3 + 3.0 * s2
    h11 = (s3 - s2) * dt
    d00, d10 = 6.0 * s2 - 6.0 * s, 3.0 * s2 - 4.0 * s + 1.0
    d01, d11 = -6.0 * s2 + 6.0 * s, 3.0 * s2 - 2.0 * s
    for i in range(pos.shape[1]):
        for c in range(2):
            p[i, c] = (h00 * pos[j, i, c] + h10 * vel[j, i, c] + h01 * pos[k, i, c]
                       + h11 * vel[k, i, c])
            v[i, c] = (h00 * vel[j, i, c] + h10 * acc[j, i, c] + h01 * vel[k, i, c]
                       + h11 * acc[k, i, c])
            a[i, c] = ((d00 * vel[j, i, c] + d01 * vel[k, i, c]) / dt + d10 * acc[j, i, c]
                       + d11 * acc[k, i, c])
    return True


@kernel
def _right(times_ns, t_ns):
    """numpy.searchsorted(times_ns, t_ns, side='right')."""
    lo, hi = 0, times_ns.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if times_ns[mid] <= t_ns:
            lo = mid + 1
        else:
            hi = mid
    return lo
