"""The plan starts when its controller can answer (trajectory ``start_when``), over real DDS.

A driver stamping with wall time publishes tips at 1 kHz from its own timer; the estimator, the
trajectory node and the controller (the shipped model, real kernels) start in every order with
random delays between them. Whatever the order, the plan's origin is a tip heard after the
controller and the estimator were up, and the controller's first command follows the origin by
the loop's latency, never seconds into the plan. A lockstep simulator's first tips, heard before
the controller could be seen, are planned from once it can.
"""
import itertools
import random
import time

from geometry_msgs.msg import PoseArray
from node_harness import FAST_GRASP
import numpy as np
import pytest
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode

pytestmark = pytest.mark.ros

PERIOD = 0.001                      # the driver's tick [s]
#: the controller's first command after the plan's origin, at most [ns] (the grasp's hold at
#: rest, t_start, is 10 ms in FAST_GRASP; a controller that came late answered seconds in)
FIRST_COMMAND_NS = 200_000_000
#: how long building a node here holds up the one executor, at most [ns]
STALL_NS = 1_000_000_000
ORDERS = list(itertools.permutations(('trajectory', 'estimator', 'controller')))


class Driver(Probe):
    """Wall-stamped tips of four fingers at the model's rest, one per timer tick."""

    def __init__(self, ctx) -> None:
        super().__init__(ctx, 'driver')
        self.tips = np.zeros((4, 3))
        self.tips[:, :2] = SDCModel().rest_tip[:2]
        self.pub = self.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        self.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        self.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
        self.create_timer(PERIOD, lambda: self.pub.publish(cv.tips_to_msg(time.time_ns(),
                                                                          self.tips)))


def build(name: str, ctx):
    if name == 'trajectory':
        return TrajectoryNode(context=ctx, parameter_overrides=overrides(**FAST_GRASP))
    if name == 'estimator':
        return EstimatorNode(context=ctx)
    return ControllerNode(context=ctx)


@pytest.mark.timeout(240)
def test_the_plan_starts_once_the_controller_can_answer_in_every_start_order():
    rng = random.Random(32)
    for order in ORDERS:
        with ros_context() as (ctx, executor):
            driver = Driver(ctx)
            executor.add_node(driver)
            nodes, ready_ns, built_ns = {}, 0, 0
            for name in order:
                spin_until(executor, lambda: False, rng.uniform(0.0, 0.6))
                start_ns = time.time_ns()
                nodes[name] = build(name, ctx)
                executor.add_node(nodes[name])
                if name != 'trajectory':
                    ready_ns = time.time_ns()  # its topics exist from here on
                    built_ns = ready_ns - start_ns
            traj, ctrl = nodes['trajectory'], nodes['controller']
            plans, commands = (driver.received[t] for t in (GRASP_REFERENCE, TORQUE_COMMANDS))
            assert spin_until(executor, lambda: plans and commands, 20.0), (
                f'{order}: no plan or no command; trajectory {traj.diag.values}')
            origin = cv.msg_to_reference(plans[0], 4)[0]
            first = cv.msg_to_torques(commands[0], 4)[0]
            # a tip queued while a node was being built in this one process may be the first
            # heard after it (in a graph of processes nothing waits on a constructor)
            assert len(plans) == 1 and origin >= ready_ns - STALL_NS, (order, ready_ns - origin)
            # the first command follows the origin by the loop's latency, and by the time the
            # last loop node took to build: this one process heard no tip meanwhile, so the
            # origin may be a tip sent before it
            assert 0 <= first - origin <= FIRST_COMMAND_NS + built_ns, (
                order, (first - origin) / 1e6, built_ns / 1e6)
            assert ctrl.gate.plan.start == origin
            assert traj.diag.values['start_when'] == 'controller'
            assert traj.diag.values['waiting_for'] in ('', None) or 'waiting_for' not in (
                traj.diag.values)
            if order[0] == 'trajectory':      # it heard tips before the controller was up
                assert traj.diag.counters['early_tips'] > 0
                assert float(traj.diag.values['waited_s']) > 0


