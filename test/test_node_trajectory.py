"""The trajectory node over real DDS (loopback), launch-free: own Context, executor, test node."""
from pathlib import Path

from geometry_msgs.msg import PoseArray
from node_harness import FAST_GRASP
from node_harness import make_trajectory as make
import numpy as np
import pytest
from rosutil import overrides, ros_context, spin_until
import yaml

from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, TIP_POSITIONS
from soft_gripper_sdre.nodes.trajectory import PARAMS, TrajectoryNode

pytestmark = pytest.mark.ros

MS = 1_000_000
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'trajectory.yaml'
FAST = FAST_GRASP
REST = np.array([[0.001, -0.002, 0.109], [0.0, -0.003, 0.108], [-0.001, -0.002, 0.109],
                 [0.0, 0.001, 0.11]])


def send(executor, node, pub, msg) -> None:
    """Publish one tip message and spin until the node has handled it."""
    c = node.diag.counters
    before = c['tips'] + c['bad_message']
    pub.publish(msg)
    assert spin_until(executor, lambda: c['tips'] + c['bad_message'] > before, 5.0)


def tick(executor, node, probe, ns) -> None:
    """Publish /clock at ``ns`` and spin until the node has handled it."""
    before = node.diag.counters['ticks']
    probe.clock.publish(cv.clock_msg(ns))
    assert spin_until(executor, lambda: node.diag.counters['ticks'] > before, 5.0)


def references(executor, node, probe):
    got = probe.received[GRASP_REFERENCE]
    assert spin_until(executor, lambda: len(got) >= node.diag.counters['references'], 5.0)
    assert len(got) == node.diag.counters['references']
    return [cv.msg_to_reference(m, 4) for m in got]


def check_plan(plan, rest, origin=0, **profile):
    """The plan is the grasp from ``rest`` on the 5 ms grid from ``origin`` [ns] to its end (at
    rest), the same points at any origin."""
    stamp, times, pos, vel, acc = plan
    traj = GraspTrajectory(rest, GraspProfile(others='open', **profile))
    assert stamp == times[0] == origin
    np.testing.assert_array_equal(np.diff(times), 5 * MS)
    offsets = times - origin
    assert offsets[-2] < traj.profile.duration * cv.NS <= offsets[-1]
    ref = traj.sample(offsets / cv.NS)
    np.testing.assert_array_equal(pos, ref.pos)
    np.testing.assert_array_equal(vel, ref.vel)
    np.testing.assert_array_equal(acc, ref.acc)
    assert not vel[-1].any() and not acc[-1].any()                  # it ends at rest


@pytest.mark.parametrize('first', [0, 7])
def test_the_whole_grasp_is_planned_from_the_first_tips_which_are_then_no_longer_received(first):
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, **FAST)
        send(executor, node, pub, cv.tips_to_msg(first * MS, REST))
        refs = references(executor, node, probe)
        assert len(refs) == 1
        check_plan(refs[0], REST, origin=first * MS, **FAST)   # the plan starts at the first tips
        assert np.abs(refs[0][3]).max() > 0.01                       # the grasp really moves
        # the tip subscription is gone: the node receives nothing per control period
        assert spin_until(executor, lambda: node.sub is None, 5.0)
        for k in range(first + 1, first + 20):
            pub.publish(cv.tips_to_msg(k * MS, REST + 0.001))
            tick(executor, node, probe, k * MS)
        assert node.diag.counters['tips'] == 1 and node.diag.counters['references'] == 1


def test_rest_samples_plans_from_the_mean_of_that_many_tips_at_the_last_ones_stamp():
    """A noisy driver's rest pose: the mean of ``rest_samples`` tip messages, the plan's origin
    the last one's stamp; a restart gathers them afresh."""
    rng = np.random.default_rng(3)
    noisy = [REST + 5e-5 * rng.standard_normal(REST.shape) for _ in range(8)]
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, rest_samples=4, reset_on_jump=0.01, **FAST)
        for k, tips in enumerate(noisy[:3]):
            send(executor, node, pub, cv.tips_to_msg((10 + k) * MS, tips))
        assert node.diag.counters['references'] == 0
        assert node.diag.values['rest_samples'] == '3 of 4'
        send(executor, node, pub, cv.tips_to_msg(13 * MS, noisy[3]))
        (plan,) = references(executor, node, probe)
        mean = np.mean(noisy[:4], axis=0)
        check_plan(plan, mean, origin=13 * MS, **FAST)
        # closer to the rest than a single message: a quarter of the noise's variance
        assert np.abs(mean - REST).max() < np.abs(noisy[0] - REST).max()
        assert spin_until(executor, lambda: node.sub is None, 5.0)
        for k in range(10, 40, 10):
            tick(executor, node, probe, k * MS)
        tick(executor, node, probe, 0)                               # restarted simulator
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 5.0)
        for k, tips in enumerate(noisy[4:]):
            send(executor, node, pub, cv.tips_to_msg((1 + k) * MS, tips))
        refs = references(executor, node, probe)
        assert len(refs) == 2
        check_plan(refs[1], np.mean(noisy[4:], axis=0), origin=0, **FAST)   # the new run's start


