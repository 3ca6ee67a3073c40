"""The grasp reference: continuity, analytic derivatives, phases."""
import numpy as np
import pytest

from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory

REST = np.array([[0.0, -0.002, 0.109], [0.001, -0.002, 0.109], [0.0, -0.002, 0.109],
                 [0.0, 0.0, 0.1]])


def test_starts_and_ends_at_rest_and_reaches_target():
    traj = GraspTrajectory(REST, GraspProfile(side_distance=0.004))
    p = traj.profile
    ref0 = traj.sample(0.0)
    np.testing.assert_array_equal(ref0.pos, REST[:, :2])
    closed = traj.sample(p.t_start + p.t_close + 0.5 * p.t_hold)
    np.testing.assert_allclose(closed.pos[0], REST[0, :2] + [0.004, p.close_distance])
    np.testing.assert_allclose(closed.pos[1], REST[1, :2])   # non-grasping finger holds
    end = traj.sample(p.duration + 1.0)
    np.testing.assert_allclose(end.pos, REST[:, :2])
    np.testing.assert_array_equal(end.vel, 0.0)


def test_derivatives_match_finite_differences():
    traj = GraspTrajectory(REST, GraspProfile(side_distance=0.003, others='open'))
    dt = 1e-5
    t = np.linspace(0.0, traj.profile.duration + 0.5, 3001)
    t = t[(np.abs(t - 0.5) > 2e-3) & (np.abs(t - 2.5) > 2e-3) & (np.abs(t - 3.5) > 2e-3)
          & (np.abs(t - 5.5) > 2e-3)]
    r, rp, rm = traj.sample(t), traj.sample(t + dt), traj.sample(t - dt)
    np.testing.assert_allclose((rp.pos - rm.pos) / (2 * dt), r.vel, atol=1e-7)
    np.testing.assert_allclose((rp.vel - rm.vel) / (2 * dt), r.acc, atol=1e-5)


def test_position_and_velocity_continuous_at_phase_changes():
    traj = GraspTrajectory(REST)
    p = traj.profile
    for t_switch in (p.t_start, p.t_start + p.t_close, p.t_start + p.t_close + p.t_hold,
                     p.duration):
        a, b = traj.sample(t_switch - 1e-9), traj.sample(t_switch + 1e-9)
        np.testing.assert_allclose(a.pos, b.pos, atol=1e-9)
        np.testing.assert_allclose(a.vel, b.vel, atol=1e-9)


def test_free_space_mask_excludes_contact_phase_of_grasping_fingers_only():
    prof = GraspProfile()
    traj = GraspTrajectory(REST, prof)
    t = np.arange(0.0, prof.duration, 1e-3)
    mask = traj.free_space(t)
    assert mask[:, 1].all() and mask[:, 3].all()
    closed = (t > prof.t_start + prof.t_close) & (t < prof.t_start + prof.t_close + prof.t_hold)
    assert not mask[closed, 0].any() and not mask[closed, 2].any()
    assert mask[t < prof.t_start + 0.5, 0].all()
    np.testing.assert_allclose(traj.peak_excursion()[[0, 1]], [prof.close_distance, 0.0])


def test_close_to_anchors_the_closed_pose_whatever_the_rest_and_moves_the_face_with_it():
    """Two grasping fingers resting 3 mm apart in Y close to the same point; each meets the cube
    face the same squeeze (close_distance − contact_distance) before the end of its travel."""
    rest = REST.copy()
    rest[2, 1] = rest[0, 1] - 0.003                     # finger 2 rests 3 mm further from the cube
    prof = GraspProfile(close_to=rest[0, 1] + 0.030)
    traj = GraspTrajectory(rest, prof)
    closed = traj.sample(prof.t_start + prof.t_close + 0.5 * prof.t_hold).pos
    np.testing.assert_allclose(closed[[0, 2], 1], prof.close_to)
    np.testing.assert_allclose([traj.travel(0), traj.travel(2)], [0.030, 0.033])
    np.testing.assert_allclose(traj.peak_excursion()[[0, 2]], [0.030, 0.033])
    t = np.arange(0.0, prof.duration, 1e-4)
    mask = traj.free_space(t)
    # the cube face stands at one Y for both: the squeeze before close_to; free space ends a margin
    # before the reference reaches it (compared away from that boundary, where rounding decides)
    clear_below = (prof.close_to - (prof.close_distance - prof.contact_distance)
                   - prof.contact_margin)
    y = traj.sample(t).pos[:, :, 1]
    for finger in (0, 2):
        far = np.abs(y[:, finger] - clear_below) > 1e-9
        np.testing.assert_array_equal(mask[far, finger], y[far, finger] < clear_below)
        assert mask[:, finger].any() and not mask[:, finger].all()
    # without close_to the same rests travel the same distance each
    plain = GraspTrajectory(rest, GraspProfile())
    assert plain.travel(0) == plain.travel(2) == GraspProfile().close_distance


@pytest.mark.parametrize('kwargs, match', [
    (dict(close_to=float('inf')), 'close_to'),
    (dict(t_close=0.0), 't_close'),
    (dict(t_start=-1.0), 't_start'),
    (dict(others='wave'), 'others'),
    (dict(grasp_fingers=(0, 0)), 'grasp_fingers'),
    (dict(close_distance=float('nan')), 'close_distance'),
])
def test_bad_profile_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GraspProfile(**kwargs)


def test_bad_rest_and_time_rejected():
    with pytest.raises(ValueError, match='rest'):
        GraspTrajectory(np.zeros((4, 4)))
    with pytest.raises(ValueError, match='non-finite'):
        GraspTrajectory(REST).sample(float('nan'))
