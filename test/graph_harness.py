"""Launch-free harness: the whole node graph in one process, on one executor, with its own Context.

``run_graph(duration, simulator=..., controller=..., ...)`` builds the simulator, estimator,
trajectory and controller nodes with parameter overrides, lets the lockstep loop run for
``duration`` seconds of sim time, and returns what a probe node recorded off the topics.
"""
from __future__ import annotations

from dataclasses import dataclass

from geometry_msgs.msg import PoseArray
import numpy as np
from rosutil import Probe, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.simulator import SimulatorNode
from soft_gripper_sdre.nodes.topics import (
    CUBE_CONTACTS,
    LOOP_QOS,
    STATE_ESTIMATE,
    STREAM_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode


@dataclass
class GraphRun:
    """Series recorded off the topics, one row per control period (T rows)."""

    t: np.ndarray            # (T,) s
    tips: np.ndarray         # (T, 4, 2) measured tip positions [m]
    estimate: np.ndarray     # (T, 4, 4)
    torques: np.ndarray      # (T, 4, 2) [N·m]
    contact_force: np.ndarray  # (S, 4) [N], at the simulator's state rate
    simulator: SimulatorNode
    controller: ControllerNode
    estimator: EstimatorNode
    trajectory: TrajectoryNode


def run_graph(duration: float, *, simulator: dict | None = None, estimator: dict | None = None,
              trajectory: dict | None = None, controller: dict | None = None,
              timeout: float = 300.0) -> GraphRun:
    """Run the graph in lockstep for ``duration`` s of sim time (see module doc)."""
    with ros_context('events') as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
            duration=duration, min_tip_subscribers=3, **(simulator or {})))
        est = EstimatorNode(context=ctx, parameter_overrides=overrides(**(estimator or {})))
        traj = TrajectoryNode(context=ctx, parameter_overrides=overrides(**(trajectory or {})))
        ctrl = ControllerNode(context=ctx, parameter_overrides=overrides(**(controller or {})))
        probe = Probe(ctx)
        subs = [probe.listen(PoseArray, TIP_POSITIONS, LOOP_QOS),
                probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS),
                probe.listen(JointState, TORQUE_COMMANDS, LOOP_QOS),
                probe.listen(JointState, CUBE_CONTACTS, STREAM_QOS)]
        for node in (probe, est, traj, ctrl):
            executor.add_node(node)
        # the probe hears everyone before the simulator (which only waits for its own peers) starts
        assert spin_until(executor, lambda: all(s.get_publisher_count() > 0 for s in subs)
                          and ctrl.sub_ref.get_publisher_count() > 0, 20.0)
        executor.add_node(sim)
        steps = int(round(duration / sim.p['control_period']))
        tips = probe.received[TIP_POSITIONS]
        assert spin_until(executor, lambda: sim.done and len(tips) > steps
                          and len(probe.received[TORQUE_COMMANDS]) >= steps, timeout), (
            f'graph did not finish: {sim.stepping.k} of {steps} steps, '
            f'counters {dict(sim.diag.counters)}')
        t, tip = zip(*(cv.msg_to_tips(m, 4) for m in tips[:steps]))
        est_ = [cv.msg_to_estimate(m, 4)[1] for m in probe.received[STATE_ESTIMATE][:steps]]
        u = [cv.msg_to_torques(m, 4)[1] for m in probe.received[TORQUE_COMMANDS][:steps]]
        force = [np.asarray(m.effort) for m in probe.received[CUBE_CONTACTS]]
        return GraphRun(np.asarray(t) / cv.NS, np.asarray(tip)[..., :2], np.asarray(est_),
                        np.asarray(u), np.asarray(force), sim, ctrl, est, traj)