def test_bad_tip_messages_are_counted_and_a_restart_takes_a_new_rest_pose():
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, reset_on_jump=0.01, **FAST)
        nan = cv.tips_to_msg(0, REST)
        nan.poses[1].position.x = float('inf')
        for bad in (nan, cv.tips_to_msg(0, REST[:2])):
            send(executor, node, pub, bad)
        assert node.diag.counters['bad_message'] == 2 and node.diag.counters['references'] == 0
        send(executor, node, pub, cv.tips_to_msg(0, REST))
        for k in range(0, 40, 10):
            tick(executor, node, probe, k * MS)
        tick(executor, node, probe, 25 * MS)                         # a little back: not a restart
        assert node.diag.counters['resets'] == 0 and node.sub is None
        tick(executor, node, probe, 0)                               # restarted simulator
        assert node.diag.counters['resets'] == 1
        # listening again
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 5.0)
        moved = REST + 0.002
        send(executor, node, pub, cv.tips_to_msg(1 * MS, moved))
        refs = references(executor, node, probe)
        assert len(refs) == 2
        check_plan(refs[0], REST, **FAST)
        check_plan(refs[1], moved, origin=0, **FAST)       # from the new run's start, new rest
        assert spin_until(executor, lambda: node.sub is None, 5.0)


def test_close_to_plans_every_grasping_finger_to_the_same_closed_y():
    rest = REST.copy()
    rest[2, 1] = -0.005                                                # 3 mm further from the cube
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, close_to='0.0261', **FAST)
        send(executor, node, pub, cv.tips_to_msg(0, rest))
        (plan,) = references(executor, node, probe)
        check_plan(plan, rest, close_to=0.0261, **FAST)
        pos = plan[2]
        np.testing.assert_allclose(pos[:, [0, 2], 1].max(axis=0), 0.0261)
        # each its own travel
        np.testing.assert_allclose(np.ptp(pos[:, [0, 2], 1], axis=0), [0.0281, 0.0311])


@pytest.mark.parametrize('params, name', [
    (dict(horizon_step=0.0), 'horizon_step'),
    (dict(horizon_step=1e-4, t_hold=10.0), 'horizon_step'),
    (dict(t_close=0.0), 't_close'), (dict(t_start=-1.0), 't_start'),
    (dict(grasp_fingers=[0, 0]), 'grasp_fingers'), (dict(grasp_fingers=[0, 4]), 'grasp_fingers'),
    (dict(grasp_fingers=[1, 3], finger_names=['left', 'right']), 'grasp_fingers'),
    (dict(finger_names=['left', 'right']), 'grasp_fingers'), (dict(others='close'), 'others'),
    (dict(close_distance=float('nan')), 'close_distance'),
    (dict(grasp_fingers='0,2'), 'grasp_fingers'),
    (dict(rest_pose='0.0, 0.01'), 'rest_pose'), (dict(rest_pose='a b c d e f g h'), 'rest_pose'),
    (dict(rest_pose=' '.join(['nan'] * 8)), 'rest_pose'), (dict(close_to='near'), 'close_to'),
    (dict(close_to='0.5'), 'close_to'), (dict(close_to='nan'), 'close_to'),
    (dict(start_at='soon'), 'start_at'), (dict(start_at='-1'), 'start_at'),
    (dict(start_at='inf'), 'start_at'), (dict(tips_reliability='sometimes'), 'tips_reliability'),
    (dict(rest_samples=0), 'rest_samples'), (dict(rest_samples=1.5), 'rest_samples')])
def test_bad_parameters_fail_at_startup_naming_the_parameter(params, name):
    with ros_context() as (ctx, executor):
        with pytest.raises(ParameterError, match=name):
            TrajectoryNode(context=ctx, parameter_overrides=overrides(**params))


