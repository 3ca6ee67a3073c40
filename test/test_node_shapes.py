"""The loop's messages and nodes for fingers unlike the hand: 3-D tips (d = 3) and one to four
inputs (m), over real DDS (loopback) where a node is involved."""
from node_harness import (
    FAST_GRASP,
    MS,
    TORQUE_LIMIT,
    commands,
    estimate,
    horizon,
    make_controller,
    make_estimator,
    make_trajectory,
    send_estimate,
)
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosutil import overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.tip_filter import make_kf
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, STATE_ESTIMATE
from soft_gripper_sdre.nodes.tracking_step import TrackingStep
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

NAMES = ('index', 'thumb')
SHAPES = [(3, 3), (2, 1), (3, 1), (2, 4)]


# -- messages ---------------------------------------------------------------------------------

@pytest.mark.parametrize('d, m', SHAPES)
def test_torque_commands_name_m_inputs_and_round_trip_fast_and_slow(d, m):
    rng = np.random.default_rng(m)
    u = rng.standard_normal((2, m))
    codec = cdr.torques_codec(NAMES, m)
    msg = cv.torques_to_msg(5 * MS, u, NAMES)
    assert list(msg.name) == [f'{f}/ax{k}' for f in NAMES for k in range(m)]
    assert cv.torque_names(NAMES, m) == list(msg.name)
    raw = codec.encode(5 * MS, u)
    assert deserialize_message(raw, JointState) == msg            # our bytes are rclpy's message
    for data in (raw, serialize_message(msg)):                    # read fast, as rclpy wrote it
        stamp, got = codec.decode(data)
        assert stamp == 5 * MS
        np.testing.assert_array_equal(got, u)
    assert codec.fallbacks == 0
    # another publisher's order goes the validating way, to the same values
    shuffled = cv.torques_to_msg(6 * MS, u, NAMES)
    order = np.arange(2 * m)[::-1]
    shuffled.name = [shuffled.name[i] for i in order]
    shuffled.effort = [shuffled.effort[i] for i in order]
    np.testing.assert_array_equal(codec.decode(serialize_message(shuffled))[1], u)
    np.testing.assert_array_equal(cv.msg_to_torques(shuffled, NAMES, m)[1], u)


def test_torque_commands_of_another_input_count_are_refused_naming_the_inputs():
    two = cv.torques_to_msg(0, np.zeros((2, 2)), NAMES)
    with pytest.raises(cv.MessageError, match=r"unknown names \['index/ax1', 'thumb/ax1'\]"):
        cv.msg_to_torques(two, NAMES, 1)
    one = cv.torques_to_msg(0, np.zeros((2, 1)), NAMES)
    with pytest.raises(cv.MessageError, match='missing names'):
        cv.msg_to_torques(one, NAMES, 2)
    with pytest.raises(cv.MessageError, match='torque_commands'):
        cdr.torques_codec(NAMES, 3).decode(serialize_message(two))
    with pytest.raises(ValueError, match="'index/ax2' is not a torque"):
        cv.effort_array_order(['index/ax2', 'index/ax0', 'thumb/ax0'], NAMES, 1)
    np.testing.assert_array_equal(
        cv.effort_array_order(['thumb/ax0', 'index/ax0'], NAMES, 1), [1, 0])


@pytest.mark.parametrize('d', [2, 3])
def test_state_estimates_carry_z_for_3d_tips(d):
    rng = np.random.default_rng(d)
    x = rng.standard_normal((2, 2 * d))
    codec = cdr.estimate_codec(NAMES, d)
    msg = cv.estimate_to_msg(9 * MS, x[:, :d], x[:, d:], NAMES)
    raw = codec.encode(9 * MS, x)
    assert deserialize_message(raw, MultiDOFJointTrajectory) == msg
    point = msg.points[0]
    z = [(t.translation.z, v.linear.z) for t, v in zip(point.transforms, point.velocities)]
    np.testing.assert_array_equal(z, x[:, [2, 5]] if d == 3 else np.zeros((2, 2)))
    for data in (raw, serialize_message(msg)):
        stamp, got = codec.decode(data)
        assert stamp == 9 * MS
        np.testing.assert_array_equal(got, x)
    # the fingers in another order: the validating way, then learned (adopted) and read fast
    swapped = cv.estimate_to_msg(10 * MS, x[::-1, :d], x[::-1, d:], NAMES[::-1])
    for _ in range(2):
        np.testing.assert_array_equal(codec.decode(serialize_message(swapped))[1], x)
    assert codec.fallbacks == 1
    bad = cv.estimate_to_msg(11 * MS, x[:, :d], x[:, d:], NAMES)
    bad.points[0].velocities[1].linear.z = float('nan')
    if d == 3:
        with pytest.raises(cv.MessageError, match='state_estimate contains NaN'):
            codec.decode(serialize_message(bad))
    else:                                   # a planar estimate does not read z
        np.testing.assert_array_equal(codec.decode(serialize_message(bad))[1], x)