@pytest.mark.timeout(60)
def test_without_a_controller_the_plan_waits_and_says_so_unless_start_when_tips():
    with ros_context() as (ctx, executor):
        driver = Driver(ctx)
        waiting = TrajectoryNode(context=ctx, parameter_overrides=overrides(**FAST_GRASP))
        regardless = TrajectoryNode(context=ctx, parameter_overrides=overrides(
            start_when='tips', **FAST_GRASP), cli_args=['--ros-args', '-r', '__node:=regardless'])
        for node in (driver, waiting, regardless):
            executor.add_node(node)
        assert spin_until(executor, lambda: regardless.traj is not None, 10.0)
        spin_until(executor, lambda: False, 0.5)
        assert waiting.traj is None and waiting.diag.counters['references'] == 0
        assert waiting.diag.counters['early_tips'] > 100
        assert 'controller /controller' in waiting.diag.values['waiting_for']
        assert float(waiting.diag.values['waited_s']) > 0.3
        assert regardless.diag.values['start_when'] == 'tips'
        assert regardless.diag.counters['early_tips'] == 0
        # a controller of another name is not taken for this one's
        other = TrajectoryNode(context=ctx, parameter_overrides=overrides(
            controller_node='right_controller', **FAST_GRASP),
            cli_args=['--ros-args', '-r', '__node:=other'])
        executor.add_node(other)
        executor.add_node(ControllerNode(context=ctx))
        executor.add_node(EstimatorNode(context=ctx))
        assert spin_until(executor, lambda: waiting.traj is not None, 20.0), (
            waiting.diag.values)
        spin_until(executor, lambda: False, 0.3)
        assert other.traj is None and 'right_controller' in other.diag.values['waiting_for']


@pytest.mark.parametrize('params, named', [
    (dict(start_when='never'), 'start_when'),
    (dict(start_when=''), 'start_when'),
    (dict(controller_node=''), 'controller_node'),
    (dict(controller_node='/controller'), 'controller_node'),
    (dict(controller_node='9lives'), 'controller_node'),
])
def test_bad_start_settings_are_refused_naming_the_parameter(params, named):
    with ros_context() as (ctx, _):
        with pytest.raises(ParameterError, match=named):
            TrajectoryNode(context=ctx, parameter_overrides=overrides(**params))


@pytest.mark.parametrize('node, arg, named', [
    ('trajectory', 'start_when:=never', 'start_when'),
    ('trajectory', 'controller_node:=a/b', 'controller_node'),
    ('excitation', 'recorder_node:=9r', 'recorder_node'),
    ('recorder', 'discard_without:=not a topic!', 'discard_without'),
])
def test_bad_start_values_exit_2_naming_them_without_a_traceback(node, arg, named, tmp_path):
    import os
    import subprocess
    import sys
    out = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.nodes.{node}', '--ros-args',
                          '-p', arg, '-p', f'output:={tmp_path / "bag"}'] if node == 'recorder'
                         else [sys.executable, '-m', f'soft_gripper_sdre.nodes.{node}',
                               '--ros-args', '-p', arg],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path,
                         env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST'))
    assert out.returncode == 2, out.stderr
    assert named in out.stderr and 'Traceback' not in out.stderr
    assert not list(tmp_path.iterdir())            # nothing written (no bag)


@pytest.mark.timeout(60)
def test_tips_heard_before_the_controller_are_planned_from_when_no_newer_ones_come():
    """A lockstep simulator's start: the tips of t = 0 once, nothing newer until they are
    answered. The trajectory node heard them before it could see the controller (in a graph of
    processes it learns the controller's name a little after its subscription matched); once the
    controller shows up the plan starts at t = 0 from those tips."""
    with ros_context() as (ctx, executor):
        driver = Probe(ctx, 'lockstep_driver')
        pub = driver.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        driver.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
        traj = TrajectoryNode(context=ctx, parameter_overrides=overrides(**FAST_GRASP))
        for node in (driver, traj):
            executor.add_node(node)
        assert spin_until(executor, lambda: pub.get_subscription_count() >= 1, 10.0)
        tips = np.zeros((4, 3))
        tips[:, :2] = SDCModel().rest_tip[:2]
        pub.publish(cv.tips_to_msg(0, tips))
        assert spin_until(executor, lambda: traj.diag.counters['early_tips'] == 1, 10.0)
        spin_until(executor, lambda: False, 0.1)
        assert traj.traj is None                                # still waiting: no controller
        for node in (EstimatorNode(context=ctx), ControllerNode(context=ctx)):
            executor.add_node(node)
        plans = driver.received[GRASP_REFERENCE]
        assert spin_until(executor, lambda: plans, 20.0), traj.diag.values
        assert cv.msg_to_reference(plans[0], 4)[0] == 0          # from the tips of t = 0
        assert traj.diag.counters['early_tips'] == 1 and traj.diag.values['waiting_for'] == ''
