"""The controller's compiled plan sample gives the bits of horizon.sample_plan."""
import numpy as np

from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.control.kernels import plan_sample


def _plan(rng, points: int, n: int = 4, regular: bool = False):
    steps = np.full(points, 5_000_000) if regular else rng.integers(1, 9_000_000, points)
    times = (np.cumsum(steps) + 123_456_789).astype(np.int64)
    return times, *(rng.normal(size=(points, n, 2)) * scale for scale in (1e-2, 1e-1, 1.0))


def test_every_sample_is_bit_for_bit_sample_plan_within_at_and_after_the_plan():
    rng = np.random.default_rng(3)
    for points, regular in ((2, True), (3, False), (1201, True), (1201, False)):
        times, pos, vel, acc = _plan(rng, points, regular=regular)
        at = np.concatenate([times, times[:-1] + 1, times[1:] - 1,
                             rng.integers(times[0], times[-1] + 40_000_000, 3000)])
        out = np.empty((3, 4, 2))
        for t in at:
            assert plan_sample(times, pos, vel, acc, int(t), out[0], out[1], out[2])
            expected = sample_plan(times, pos, vel, acc, int(t), with_acc=True)
            for got, want in zip(out, expected):
                assert np.array_equal(got, want), (points, int(t))


def test_before_the_plan_or_with_one_point_it_leaves_the_case_to_sample_plan():
    rng = np.random.default_rng(4)
    times, pos, vel, acc = _plan(rng, 5)
    out = np.full((3, 4, 2), 7.0)
    assert not plan_sample(times, pos, vel, acc, int(times[0]) - 1, out[0], out[1], out[2])
    assert not plan_sample(times[:1], pos[:1], vel[:1], acc[:1], int(times[0]), out[0], out[1],
                           out[2])
    assert np.all(out == 7.0)