def test_a_planar_estimate_ignores_z():
    x = np.array([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]])
    msg = cv.estimate_to_msg(0, x[:, :2], x[:, 2:], NAMES)
    msg.points[0].transforms[0].translation.z = float('nan')
    np.testing.assert_array_equal(cv.msg_to_estimate(msg, NAMES)[1], x)
    np.testing.assert_array_equal(cdr.estimate_codec(NAMES).decode(serialize_message(msg))[1], x)


@pytest.mark.parametrize('d', [2, 3])
def test_plans_carry_z_for_3d_tips_fast_and_slow(d):
    rng = np.random.default_rng(10 + d)
    h = 7
    offsets = 5 * MS * np.arange(h)
    pos, vel, acc = (rng.standard_normal((h, 2, d)) for _ in range(3))
    codec = PlanCodec(NAMES, d)
    msg = cv.reference_to_msg(3 * MS, offsets, pos, vel, acc, NAMES)
    raw = codec.encode(3 * MS, offsets, pos, vel, acc)
    assert deserialize_message(raw, MultiDOFJointTrajectory) == msg
    for data in (raw, serialize_message(msg)):
        stamp, times, p, v, a = codec.decode(data)
        assert stamp == 3 * MS and times.tolist() == (3 * MS + offsets).tolist()
        for got, want in ((p, pos), (v, vel), (a, acc)):
            np.testing.assert_array_equal(got, want)
    assert codec.fallbacks == 0
    slow = cv.msg_to_reference(msg, NAMES[::-1], d)        # another order: the validating way
    np.testing.assert_array_equal(slow[2], pos[:, ::-1])
    if d == 3:
        bad = cv.reference_to_msg(3 * MS, offsets, pos, vel, acc, NAMES)
        bad.points[4].accelerations[1].linear.z = float('inf')
        with pytest.raises(cv.MessageError, match='grasp_reference contains NaN or Inf'):
            codec.decode(serialize_message(bad))


def test_a_plan_codec_of_another_task_dimension_is_refused():
    with pytest.raises(ValueError, match='task dimension must be 2 or 3, got 4'):
        PlanCodec(NAMES, 4)


def test_3d_tips_are_published_with_z_and_planar_ones_with_z_zero():
    tips = np.array([[0.001, 0.002, 0.003], [0.004, 0.005, 0.006]])
    stamp, got = cv.msg_to_tips(cv.tips_to_msg(7, tips), 2)
    assert stamp == 7
    np.testing.assert_array_equal(got, tips)
    np.testing.assert_array_equal(cv.msg_to_tips(cv.tips_to_msg(7, tips[:, :2]), 2)[1][:, 2], 0.0)


# -- the estimator ----------------------------------------------------------------------------

@pytest.mark.ros
def test_estimator_filters_3d_tips_like_the_offline_3d_filter():
    rng = np.random.default_rng(4)
    p0 = np.array([[0.001, -0.002, 0.05], [0.0, 0.001, 0.06]])
    v = np.array([[0.02, -0.01, 0.03], [0.0, 0.015, -0.02]])
    steps, sigma = 250, 1e-6
    stamps = 5 * MS + MS * np.arange(steps)
    z = p0 + v * (stamps[:, None, None] - stamps[0]) / cv.NS
    z = z + rng.normal(size=z.shape) * sigma
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor, task_dim=3, finger_names=list(NAMES))
        got = probe.received[STATE_ESTIMATE]
        for k in range(steps):
            pub.publish(cv.tips_to_msg(int(stamps[k]), z[k]))
            assert spin_until(executor, lambda: len(got) == k + 1, 5.0)
        assert node.diag.values['task_dim'] == '3'
        est = [cv.msg_to_estimate(m, NAMES, 3) for m in got]
    kf = make_kf(1e-3, 1.0, 5e-5, 2, 'independent', 3)
    kf.reset(z[0])
    offline = [kf.x.copy()] + [kf.step(z[k]) for k in range(1, steps)]
    assert [s for s, _ in est] == stamps.tolist()
    x = np.array([e for _, e in est])
    np.testing.assert_array_equal(x, np.array(offline))
    assert x.shape == (steps, 2, 6)
    np.testing.assert_allclose(x[-1, :, 3:], v, atol=2e-3)        # Ż too, from zero velocity
    np.testing.assert_allclose(x[:, :, :3], z, atol=5 * sigma + 1e-5)


