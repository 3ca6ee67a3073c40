"""Fuzzed messages on every loop subscription: no node crashes, nothing non-finite comes out.

A seeded generator builds well-typed messages with hostile content — NaN/Inf, huge values, empty
and oversized arrays, unknown and duplicate names, stamps at zero, in the past and far in the
future — and sends 1000 of them to each node over real DDS. An exception in any callback would
surface from the executor and fail the test; every message holding a non-finite number must be
refused, message by message (a NaN where a planar reader looks: X, Y and the fields it reads);
the node must still answer a good message afterwards.
"""
from faults_common import hostile_value, record
from geometry_msgs.msg import Pose, PoseArray, Transform, Twist
from node_harness import FAST_GRASP as FAST
from node_harness import make_controller, make_estimator, make_trajectory
import numpy as np
import pytest
from rosgraph_msgs.msg import Clock
from rosutil import Probe, drain, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.estimator import MESSAGE_OUTCOMES
from soft_gripper_sdre.nodes.simulator import SimulatorNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)

pytestmark = pytest.mark.ros

N_MESSAGES = 1000
NAMES = ['finger_0', 'finger_1', 'finger_2', 'finger_3', 'thumb', '', 'finger_0']


class Fuzz:
    """Seeded hostile content of the right message types."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.bad = 0           # messages holding a non-finite number where a planar reader looks

    def value(self) -> float:
        return hostile_value(self.rng, 0.05)

    def values(self, n: int) -> list[float]:
        return [self.value() for _ in range(n)]

    def count(self) -> int:
        """Array lengths: mostly right (4 fingers / 8 torques), often not."""
        return int(self.rng.choice([0, 1, 3, 4, 4, 4, 5, 8, 8, 8, 9, 64]))

    def stamp(self, msg) -> None:
        sec = int(self.rng.choice([0, 0, 1, 2, 10**6, 2**31 - 1]))
        msg.header.stamp.sec = sec
        msg.header.stamp.nanosec = int(self.rng.integers(0, 10**9))

    def note(self, numbers: list[float]) -> None:
        if not np.all(np.isfinite(numbers)):
            self.bad += 1

    def joint_state(self) -> JointState:
        msg = JointState()
        self.stamp(msg)
        n = self.count()
        names = cv.torque_names(4)
        msg.name = [str(self.rng.choice(names + ['finger_9/ax0', 'x'])) for _ in range(n)] \
            if self.rng.random() < 0.3 else names[:n]
        msg.effort = self.values(int(self.rng.choice([n, n, self.count()])))
        self.note(msg.effort)
        return msg

    def pose_array(self) -> PoseArray:
        msg = PoseArray()
        self.stamp(msg)
        numbers = []
        for _ in range(self.count()):
            p = Pose()
            p.position.x, p.position.y, p.position.z = xyz = self.values(3)
            numbers += xyz[:2]
            msg.poses.append(p)
        self.note(numbers)
        return msg

    def trajectory(self, points: int, read=('transforms', 'velocities', 'accelerations')
                   ) -> MultiDOFJointTrajectory:
        """A horizon of ``points``; NaN/Inf noted where a planar reader of ``read`` looks (X, Y)."""
        msg = MultiDOFJointTrajectory()
        self.stamp(msg)
        n = self.count() // 2 if self.rng.random() < 0.3 else 4
        msg.joint_names = [str(self.rng.choice(NAMES)) for _ in range(n)] \
            if self.rng.random() < 0.3 else NAMES[:n]
        numbers = []
        for k in range(points):
            pt = MultiDOFJointTrajectoryPoint()
            for field in ('transforms', 'velocities', 'accelerations'):
                items = []
                for _ in range(int(self.rng.choice([n, n, n, self.count()]))):
                    xyz = self.values(3)
                    if field in read:
                        numbers += xyz[:2]
                    if field == 'transforms':
                        item = Transform()
                        item.translation.x, item.translation.y, item.translation.z = xyz
                    else:
                        item = Twist()
                        item.linear.x, item.linear.y, item.linear.z = xyz
                    items.append(item)
                setattr(pt, field, items)
            pt.time_from_start.sec = int(self.rng.choice([0, k, 1]))
            msg.points.append(pt)
        self.note(numbers)
        return msg


def _finite_outputs(msgs, reader) -> bool:
    return all(np.all(np.isfinite(reader(m))) for m in msgs)


def _fuzz(executor, pub, make, node, received, refused=(), fz=None, n=N_MESSAGES):
    """Send ``n`` fuzzed messages one at a time, each once the node has taken the previous one
    (``received`` counters of its diagnostics), so no queue overflows and every one is judged; a
    message ``fz`` noted as holding a NaN/Inf must have raised one of the ``refused`` counters."""
    def count(keys) -> int:
        return sum(node.diag.counters[k] for k in keys)
    for i in range(n):
        taken, was_refused, bad = count(received), count(refused), fz.bad if fz else 0
        pub.publish(make())
        assert spin_until(executor, lambda: count(received) > taken, 5.0), (
            f'message {i} not handled; counters {dict(node.diag.counters)}')
        if fz is not None and fz.bad > bad:
            assert count(refused) > was_refused, (
                f'message {i} held a NaN/Inf and was not refused; counters '
                f'{dict(node.diag.counters)}')


def _record(node: str, topic: str, rejected: int, bad: int) -> None:
    record(f'fuzz_{node}', injected=f'hostile {topic} messages (seeded)', times=N_MESSAGES,
           crashes=0, nonfinite_outputs=0, messages_lost=None, recovery_s=None,
           notes=f'{rejected} rejected and counted, of which {bad} held NaN/Inf; a good message is '
                 'answered afterwards')


def _rejected(node, keys) -> int:
    return sum(node.diag.counters[k] for k in keys)


def test_fuzzed_torque_commands_never_reach_the_physics():
    fz = Fuzz(1)
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
            scene='hand', startup_timeout=0.0, lockstep_timeout=60.0, noise_std=0.0))
        probe = Probe(ctx)
        probe.listen(PoseArray, TIP_POSITIONS, LOOP_QOS)
        pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        executor.add_node(sim)
        executor.add_node(probe)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0
                          and sim.stepping.started and probe.received[TIP_POSITIONS])
        refused = ('bad_command', 'stale_command', 'future_command')
        _fuzz(executor, pub, fz.joint_state, sim, ('commands', *refused), refused, fz)
        rejected = _rejected(sim, refused)
        assert rejected >= fz.bad > 50
        assert np.all(np.isfinite(sim.sim.truth().tip_pos))
        assert _finite_outputs(probe.received[TIP_POSITIONS], lambda m: cv.msg_to_tips(m, 4)[1])
    _record('simulator', 'torque_commands', rejected, fz.bad)


def test_fuzzed_tips_never_reach_the_estimate():
    fz = Fuzz(2)
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor)
        _fuzz(executor, pub, fz.pose_array, node, MESSAGE_OUTCOMES, MESSAGE_OUTCOMES[1:], fz)
        assert _rejected(node, MESSAGE_OUTCOMES[1:]) >= fz.bad > 50
        out = probe.received[STATE_ESTIMATE]
        assert _finite_outputs(out, lambda m: cv.msg_to_estimate(m, 4)[1])
        # still a working filter: a good measurement far in the future resets and is published
        before = len(out)
        good = cv.tips_to_msg(10**15, np.zeros((4, 3)))
        pub.publish(good)
        assert spin_until(executor, lambda: len(out) > before)
        _record('estimator', 'tip_positions', _rejected(node, MESSAGE_OUTCOMES[1:]), fz.bad)


def test_fuzzed_tips_never_reach_the_plan():
    """The node takes tips only while it wants a rest pose: a hostile message is refused and it
    keeps listening; a well-formed one is planned from, and a restart (/clock jumping back) makes
    it listen again for the next one."""
    fz = Fuzz(3)
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, **FAST)
        c = node.diag.counters
        for i in range(N_MESSAGES):
            taken, refused, bad = c['tips'], c['bad_message'], fz.bad
            pub.publish(fz.pose_array())
            assert spin_until(executor, lambda: c['tips'] + c['bad_message'] > i, 5.0), (
                f'message {i} not handled; counters {dict(c)}')
            assert fz.bad == bad or c['bad_message'] > refused, (
                f'message {i} held a NaN/Inf and was not refused; counters {dict(c)}')
            if c['tips'] > taken:                               # planned: restart to listen again
                resets = c['resets']
                for ns in (10**9, 0):
                    probe.clock.publish(cv.clock_msg(ns))
                assert spin_until(executor, lambda: c['resets'] > resets and node.sub is not None
                                  and pub.get_subscription_count() > 0, 5.0)
        assert c['bad_message'] >= fz.bad > 50 and c['tips'] > 50
        plans = probe.received[GRASP_REFERENCE]
        assert spin_until(executor, lambda: len(plans) == c['references'] == c['tips'], 5.0)
        assert _finite_outputs(plans, lambda m: np.concatenate(
            [a.ravel() for a in cv.msg_to_reference(m, 4)[2:]]))
        _record('trajectory', 'tip_positions', c['bad_message'], fz.bad)


def test_fuzzed_clock_ticks_restart_the_plan_and_nothing_else():
    """/clock at zero, in the past, far ahead and jumping back: each jump back is taken for a
    restarted simulator and the plan (from the given rest pose) goes out again, always finite."""
    fz = Fuzz(5)
    rest = ', '.join(repr(v) for v in (0.001, -0.01, 0.0, -0.01, -0.001, -0.01, 0.0, -0.01))
    with ros_context() as (ctx, executor):
        node, probe, pub = make_trajectory(ctx, executor, rest_pose=rest, **FAST)
        c = node.diag.counters

        def hostile_tick():
            msg = Clock()
            msg.clock.sec = int(fz.rng.choice([0, 0, 1, 2, 10**6, 2**31 - 1]))
            msg.clock.nanosec = int(fz.rng.integers(0, 10**9))
            return msg
        _fuzz(executor, probe.clock, hostile_tick, node, ('ticks',))
        plans = probe.received[GRASP_REFERENCE]
        assert c['resets'] > 100 and c['references'] == 1 + c['resets']     # one plan per restart
        # the plan's writer keeps only the newest (REFERENCE_QOS): a reader that falls behind a
        # burst of restarts misses some plans, still gets the newest (reliable), never an extra one
        assert spin_until(executor, lambda: len(plans) >= 2)
        drain(executor, 1.0)
        assert len(plans) <= c['references']
        first = cv.msg_to_reference(plans[0], 4)
        for msg in plans[1:]:
            for a, b in zip(cv.msg_to_reference(msg, 4), first):
                np.testing.assert_array_equal(a, b)
        assert _finite_outputs(plans[:1], lambda m: np.concatenate(
            [a.ravel() for a in cv.msg_to_reference(m, 4)[2:]]))
        record('fuzz_trajectory_clock', injected='hostile /clock ticks (zero, past, far future, '
               'jumping back)', times=N_MESSAGES, crashes=0, nonfinite_outputs=0,
               messages_lost=None, recovery_s=None,
               notes=f'{c["resets"]} restarts detected, each answered with the plan again (from '
                     'the given rest pose, identical and finite)')


def test_fuzzed_estimates_and_references_never_reach_the_actuators():
    fz = Fuzz(4)
    model = SDCModel()
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(ctx, executor, estimate_watchdog=60.0)
        cmds = probe.received[TORQUE_COMMANDS]
        bad_before = fz.bad
        _fuzz(executor, ref_pub, lambda: fz.trajectory(points=int(fz.rng.integers(0, 6))), node,
              ('references', 'bad_reference'), ('bad_reference',), fz, N_MESSAGES // 2)
        bad_refs = fz.bad - bad_before
        _fuzz(executor, est_pub, lambda: fz.trajectory(1, ('transforms', 'velocities')), node,
              ('estimates', 'bad_estimate', 'old_estimate'), ('bad_estimate', 'old_estimate'), fz,
              N_MESSAGES // 2)
        bad_est = fz.bad - bad_before - bad_refs
        assert node.diag.counters['bad_reference'] >= bad_refs > 20
        assert (node.diag.counters['bad_estimate'] + node.diag.counters['old_estimate']
                >= bad_est > 20)
        assert _finite_outputs(cmds, lambda m: cv.msg_to_torques(m, 4)[1])
        # a clean restart of time: the controller resets and tracks again
        times = np.arange(0, 21) * 5_000_000
        pos = np.repeat(rest[None], 21, 0)
        ref_pub.publish(cv.reference_to_msg(0, times, pos, 0 * pos, 0 * pos))
        est_pub.publish(cv.estimate_to_msg(0, rest, np.zeros((4, 2))))
        est_pub.publish(cv.estimate_to_msg(1_000_000, rest, np.zeros((4, 2))))
        n = len(cmds)
        assert spin_until(executor, lambda: len(cmds) > n, 5.0)
        assert _finite_outputs(cmds, lambda m: cv.msg_to_torques(m, 4)[1])
        c = node.diag.counters
        _record('controller', 'state_estimate + grasp_reference (500 each)', c['bad_reference']
                + c['bad_estimate'] + c['old_estimate'], fz.bad)