def test_defaults_are_the_grasp_profile_with_every_finger_moving():
    with ros_context() as (ctx, executor):
        node = TrajectoryNode(context=ctx)
        assert node.profile == GraspProfile(others='open')
    doc = yaml.safe_load(CONFIG.read_text())
    assert doc == {'/**/trajectory': {'ros__parameters': {p.name: p.default for p in PARAMS}}}


def test_runtime_changes_are_checked_and_refusals_keep_the_old_value():
    from rclpy.parameter import Parameter
    with ros_context() as (ctx, executor):
        node = TrajectoryNode(context=ctx)
        res = node.set_parameters([Parameter('reset_on_jump', value=-1.0)])[0]   # a negative period
        assert not res.successful and res.reason
        res = node.set_parameters([Parameter('others', value='wave')])[0]        # read-only mode
        assert not res.successful and 'others' in res.reason
        assert node.get_parameter('others').value == 'open' and node.jump_ns == 100 * MS
        assert node.set_parameters([Parameter('reset_on_jump', value=0.3)])[0].successful
        assert node.jump_ns == 300 * MS


def test_a_restart_mid_run_keeps_the_given_rest_pose():
    """With rest_pose the plan goes out at once, without a tip (they are bent mid-grasp), and again
    after a simulator restart; with start_at and without rest_pose, the first tips after start_at +
    t_start are flagged."""
    rest = ', '.join(repr(v) for v in REST[:, :2].ravel().tolist())
    bent = REST + 0.01
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, rest_pose=rest, **FAST)
        assert node.sub is None                                      # no tip subscription at all
        refs = references(executor, node, probe)
        assert len(refs) == 1
        check_plan(refs[0], REST, **FAST)
        tick(executor, node, probe, 500 * MS)
        tick(executor, node, probe, 0)                               # restarted simulator
        refs = references(executor, node, probe)
        assert len(refs) == 2 and node.sub is None
        check_plan(refs[1], REST, **FAST)
        assert node.diag.counters['late_start'] == 0
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, start_at='0', **FAST)
        send(executor, node, pub, cv.tips_to_msg(30 * MS, bent))
        assert node.diag.counters['late_start'] == 1
        check_plan(references(executor, node, probe)[0], bent, **FAST)


WALL_NS = 1_767_225_600_123_456_789          # a wall-time stamp [ns] (2026)


def diagnostics_value(node, key):
    return node.diag.values[key]


@pytest.mark.parametrize('reliability', ['reliable', 'best_effort'])
def test_a_wall_time_driver_gets_a_plan_starting_at_its_first_tips(reliability):
    """Tips stamped with wall time, from a driver with the sensor-data QoS when the node's tips are
    best effort: the plan starts at their stamp, and /diagnostics carries the origin exactly."""
    from rclpy.qos import qos_profile_sensor_data
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, tips_reliability=reliability, **FAST)
        if reliability == 'best_effort':
            pub = probe.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
            assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 10.0)
        send(executor, node, pub, cv.tips_to_msg(WALL_NS, REST))
        (plan,) = references(executor, node, probe)
        check_plan(plan, REST, origin=WALL_NS, **FAST)
        assert node.diag.counters['late_start'] == 0
        assert diagnostics_value(node, 'start_at') == '1767225600.123456789'
        # the same plan, bit for bit, as the one at origin 0 (times apart)
        zero = GraspTrajectory(REST, GraspProfile(others='open', **FAST)).sample(
            (plan[1] - WALL_NS) / cv.NS)
        np.testing.assert_array_equal(plan[2], zero.pos)


def test_a_restart_with_the_published_rest_pose_and_start_reproduces_the_plan():
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, **FAST)
        send(executor, node, pub, cv.tips_to_msg(WALL_NS, REST))
        (first,) = references(executor, node, probe)
        given = dict(rest_pose=diagnostics_value(node, 'rest_pose'),
                     start_at=diagnostics_value(node, 'start_at'))
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, **given, **FAST)
        assert node.sub is None                                      # no tips needed
        (again,) = references(executor, node, probe)
        for a, b in zip(first, again):
            np.testing.assert_array_equal(a, b)


def test_start_at_sets_the_origin_of_a_plan_from_the_first_tips():
    with ros_context() as (ctx, executor):
        node, probe, pub = make(ctx, executor, start_at='1767225600.5', **FAST)
        send(executor, node, pub, cv.tips_to_msg(WALL_NS, REST))
        (plan,) = references(executor, node, probe)
        check_plan(plan, REST, origin=1_767_225_600_500_000_000, **FAST)
