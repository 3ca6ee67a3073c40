"""A driver stamping with wall time (no /clock): the trajectory node plans from its first tips and
the controller tracks that plan, over real DDS (loopback). Wall-time stamps (~1.8e18 ns) go through
the plan's int64 times and the controller's sampling of it without losing a nanosecond."""
from geometry_msgs.msg import PoseArray
from node_harness import FAST_GRASP, MS, TORQUE_LIMIT, estimate
import numpy as np
import pytest
from rclpy.qos import qos_profile_sensor_data
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode

pytestmark = pytest.mark.ros

WALL_NS = 1_767_225_600_123_456_789          # the driver's first stamp: wall time [ns]
STEPS = 120                                  # 1 ms apart: beyond the FAST grasp's end (90 ms)


def test_a_wall_time_stamped_loop_tracks_the_plan_from_its_first_tips():
    rest = SDCModel().rest_tip[:2]
    tips = np.zeros((4, 3))
    tips[:, :2] = rest
    rng = np.random.default_rng(3)
    with ros_context() as (ctx, executor):
        traj = TrajectoryNode(context=ctx, parameter_overrides=overrides(
            tips_reliability='best_effort', **FAST_GRASP))
        ctrl = ControllerNode(context=ctx, parameter_overrides=overrides(torque_limit=TORQUE_LIMIT))
        # the same law, never spun: what the controller must answer, sampled on a plan at 0
        twin = ControllerNode(context=ctx, parameter_overrides=overrides(torque_limit=TORQUE_LIMIT),
                              cli_args=['--ros-args', '-r', '__node:=twin'])
        probe = Probe(ctx, 'driver')
        tip_pub = probe.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
        est_pub = probe.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        probe.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
        for node in (traj, ctrl, probe):
            executor.add_node(node)
        assert spin_until(executor, lambda: tip_pub.get_subscription_count() > 0
                          and est_pub.get_subscription_count() > 1        # controller and twin
                          and ctrl.pub_cmd.get_subscription_count() > 0
                          and traj.pub.get_subscription_count() > 1, 20.0)
        tip_pub.publish(cv.tips_to_msg(WALL_NS, tips))
        plans = probe.received[GRASP_REFERENCE]
        assert spin_until(executor, lambda: ctrl.gate.plan is not None and plans, 5.0), 'no plan'
        stamp, times, pos, vel, acc = cv.msg_to_reference(plans[0], 4)
        assert stamp == times[0] == WALL_NS and times.dtype == np.int64
        assert ctrl.gate.plan.start == WALL_NS

        got = probe.received[TORQUE_COMMANDS]
        x = np.zeros((STEPS, 4, 4))
        x[:, :, :2] = rest + rng.normal(0.0, 5e-5, (STEPS, 4, 2))
        x[:, :, 2:] = rng.normal(0.0, 1e-3, (STEPS, 4, 2))
        for k in range(STEPS):
            est_pub.publish(estimate(WALL_NS + k * MS, x[k, :, :2], x[k, :, 2:]))
            assert spin_until(executor, lambda: len(got) > k, 5.0), f'estimate {k} not answered'
        c = ctrl.diag.counters
        assert c['estimates'] == c['commands'] == STEPS and c['old_estimate'] == c['resets'] == 0

        torques = [cv.msg_to_torques(m, 4) for m in got]
        assert [s for s, _ in torques] == [WALL_NS + k * MS for k in range(STEPS)]
        u = np.array([u for _, u in torques])
        expected, law = [], twin.tuning.law
        for k in range(STEPS):                 # the same plan with its times from 0
            ref = sample_plan(times - WALL_NS, pos, vel, acc, k * MS, with_acc=True)
            expected.append(law.compute(x[k, :, :2], x[k, :, 2:], *ref[:2], ref_acc=ref[2]).u)
        np.testing.assert_array_equal(u, np.array(expected))
        # the torque follows the plan: the grasping fingers are pushed toward the cube (+Y: ax0 < 0)
        # while the plan closes them
        closing = int((FAST_GRASP['t_start'] + 0.5 * FAST_GRASP['t_close']) * 1e3)
        assert np.all(u[closing, [0, 2], 0] < 0) and np.abs(u[0]).max() < np.abs(u[closing]).max()
