"""Sampling a published reference horizon (cubic Hermite) against the grasp trajectory itself."""
import numpy as np
import pytest

from soft_gripper_sdre.control.horizon import sample_horizon, sample_plan
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory

NS = 1_000_000_000
REST = np.array([[0.0, -0.002], [0.001, -0.002], [0.0, -0.002], [0.0, 0.0]])


def grid_horizon(traj, t0_ns, t1_ns, step_ns):
    times = np.arange(t0_ns, t1_ns + 1, step_ns, dtype=np.int64)
    ref = traj.sample(times / NS)
    return times, ref.pos, ref.vel, ref.acc


def test_hermite_on_a_5ms_grid_reproduces_the_trajectory_anywhere():
    traj = GraspTrajectory(REST, GraspProfile(side_distance=0.004, others='open'))
    end_ns = int(round((traj.profile.duration + 0.2) * NS))
    times, pos, vel, acc = grid_horizon(traj, 0, end_ns, 5_000_000)
    rng = np.random.default_rng(0)
    t_ns = np.concatenate([rng.integers(0, times[-1], 3000),
                           # around the phase changes, where the acceleration steps
                           np.array([0.5, 2.5, 3.5, 5.5]).repeat(50) * NS
                           + rng.integers(-6e6, 6e6, 200)])
    got = [sample_horizon(times, pos, vel, acc, int(t)) for t in t_ns]
    ref = traj.sample(t_ns / NS)
    np.testing.assert_allclose([g[0] for g in got], ref.pos, rtol=0, atol=1e-6)
    np.testing.assert_allclose([g[1] for g in got], ref.vel, rtol=0, atol=1e-4)
    assert np.max(np.abs(ref.vel)) > 0.01           # the comparison covered real motion


def test_grid_points_are_returned_exactly():
    traj = GraspTrajectory(REST, GraspProfile(t_start=0.0, t_close=0.1, others='open'))
    times, pos, vel, acc = grid_horizon(traj, 20_000_000, 120_000_000, 5_000_000)
    for k in (0, 7, len(times) - 1):
        p, v = sample_horizon(times, pos, vel, acc, int(times[k]))
        np.testing.assert_array_equal(p, pos[k])
        np.testing.assert_array_equal(v, vel[k])


def test_cubic_motion_is_interpolated_exactly():
    c = np.array([[0.01, -0.02], [0.3, 0.1], [-2.0, 1.5], [4.0, -3.0]])    # p = Σ c_i t^i
    t = np.array([0.0, 0.004, 0.011, 0.02])                               # uneven grid
    pos = (c[0] + t[:, None] * c[1] + t[:, None] ** 2 * c[2] + t[:, None] ** 3 * c[3])[:, None, :]
    vel = (c[1] + 2 * t[:, None] * c[2] + 3 * t[:, None] ** 2 * c[3])[:, None, :]
    acc = (2 * c[2] + 6 * t[:, None] * c[3])[:, None, :]
    times = np.round(t * NS).astype(np.int64)
    for tq in (0.001, 0.0075, 0.0199):
        p, v = sample_horizon(times, pos, vel, acc, int(round(tq * NS)))
        np.testing.assert_allclose(p[0], c[0] + tq * c[1] + tq**2 * c[2] + tq**3 * c[3],
                                   rtol=0, atol=1e-15)
        np.testing.assert_allclose(v[0], c[1] + 2 * tq * c[2] + 3 * tq**2 * c[3],
                                   rtol=0, atol=1e-13)


def test_a_one_point_horizon_is_sampled_at_its_point_only():
    pos, vel, acc = np.ones((1, 2, 2)), np.full((1, 2, 2), 0.5), np.zeros((1, 2, 2))
    p, v = sample_horizon(np.array([7]), pos, vel, acc, 7)
    np.testing.assert_array_equal(p, pos[0])
    np.testing.assert_array_equal(v, vel[0])
    with pytest.raises(ValueError, match='outside the horizon'):
        sample_horizon(np.array([7]), pos, vel, acc, 8)


@pytest.mark.parametrize('t_ns', [19_999_999, 40_000_001])
def test_times_outside_the_horizon_raise(t_ns):
    traj = GraspTrajectory(REST)
    times, pos, vel, acc = grid_horizon(traj, 20_000_000, 40_000_000, 5_000_000)
    with pytest.raises(ValueError, match='outside the horizon'):
        sample_horizon(times, pos, vel, acc, t_ns)


