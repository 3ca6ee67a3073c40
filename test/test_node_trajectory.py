"""The trajectory node over real DDS (loopback), launch-free: own Context, executor, test node."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from node_harness import MS, make_trajectory
from rosutil import overrides, ros_context, spin_until
from soft_gripper_sdre.control.horizon import sample_horizon
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE
from soft_gripper_sdre.nodes.trajectory import PARAMS, TrajectoryNode
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'trajectory.yaml'
#: a grasp short enough that 100 ms of sim time see every phase
FAST = dict(t_start=0.01, t_close=0.04, t_hold=0.01, t_open=0.03, side_distance=0.002)
REST = np.array([[0.001, -0.002, 0.109], [0.0, -0.003, 0.108], [-0.001, -0.002, 0.109], [0.0, 0.001, 0.11]])


def send(executor, node, pub, msg) -> None:
    """Publish one tip message and spin until the node has handled it."""
    c = node.diag.counters
    before = c['tips'] + c['bad_message'] + c['stale']
    pub.publish(msg)
    assert spin_until(executor, lambda: c['tips'] + c['bad_message'] + c['stale'] > before, 5.0)


def references(executor, node, probe):
    got = probe.received[GRASP_REFERENCE]
    assert spin_until(executor, lambda: len(got) >= node.diag.counters['references'], 5.0)
    assert len(got) == node.diag.counters['references']
    return [cv.msg_to_reference(m, 4) for m in got]


def run_tips(stamps_ms, **params):
    """Send tips at the given stamps (the first at REST, later ones displaced); return the
    references and the node's counters."""
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, **params)
        for i, k in enumerate(stamps_ms):
            send(executor, node, pub, cv.tips_to_msg(k * MS, REST + (0.0 if i == 0 else 0.001)))
        return references(executor, node, probe), dict(node.diag.counters)


@pytest.mark.parametrize('first, count', [(0, 5), (1, 6)])
def test_horizons_follow_the_sim_clock_and_the_grasp_from_the_first_rest_pose(first, count):
    stamps = list(range(first, first + 100))
    refs, counters = run_tips(stamps, **FAST)
    assert counters['references'] == count
    # published on the first message, then when the stamp reaches a multiple of 20 ms
    expected_at = [first] + [k for k in stamps[1:] if k % 20 == 0]
    traj = GraspTrajectory(REST, GraspProfile(others='open', **FAST))
    for at, (stamp, times, pos, vel, acc) in zip(expected_at, refs):
        assert stamp == times[0] == (at * MS) // (5 * MS) * (5 * MS)      # grid start
        np.testing.assert_array_equal(np.diff(times), 5 * MS)
        assert times[0] <= at * MS and times[-1] >= at * MS + 100 * MS > times[-2]
        ref = traj.sample(times / cv.NS)
        np.testing.assert_array_equal(pos, ref.pos)
        np.testing.assert_array_equal(vel, ref.vel)
        np.testing.assert_array_equal(acc, ref.acc)
    assert any(np.abs(r[3]).max() > 0.01 for r in refs)             # the grasp really moves
    # overlapping horizons agree point for point, so the controller's sample never depends on which
    (_, t_a, p_a, v_a, a_a), (_, t_b, p_b, v_b, a_b) = refs[0], refs[1]
    common = np.intersect1d(t_a, t_b)
    assert len(common) > 10
    ia, ib = np.searchsorted(t_a, common), np.searchsorted(t_b, common)
    np.testing.assert_array_equal(p_a[ia], p_b[ib])
    t = int(common[3]) + 1_234_567
    for x, y in zip(sample_horizon(t_a, p_a, v_a, a_a, t), sample_horizon(t_b, p_b, v_b, a_b, t)):
        np.testing.assert_array_equal(x, y)


def test_bad_tip_messages_are_counted_and_a_restart_takes_a_new_rest_pose():
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, reset_on_jump=0.01, **FAST)
        for k in range(0, 30):
            send(executor, node, pub, cv.tips_to_msg(k * MS, REST))
        nan = cv.tips_to_msg(30 * MS, REST)
        nan.poses[1].position.x = float('inf')
        for bad in (nan, cv.tips_to_msg(30 * MS, REST[:2]), cv.tips_to_msg(29 * MS, REST),
                    cv.tips_to_msg(25 * MS, REST)):
            send(executor, node, pub, bad)
        c = node.diag.counters
        assert (c['bad_message'], c['stale'], c['references']) == (2, 2, 2)
        moved = REST + 0.002
        send(executor, node, pub, cv.tips_to_msg(3 * MS, moved))          # restarted simulator
        refs = references(executor, node, probe)
        assert c['resets'] == 1 and len(refs) == 3
        stamp, times, pos, _, _ = refs[-1]
        assert stamp == 0
        np.testing.assert_array_equal(pos, GraspTrajectory(moved, GraspProfile(others='open', **FAST))
                                      .sample(times / cv.NS).pos)
        assert all(np.all(np.isfinite(r[2])) for r in refs)


@pytest.mark.parametrize('params, name', [
    (dict(horizon=0.03), 'horizon'), (dict(horizon=0.1, horizon_step=0.2), 'horizon_step'),
    (dict(publish_period=0.06), 'horizon'), (dict(t_close=0.0), 't_close'), (dict(t_start=-1.0), 't_start'),
    (dict(grasp_fingers=[0, 0]), 'grasp_fingers'), (dict(grasp_fingers=[0, 4]), 'grasp_fingers'),
    (dict(grasp_fingers=[1, 3], n_fingers=2), 'grasp_fingers'), (dict(others='close'), 'others'),
    (dict(close_distance=float('nan')), 'close_distance'), (dict(grasp_fingers='0,2'), 'grasp_fingers'),
    (dict(rest_pose='0.0, 0.01'), 'rest_pose'), (dict(rest_pose='a b c d e f g h'), 'rest_pose'),
    (dict(rest_pose=' '.join(['nan'] * 8)), 'rest_pose')])
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
    """With rest_pose the first tips (bent mid-grasp) do not become the rest; without it, flagged."""
    rest = ', '.join(repr(v) for v in REST[:, :2].ravel().tolist())
    bent = REST + 0.01
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, rest_pose=rest, **FAST)
        send(executor, node, pub, cv.tips_to_msg(30 * MS, bent))
        np.testing.assert_array_equal(node.traj.rest, REST[:, :2])
        assert node.diag.counters['late_start'] == 0 and references(executor, node, probe)
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, **FAST)
        send(executor, node, pub, cv.tips_to_msg(30 * MS, bent))
        assert node.diag.counters['late_start'] == 1