def test_the_3d_filter_is_three_independent_planar_axes():
    """The filter of 3-D tips gives on X, Y what the hand's planar filter gives, and on Z what
    that filter gives on an axis of Z measurements."""
    rng = np.random.default_rng(8)
    z = np.cumsum(rng.normal(size=(60, 2, 3)) * 1e-4, axis=0)
    three = make_kf(1e-3, 2.0, 1e-5, 2, d=3)
    xy, zz = make_kf(1e-3, 2.0, 1e-5, 2), make_kf(1e-3, 2.0, 1e-5, 2)
    three.reset(z[0])
    xy.reset(z[0, :, :2])
    zz.reset(z[0, :, [2, 0]].T)
    for k in range(1, 60):
        dt = None if k % 7 else 2.5e-3                  # the step of its own Δt too
        x3, x2, xz = three.step(z[k], dt=dt), xy.step(z[k, :, :2], dt=dt), zz.step(
            z[k, :, [2, 0]].T, dt=dt)
        np.testing.assert_allclose(x3[:, [0, 1, 3, 4]], x2, rtol=0, atol=1e-15)
        np.testing.assert_allclose(x3[:, [2, 5]], xz[:, [0, 2]], rtol=0, atol=1e-15)


@pytest.mark.ros
@pytest.mark.parametrize('params, needle', [
    (dict(task_dim=4), 'task_dim'), (dict(task_dim=1), 'task_dim'),
    (dict(task_dim='three'), 'task_dim')])
def test_estimator_refuses_a_bad_task_dim_naming_it(params, needle):
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError, match=needle):
            EstimatorNode(context=ctx, parameter_overrides=overrides(**params))


@pytest.mark.ros
def test_a_3d_estimator_refuses_tips_whose_z_is_not_finite():
    tips = np.array([[0.001, 0.002, 0.003], [0.004, 0.005, 0.006]])
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor, task_dim=3, finger_names=list(NAMES))
        bad = cv.tips_to_msg(MS, tips)
        bad.poses[1].position.z = float('nan')
        pub.publish(bad)
        assert spin_until(executor, lambda: node.diag.counters['bad_message'] == 1, 5.0)
        assert not probe.received[STATE_ESTIMATE]


# -- the trajectory node ----------------------------------------------------------------------

REST3 = np.array([[0.001, -0.002, 0.109], [0.0, -0.003, 0.108]])


def _plan(executor, node, probe, d):
    got = probe.received[GRASP_REFERENCE]
    assert spin_until(executor, lambda: len(got) == node.diag.counters['references'] == 1, 5.0)
    return cv.msg_to_reference(got[0], NAMES, d)


@pytest.mark.ros
def test_trajectory_node_plans_a_3d_grasp_along_its_direction():
    direction = np.array([0.0, 0.6, 0.8])
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(
            ctx, executor, finger_names=list(NAMES), grasp_fingers=[0, 1], task_dim=3,
            direction=[0.0, 3.0, 4.0], **FAST_GRASP)
        pub.publish(cv.tips_to_msg(0, REST3))
        stamp, times, pos, vel, acc = _plan(executor, node, probe, 3)
    assert pos.shape[1:] == (2, 3)
    traj = GraspTrajectory(REST3, GraspProfile(**FAST_GRASP, grasp_fingers=(0, 1),
                                               direction=(0.0, 3.0, 4.0), others='open'), 3)
    ref = traj.sample((times - stamp) / cv.NS)
    for got, want in ((pos, ref.pos), (vel, ref.vel), (acc, ref.acc)):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(pos[0], REST3)                       # from the 3-D rest
    closed = pos[np.argmax(np.linalg.norm(pos - REST3, axis=2).sum(axis=1))]
    expected = REST3 + 0.030 * direction + [FAST_GRASP['side_distance'], 0.0, 0.0]
    np.testing.assert_allclose(closed, expected, atol=1e-12)           # z moved: 24 mm
    np.testing.assert_allclose(pos[-1], REST3, atol=1e-15)


