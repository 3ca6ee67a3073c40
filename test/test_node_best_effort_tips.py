"""A driver publishing tip_positions best effort (the sensor-data QoS) at 200 Hz, stamped with wall
time, in a graph without /clock: every node that reads the tips hears it with
``tips_reliability:=best_effort`` (the recorder, the trajectory node, the excitation node), over
real DDS (loopback)."""
import time

from geometry_msgs.msg import PoseArray
from node_harness import FAST_GRASP, MS
import numpy as np
import pytest
from rclpy.qos import qos_profile_sensor_data
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.analysis.bag import read_bag, topic_counts
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.recorder import RecorderNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode

pytestmark = pytest.mark.ros

BEST_EFFORT = dict(tips_reliability='best_effort')
PERIOD_NS = 5 * MS                                     # 200 Hz
REST = np.array([[0.0, -0.0105, 0.1076]] * 4)


def test_a_best_effort_wall_time_driver_is_heard_by_every_tip_reader(tmp_path):
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), **BEST_EFFORT))
        traj = TrajectoryNode(context=ctx, parameter_overrides=overrides(  # no controller here
            start_when='tips', **BEST_EFFORT, **FAST_GRASP))
        exc = ExcitationNode(context=ctx, parameter_overrides=overrides(
            signals=['x1'], duration=0.1, settle_time=0.02, settle_samples=0, torque_limit=0.1,
            **BEST_EFFORT))
        driver = Probe(ctx, 'driver')
        tips = driver.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
        driver.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        driver.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
        for node in (rec, traj, exc, driver):
            executor.add_node(node)
        assert spin_until(executor, lambda: tips.get_subscription_count() == 3
                          and exc.pub_cmd.get_subscription_count() == 2
                          and traj.pub.get_subscription_count() == 2, 20.0)

        commands = driver.received[TORQUE_COMMANDS]
        t0 = time.time_ns()
        stamps = []
        while not exc.done and len(stamps) < 100:      # paced: one answered before the next
            stamps.append(t0 + len(stamps) * PERIOD_NS)
            tips.publish(cv.tips_to_msg(stamps[-1], REST))
            assert spin_until(executor, lambda: len(commands) == len(stamps)
                              and rec.counts['/tip_positions'] == len(stamps), 5.0)
        assert exc.done and exc.exit_code == 0 and exc.diag.counters['tips'] == len(stamps)
        assert [cv.msg_to_torques(m, 4)[0] for m in commands] == stamps

        plans = driver.received[GRASP_REFERENCE]
        assert spin_until(executor, lambda: plans, 5.0)
        stamp, times, *_ = cv.msg_to_reference(plans[0], 4)
        assert stamp == times[0] == t0                 # the plan starts at the driver's first tips
        assert traj.diag.counters['tips'] == 1 and traj.diag.counters['late_start'] == 0
        assert spin_until(executor, lambda: rec.counts['/torque_commands'] == len(stamps), 5.0)
        rec.close()

    bag = tmp_path / 'bag'
    counts = topic_counts(bag)
    assert counts['/tip_positions'] == counts['/torque_commands'] == len(stamps)
    data = read_bag(bag, ['tip_positions', 'torque_commands', 'grasp_reference'])
    assert [t for t, _ in data['/tip_positions']] == stamps      # each at its own stamp
    assert [t for t, _ in data['/torque_commands']] == stamps
    assert [t for t, _ in data['/grasp_reference']] == [t0]
