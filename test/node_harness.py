"""One node at a time over real DDS (loopback): the node under test and a probe node, matched.

Each ``make_*`` builds the node with parameter overrides in the caller's Context, adds it and a
:class:`~rosutil.Probe` to the executor, and returns once the probe's publishers and the node's
publisher are matched both ways, so nothing the test sends next is lost to discovery.
"""
from __future__ import annotations

from geometry_msgs.msg import PoseArray
import numpy as np
from rosgraph_msgs.msg import Clock
from rosutil import Probe, deep, linked, overrides, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode, composed
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.topics import (
    CLOCK,
    CLOCK_QOS,
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode

#: one millisecond of sim time [ns]
MS = 1_000_000
#: the controller's torque limit in these tests [N·m]
TORQUE_LIMIT = 0.0625
#: a grasp short enough that 100 ms of sim time see every phase (trajectory node parameters)
FAST_GRASP = dict(t_start=0.01, t_close=0.04, t_hold=0.01, t_open=0.03, side_distance=0.002)


def make_controller(ctx, executor, **params):
    """Controller + a probe publishing state_estimate and grasp_reference and recording
    torque_commands: ``(node, probe, estimate publisher, reference publisher)``."""
    node = ControllerNode(context=ctx, parameter_overrides=overrides(**params))
    probe = Probe(ctx)
    probe.listen(JointState, TORQUE_COMMANDS, LOOP_QOS)
    est_pub = probe.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
    ref_pub = probe.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor, lambda: est_pub.get_subscription_count() > 0
                      and ref_pub.get_subscription_count() > 0
                      and node.pub_cmd.get_subscription_count() > 0, 20.0)
    return node, probe, est_pub, ref_pub


def make_composed(ctx, executor, **params):
    """``controller --with-estimator`` (:func:`~soft_gripper_sdre.nodes.controller.composed`) + a
    probe publishing tip_positions and grasp_reference and recording torque_commands, every
    link matched: ``(estimator, controller, probe, tip publisher, reference publisher)``."""
    est, ctl = composed(context=ctx, parameter_overrides=overrides(**params))
    probe = Probe(ctx)
    probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
    tip_pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    ref_pub = probe.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
    for node in (est, ctl, probe):
        executor.add_node(node)
    assert spin_until(executor, lambda: linked(tip_pub, est) and linked(ref_pub, ctl)
                      and linked(ctl.pub_cmd, probe), 20.0)
    return est, ctl, probe, tip_pub, ref_pub


def make_estimator(ctx, executor, **params):
    """Estimator + a probe publishing tip_positions and recording state_estimate:
    ``(node, probe, tip publisher)``."""
    node = EstimatorNode(context=ctx, parameter_overrides=overrides(**params))
    probe = Probe(ctx)
    probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
    pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor, lambda: pub.get_subscription_count() > 0
                      and node.pub.get_subscription_count() > 0, 10.0)
    return node, probe, pub


def make_trajectory(ctx, executor, **params):
    """Trajectory node + a probe publishing tip_positions and /clock (``probe.clock``) and recording
    grasp_reference: ``(node, probe, tip publisher)``, matched. The probe plays the driver and no
    controller is there: the plan starts at the first tips (``start_when: tips``) unless the
    caller says otherwise."""
    params.setdefault('start_when', 'tips')
    node = TrajectoryNode(context=ctx, parameter_overrides=overrides(**params))
    probe = Probe(ctx)
    probe.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
    pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    probe.clock = probe.create_publisher(Clock, CLOCK, CLOCK_QOS)
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor, lambda: (pub.get_subscription_count() > 0
                                         or node.fixed_rest is not None)
                      and probe.clock.get_subscription_count() > 0
                      and node.pub.get_subscription_count() > 0, 10.0)
    return node, probe, pub


def estimate(ns: int, pos: np.ndarray, vel: np.ndarray | None = None) -> MultiDOFJointTrajectory:
    """A state_estimate message stamped ``ns`` with positions ``pos`` (n, 2) and velocities
    ``vel`` (zero if None)."""
    return cv.estimate_to_msg(ns, pos, np.zeros_like(pos) if vel is None else vel)


def commands(probe: Probe) -> list[JointState]:
    """The torque_commands messages ``probe`` has received so far (a live list)."""
    return probe.received[TORQUE_COMMANDS]


def horizon(rest, start_ns, close_mm=5.0, points=21, step_ns=5 * MS):
    """A plan message: a constant reference ``close_mm`` towards the palm (+Y) for every finger,
    from ``start_ns`` on (held after its last point); returns (message, (n, 2) positions)."""
    times = start_ns + step_ns * np.arange(points)
    pos = np.repeat(rest[None, :, :], points, 0).copy()
    pos[..., 1] += close_mm * 1e-3
    zeros = np.zeros_like(pos)
    return cv.reference_to_msg(start_ns, times - start_ns, pos, zeros, zeros), pos[0]


def send_estimate(executor, node, est_pub, msg) -> None:
    """Publish one estimate and spin until the controller has taken it (it keeps only the newest
    message, so a burst would be skipped down to its last)."""
    c = node.diag.counters

    def taken() -> int:
        return c['estimates'] + c['bad_estimate'] + c['old_estimate']
    before = taken()
    est_pub.publish(msg)
    assert spin_until(executor, lambda: taken() > before, 5.0), 'estimate not taken'