@pytest.mark.ros
def test_trajectory_node_closes_a_finger_along_its_close_path():
    """A one-input finger's tip reaches a curve: the plan goes from rest through the waypoints to
    the last one, smoothly (finite velocity and acceleration), and back."""
    path = np.array([[0.004, 0.002], [0.006, 0.006], [0.005, 0.010]])
    rest = REST3[:, :2]
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(
            ctx, executor, finger_names=list(NAMES), grasp_fingers=[0], others='hold',
            close_path=path.ravel().tolist(), horizon_step=0.001,
            **FAST_GRASP)
        pub.publish(cv.tips_to_msg(0, REST3))
        stamp, times, pos, vel, acc = _plan(executor, node, probe, 2)
    t = (times - stamp) / cv.NS
    moved = pos[:, 0] - rest[0]
    np.testing.assert_allclose(moved[0], 0.0, atol=1e-15)
    hold = (t >= 0.05) & (t < 0.06)                                     # closed: the last waypoint
    np.testing.assert_allclose(moved[hold], np.repeat(path[-1:], hold.sum(), 0), atol=1e-12)
    for point in path[:-1]:                                             # through every waypoint
        assert np.linalg.norm(moved - point, axis=1).min() < 2e-4
    np.testing.assert_array_equal(pos[:, 1], np.repeat(rest[1:], len(t), 0))    # the other holds
    assert np.all(np.isfinite(vel)) and np.all(np.isfinite(acc))
    # the velocity is the derivative of the position (no jump at a waypoint): each step's
    # displacement is the trapezoid of the velocities at its ends
    np.testing.assert_allclose(np.diff(pos[:, 0], axis=0) / np.diff(t)[:, None],
                               0.5 * (vel[1:, 0] + vel[:-1, 0]), atol=0.02 * np.abs(vel).max())
    np.testing.assert_allclose(pos[-1, 0], rest[0], atol=1e-15)


@pytest.mark.ros
@pytest.mark.parametrize('params, needle', [
    (dict(task_dim=4), 'task_dim'),
    (dict(direction=[0.0, 1.0, 0.0]), 'direction'),           # 3 values for a planar tip
    (dict(direction=[0.0, 0.0]), 'direction'),
    (dict(direction=[0.0, float('nan')]), 'direction'),
    (dict(direction='up'), 'direction'),
    (dict(task_dim=3, direction=[0.0, 1.0]), 'direction'),
    (dict(close_path=[0.001, 0.002, 0.003]), 'close_path'),   # not 2 per point
    (dict(close_path=[0.001, float('inf')]), 'close_path'),
    (dict(close_path=[0.0, 0.0, 0.001, 0.002]), 'close_path'),    # a first waypoint at rest
    (dict(close_path=['a', 'b']), 'close_path'),
    (dict(task_dim=3, rest_pose='0, 0, 0, 0, 0, 0, 0, 0'), 'rest_pose'),
])
def test_trajectory_node_refuses_bad_shape_parameters_naming_them(params, needle):
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError, match=needle):
            TrajectoryNode(context=ctx, parameter_overrides=overrides(**params))


def test_the_hand_plans_the_same_with_direction_plus_y_given():
    rest = REST3[:, :2]
    t = np.linspace(0.0, 6.0, 301)
    default = GraspTrajectory(rest, GraspProfile(grasp_fingers=(0,), side_distance=0.001,
                                                 others='open'))
    given = GraspTrajectory(rest, GraspProfile(grasp_fingers=(0,), side_distance=0.001,
                                               others='open', direction=(0.0, 2.0)))
    a, b = default.sample(t), given.sample(t)
    for x, y in ((a.pos, b.pos), (a.vel, b.vel), (a.acc, b.acc)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-18)
    np.testing.assert_array_equal(default.free_space(t), given.free_space(t))


# -- the controller ---------------------------------------------------------------------------

@pytest.fixture(scope='module')
def model():
    return SDCModel()