def test_mismatched_shapes_raise():
    times = np.array([0, 5, 10])
    good = np.zeros((3, 4, 2))
    for pos, vel, acc in ((np.zeros((2, 4, 2)), good, good), (good, np.zeros((3, 3, 2)), good),
                          (good, good, np.zeros((3, 4, 3)))):
        with pytest.raises(ValueError, match=r'\(h, n, 2\)'):
            sample_horizon(times, pos, vel, acc, 5)
    with pytest.raises(ValueError, match=r'\(h, n, 2\)'):
        sample_horizon(np.array([], dtype=np.int64), np.zeros((0, 4, 2)), np.zeros((0, 4, 2)),
                       np.zeros((0, 4, 2)), 0)


def test_acceleration_on_request_is_the_derivative_of_the_velocity_interpolant():
    """Cubic motion: the acceleration is linear, so dv/dt of the (exact) velocity Hermite is exact
    between points and the grid values at the points; without the flag the call is unchanged."""
    c = np.array([[0.01, -0.02], [0.3, 0.1], [-2.0, 1.5], [4.0, -3.0]])
    t = np.array([0.0, 0.004, 0.011, 0.02])
    pos = (c[0] + t[:, None] * c[1] + t[:, None] ** 2 * c[2] + t[:, None] ** 3 * c[3])[:, None, :]
    vel = (c[1] + 2 * t[:, None] * c[2] + 3 * t[:, None] ** 2 * c[3])[:, None, :]
    acc = (2 * c[2] + 6 * t[:, None] * c[3])[:, None, :]
    times = np.round(t * NS).astype(np.int64)
    for tq in (0.001, 0.0075, 0.0199):
        p, v, a = sample_horizon(times, pos, vel, acc, int(round(tq * NS)), with_acc=True)
        np.testing.assert_allclose(a[0], 2 * c[2] + 6 * tq * c[3], rtol=0, atol=1e-9)
        assert len(sample_horizon(times, pos, vel, acc, int(round(tq * NS)))) == 2
    for k in range(len(t)):
        np.testing.assert_allclose(sample_horizon(times, pos, vel, acc, int(times[k]),
                                                  with_acc=True)[2],
                                   acc[k], rtol=0, atol=1e-9)
    one = sample_horizon(times[:1], pos[:1], vel[:1], acc[:1], int(times[0]), with_acc=True)
    np.testing.assert_array_equal(one[2], acc[0])


def test_a_whole_plan_samples_bit_for_bit_like_short_horizons_on_the_same_grid():
    """One plan of the whole grasp (ending at rest, held after it) samples like 0.1 s horizons on
    the same absolute grid published every 20 ms: every instant of a 10 s run, the grasp's 5.5 s
    and beyond, gives the very same floats."""
    traj = GraspTrajectory(REST, GraspProfile(side_distance=0.004, others='open'))
    step, horizon, every = 5_000_000, 100_000_000, 20_000_000
    end = -(-int(round(traj.profile.duration * NS)) // step) * step
    plan = grid_horizon(traj, 0, end, step)
    for t in range(0, 10 * NS, 1_000_000):
        stamp = t // every * every                          # the newest horizon's publishing stamp
        start = stamp // step * step
        h = grid_horizon(traj, start, start + (-(-(stamp + horizon - start) // step)) * step, step)
        for a, b in zip(sample_plan(*plan, t, with_acc=True), sample_horizon(*h, t, with_acc=True)):
            np.testing.assert_array_equal(a, b)


def test_a_plan_holds_its_last_point_after_its_end_and_raises_before_its_start():
    times = np.array([10, 20, 30], dtype=np.int64) * 1_000_000
    pos = np.arange(24, dtype=float).reshape(3, 4, 2)
    zeros = np.zeros_like(pos)
    for t in (30_000_000, 31_000_000, 45_500_000, 10**12):
        p, v, a = sample_plan(times, pos, zeros, zeros, t, with_acc=True)
        np.testing.assert_allclose(p, pos[-1], rtol=1e-15, atol=0)    # (the Hermite's rounding)
        assert not v.any() and not a.any()
    with pytest.raises(ValueError, match='outside the horizon'):
        sample_plan(times, pos, zeros, zeros, 9_999_999)
