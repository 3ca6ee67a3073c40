"""The controller node on a test graph: a probe that publishes estimates and references and records
the torque commands (shared by the controller's node, law and fuzz tests)."""
import numpy as np
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from rosutil import Probe, overrides, spin_until
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.topics import (GRASP_REFERENCE, LOOP_QOS, REFERENCE_QOS, STATE_ESTIMATE,
                                            TORQUE_COMMANDS)

MS = 1_000_000
LIMIT = 0.0625


def horizon(rest, start_ns, close_mm=5.0, points=21, step_ns=5 * MS):
    """A plan message: a constant reference ``close_mm`` towards the palm (+Y) for every finger,
    from ``start_ns`` on (held after its last point)."""
    times = start_ns + step_ns * np.arange(points)
    pos = np.repeat(rest[None, :, :], points, 0).copy()
    pos[..., 1] += close_mm * 1e-3
    zeros = np.zeros_like(pos)
    return cv.reference_to_msg(start_ns, times - start_ns, pos, zeros, zeros), pos[0]


def estimate(ns, pos, vel=None):
    return cv.estimate_to_msg(ns, pos, np.zeros_like(pos) if vel is None else vel)


def make(ctx, executor, **params):
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


def commands(probe):
    return probe.received[TORQUE_COMMANDS]


def send_estimate(executor, node, est_pub, msg) -> None:
    """Publish one estimate and spin until the node has taken it (it keeps only the newest
    message, so a burst would be skipped down to its last)."""
    c = node.diag.counters

    def taken() -> int:
        return c['estimates'] + c['bad_estimate'] + c['old_estimate']
    before = taken()
    est_pub.publish(msg)
    assert spin_until(executor, lambda: taken() > before, 5.0), 'estimate not taken'