@pytest.mark.ros
def test_controller_with_symmetric_input_bounds_is_the_law_at_that_limit(model):
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    limit = 0.02
    offline = make_law('sdre_ff', model, Weights(**DEFAULT_WEIGHTS), limit)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, input_lower=[-0.02, -0.02], input_upper=[0.02, 0.02])
        assert node.diag.values['input_bounds'] == 'ax0 [-0.02, 0.02], ax1 [-0.02, 0.02]'
        assert node.diag.values['shape'] == 'd=2, m=2'
        ref_msg, ref_pos = horizon(rest, 0, close_mm=20.0)
        ref_pub.publish(ref_msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        for k in range(4):
            send_estimate(executor, node, est_pub, estimate(k * MS, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 4)
        for msg in commands(probe):
            u = cv.msg_to_torques(msg, 4)[1]
            zeros = np.zeros((4, 2))
            np.testing.assert_allclose(u, offline.compute(rest, zeros, ref_pos, zeros,
                                                          ref_acc=zeros).u, rtol=1e-9, atol=1e-12)
            assert np.abs(u).max() <= limit
        assert np.abs(u).max() == limit                         # 20 mm away: saturated
        assert node.diag.counters['saturated'] > 0


@pytest.mark.ros
@pytest.mark.parametrize('params, needle', [
    (dict(input_lower=[0.01]), '2 input(s); got 1 lower and 0 upper'),      # upper unset
    (dict(input_lower=[0.0], input_upper=[0.01]), '2 input(s); got 1 lower and 1 upper'),
    (dict(input_lower=[0.0, 0.0, 0.0], input_upper=[1.0, 1.0, 1.0]), '2 input(s)'),
    (dict(input_lower=[0.01, 0.0], input_upper=[0.01, 0.01]), 'input ax0: the lower bound'),
    (dict(input_lower=[0.0, float('nan')], input_upper=[1.0, 1.0]),
     "parameter 'input_lower': [0.0, nan] holds a value that is not finite"),
    (dict(input_lower='0, zero', input_upper=[1.0, 1.0]), "'input_lower'"),
    (dict(input_lower=0, input_upper=[1.0, 1.0]), '2 input(s); got 1 lower and 2 upper'),
    (dict(effort_topic='/efforts', effort_joints=['finger_0/ax2']), 'effort_joints'),
])
def test_controller_refuses_bad_input_bounds_naming_them(params, needle):
    """Checked against the model's inputs (the hand's model: m = 2) at start-up; the process then
    exits with status 2 naming them (test_node_cli.py)."""
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(**params))
    assert needle in str(info.value)


def test_a_command_outside_bounds_of_their_own_is_clipped_and_a_nonfinite_one_rests(model):
    """One-sided inputs: the step keeps the published command within [lower, upper] whatever the
    law gave (here the hand's PD law, bounded only by ±torque_limit, asked to move both ways)."""
    law = make_law('pd', model, Weights(**DEFAULT_WEIGHTS), TORQUE_LIMIT, n_fingers=2)
    bounds = InputBounds(np.array([0.0, 0.005]), np.array([0.03, 0.04]))
    step = TrackingStep(model, NAMES, FingerShape(2, 2), bounds)
    rest = np.repeat(model.rest_tip[None, :2], 2, 0)
    times = np.array([0, 5 * MS])
    for sign in (1.0, -1.0):
        target = rest + sign * np.array([[0.0, 0.02], [0.02, 0.0]])
        plan = _plan_of(times, target)
        x = np.hstack([rest, np.zeros((2, 2))])
        cmd = step.command(law, MS, x, plan)
        assert bounds.contains(cmd.u)
        assert cmd.clipped and not cmd.replaced
        assert not bounds.contains(cmd.out.u)                   # the law asked for more
        np.testing.assert_array_equal(cmd.u, bounds.clip(cmd.out.u))
    x = np.hstack([rest, np.full((2, 2), np.nan)])
    law.reset()
    cmd = step.command(law, 2 * MS, x, plan)
    assert bounds.contains(cmd.u) and np.isfinite(cmd.u).all()


def _plan_of(times, pos):
    from soft_gripper_sdre.control.command_gate import Plan
    h = len(times)
    p = np.repeat(pos[None], h, 0)
    return Plan(int(times[0]), int(times[-1]), times, p, np.zeros_like(p), np.zeros_like(p))


# -- markers ----------------------------------------------------------------------------------

def test_markers_draw_a_3d_reference_at_its_own_z():
    """A planar reference is drawn at its tip's height; a 3-D one where its z says."""
    from soft_gripper_sdre.nodes.markers import HandMarkers, decode
    from soft_gripper_sdre.sim.hand_description import hand_urdf
    names = list(cv.finger_names(4))
    markers = HandMarkers(hand_urdf(), names, range(4), with_references=True)
    q = np.zeros((4, 10))
    links = markers.kin.link_poses({f'{n}/joint_{j}': 0.0 for n in names for j in range(10)})

    def points(refs):
        msg = decode(markers.encode(0, q, None, refs))
        by_ns = {m.ns: m for m in msg.markers}
        return [np.array([[p.x, p.y, p.z] for p in by_ns[ns].points])
                for ns in ('tips', 'references')]

    tips, _ = points(None)
    step = np.array([0.0, 0.002, 0.001])
    local = np.array([links[f'{n}/base'][:3, :3].T @ (tips[i] - links[f'{n}/base'][:3, 3])
                      for i, n in enumerate(names)]) + step
    for refs, lift in ((local, step), (local[:, :2], step * [1, 1, 0])):
        _, drawn = points(refs)
        expected = np.array([links[f'{n}/base'][:3, :3] @ lift for n in names])
        np.testing.assert_allclose(drawn - tips, expected, atol=1e-12)
