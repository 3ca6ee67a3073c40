"""Fuzzed messages on the nodes of fingers unlike the hand: no node crashes, nothing non-finite
comes out, and no command leaves its inputs' bounds.

The nodes of a lab's own gripper, each over real DDS: the controller with a model really trained
on a one-chamber planar finger (d = 2, m = 1, pressure 0..2e5 Pa) and on a three-tendon 3-D
segment (d = 3, m = 3, pull-only tendons 0..2 N), alone and composed with the estimator; the
estimator and the trajectory node on 3-D tips; the plant driver (``pneumatic1``, ``trunk3``);
the motion-capture node; the excitation node playing one-sided inputs. A seeded generator builds
well-typed messages with hostile content for two named fingers — NaN/Inf and huge values in any
coordinate (z included), wrong, unknown and duplicate names, the inputs of another finger shape,
empty and oversized arrays, zero and far-future stamps — and sends each node 400 of them, one at a
time. An exception in a callback would surface from the executor and fail the test; every message
holding a non-finite number where the node reads one must be refused and counted; the node must
still answer a good message afterwards.
"""
from faults_common import hostile_value, record
from geometry_msgs.msg import Pose, PoseArray, PoseStamped, Transform, Twist
from node_harness import make_composed
import numpy as np
import pytest
from rclpy.qos import qos_profile_sensor_data
from rosutil import Probe, deep, drain, linked, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from shaped_models import KNOWN_SYSTEMS, trained_known_system
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint

from soft_gripper_sdre.analysis.bag import read_bag, topic_counts
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.laws.registry import DEFAULT_WEIGHTS, graph_laws, model_shape
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import MESSAGE_OUTCOMES, EstimatorNode
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.mocap_tips import MocapTipsNode
from soft_gripper_sdre.nodes.plant_driver import TRUE_TIP_POSITIONS, PlantDriverNode
from soft_gripper_sdre.nodes.recorder import RecorderNode
from soft_gripper_sdre.nodes.simulator import SimulatorNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.trajectory import TrajectoryNode
from soft_gripper_sdre.sim.shape import InputBounds, ShapeError

pytestmark = pytest.mark.ros

N_MESSAGES = 400
NAMES = ['index', 'thumb']
MS = 1_000_000
#: the motion capture's stamps: wall time [ns]
T0 = 1_767_225_600_000_000_000
#: the hostile stamps :meth:`Fuzz.stamp` mixes in
JUMPS = ('zero', 'repeat', 'back', 'ahead', 'far')
#: the fields of a state_estimate its readers take
ESTIMATE_FIELDS = ('transforms', 'velocities')


class Fuzz:
    """Seeded hostile content of the right message types for the fingers ``NAMES``, whose tips
    have ``d`` coordinates the nodes read and whose commands ``m`` inputs."""

    def __init__(self, seed: int, d: int, m: int, step: int = MS,
                 jumps: tuple[str, ...] = JUMPS) -> None:
        self.rng = np.random.default_rng(seed)
        self.d, self.m = d, m
        self.bad = 0           # messages holding a non-finite number where the node reads one
        self.last_bad = False  # whether the newest message does
        self.step, self.k, self.jumps = step, 0, jumps   # the running clock of :meth:`stamp`

    def value(self) -> float:
        return hostile_value(self.rng, 0.005)

    def xyz(self, numbers: list) -> tuple[float, float, float]:
        """Three hostile coordinates; the ``d`` the nodes read are noted in ``numbers``."""
        xyz = (self.value(), self.value(), self.value())
        numbers += xyz[:self.d]
        return xyz

    def count(self, n: int) -> int:
        """Array lengths: mostly ``n``, often not."""
        return int(self.rng.choice([0, 1, n, n, n, n, n + 1, 2 * n, 64]))

    def names(self, n: int) -> list[str]:
        if self.rng.random() < 0.3:
            return [str(self.rng.choice(NAMES + ['', 'pinky', NAMES[0]])) for _ in range(n)]
        return (NAMES * n)[:n]

    def stamp(self, msg) -> None:
        """Mostly the running clock's next period (so well-formed messages reach the laws and
        filters), one in seven a hostile stamp: zero, repeated, seconds back or far ahead."""
        self.k += 1
        ns = self.k * self.step
        if self.jumps and self.rng.random() < 1 / 7:
            ns = {'zero': 0, 'repeat': ns - self.step, 'back': max(ns - 3 * 10**9, 0),
                  'ahead': ns + 10**12, 'far': 2**62}[str(self.rng.choice(self.jumps))]
        msg.header.stamp = cv.to_time(ns)

    def note(self, numbers: list[float]) -> None:
        self.last_bad = not np.all(np.isfinite(numbers))
        self.bad += self.last_bad

    def pose_array(self) -> PoseArray:
        msg = PoseArray()
        self.stamp(msg)
        numbers = []
        for _ in range(self.count(len(NAMES))):
            p = Pose()
            p.position.x, p.position.y, p.position.z = self.xyz(numbers)
            msg.poses.append(p)
        self.note(numbers)
        return msg

    def trajectory(self, points: int,
                   read: tuple[str, ...] = ('transforms', 'velocities', 'accelerations')
                   ) -> MultiDOFJointTrajectory:
        """A plan of ``points`` points, or an estimate (one point, whose accelerations no node
        reads: ``read`` names the fields whose numbers count)."""
        msg = MultiDOFJointTrajectory()
        self.stamp(msg)
        n = self.count(len(NAMES)) if self.rng.random() < 0.3 else len(NAMES)
        msg.joint_names = self.names(n)
        numbers = []
        for k in range(points):
            pt = MultiDOFJointTrajectoryPoint()
            for field in ('transforms', 'velocities', 'accelerations'):
                items = []
                for _ in range(int(self.rng.choice([n, n, n, self.count(n)]))):
                    x, y, z = self.xyz(numbers if field in read else [])
                    if field == 'transforms':
                        item = Transform()
                        item.translation.x, item.translation.y, item.translation.z = x, y, z
                    else:
                        item = Twist()
                        item.linear.x, item.linear.y, item.linear.z = x, y, z
                    items.append(item)
                setattr(pt, field, items)
            pt.time_from_start.nanosec = int(self.rng.choice([0, k, 5 * MS * k]))
            msg.points.append(pt)
        self.note(numbers)
        return msg

    def joint_state(self, lower, upper, ns: int | None = None) -> JointState:
        """Commands for the fingers' inputs (or another finger shape's), effort values hostile
        or anywhere from twice below the bounds to twice above them; stamped ``ns`` (one in
        seven a hostile stamp instead), or anywhere."""
        msg = JointState()
        if ns is None or self.rng.random() < 1 / 7:
            ns = int(self.rng.integers(0, 2**62))
        msg.header.stamp = cv.to_time(ns)
        m = int(self.rng.choice([self.m, self.m, self.m, self.m + 1, max(self.m - 1, 1)]))
        names = cv.torque_names(NAMES, m)
        n = self.count(len(names))
        msg.name = self.names(n) if self.rng.random() < 0.2 else (names * n)[:n]
        span = np.max(upper) - np.min(lower)
        msg.effort = [self.value() if self.rng.random() < 0.3 else
                      float(self.rng.uniform(np.min(lower) - span, np.max(upper) + span))
                      for _ in range(int(self.rng.choice([n, n, self.count(n)])))]
        self.note(msg.effort)
        return msg

    def pose_stamped(self, frame: str, ns: int) -> PoseStamped:
        """A body's pose stamped ``ns``, one in seven a hostile stamp instead."""
        msg = PoseStamped()
        msg.header.stamp = cv.to_time(ns if self.rng.random() >= 1 / 7 else int(
            self.rng.choice([0, ns - 10**9, ns + 10**12])))
        msg.header.frame_id = frame if self.rng.random() < 0.8 else str(
            self.rng.choice(['', 'camera', frame.upper()]))
        numbers = []
        p = msg.pose
        p.position.x, p.position.y, p.position.z = self.xyz(numbers)
        q = [self.value() for _ in range(4)] if self.rng.random() < 0.3 else [0.0, 0.0, 0.0, 1.0]
        numbers += q
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
        self.note(numbers)
        return msg


def _fuzz(executor, pub, make, node, received, refused, fz, n=N_MESSAGES):
    """Send ``n`` fuzzed messages one at a time, each once the node has taken the previous one
    (``received`` counters of its diagnostics), so no queue overflows and every one is judged;
    each one ``fz`` noted as holding NaN/Inf must have raised a ``refused`` counter."""
    def count(keys) -> int:
        return sum(node.diag.counters[k] for k in keys)
    start = count(received)
    for i in range(n):
        before = count(refused)
        pub.publish(make())
        assert spin_until(executor, lambda: count(received) >= start + i + 1, 5.0), (
            f'message {i} not handled; counters {dict(node.diag.counters)}')
        assert not fz.last_bad or count(refused) > before, f'message {i} with NaN/Inf taken'


def _rejected(node, keys) -> int:
    return sum(node.diag.counters[k] for k in keys)


def _record(name: str, topic: str, rejected: int, bad: int, extra: str = '',
            good: str = 'a good message is answered afterwards') -> None:
    record(f'fuzz_{name}', injected=f'hostile {topic} messages (seeded)', times=N_MESSAGES,
           crashes=0, nonfinite_outputs=0, messages_lost=None, recovery_s=None,
           notes=f'{rejected} rejected and counted, of which {bad} held NaN/Inf{extra}; {good}')


def _bounds_params(bounds: InputBounds) -> dict:
    return dict(input_lower=[float(v) for v in bounds.lower],
                input_upper=[float(v) for v in bounds.upper])


def _commands(msgs, m: int, bounds: InputBounds) -> np.ndarray:
    """Every command (k, 2, m), each named ``<finger>/ax<j>`` for j < m."""
    assert all(list(msg.name) == cv.torque_names(NAMES, m) for msg in msgs)
    return np.array([cv.msg_to_torques(msg, NAMES, m)[1] for msg in msgs]).reshape(-1, 2, m)


def _within(u: np.ndarray, bounds: InputBounds) -> bool:
    return bool(np.isfinite(u).all() and bounds.contains(u.reshape(-1, bounds.m)))


@pytest.fixture(scope='module', params=list(KNOWN_SYSTEMS), ids=lambda s: f'd{s[0]}m{s[1]}')
def checkpoint(request, tmp_path_factory):
    """(shape, bounds, the path of a model trained on the known system of that shape)."""
    return trained_known_system(*request.param, tmp_path_factory.mktemp('fuzz_shape'))


def _good_plan(d: int) -> MultiDOFJointTrajectory:
    pos = np.zeros((21, 2, d))
    pos[:, 0] += 0.001
    return cv.reference_to_msg(0, 5 * MS * np.arange(21), pos, 0 * pos, 0 * pos, NAMES)


def test_fuzzed_estimates_and_references_never_leave_the_inputs_bounds(checkpoint):
    """The controller of a one-chamber finger and of a three-tendon segment, each finger's
    command divided by its input gain: every command it sends is finite and within the
    actuators' own bounds (pressure and tension never below zero)."""
    shape, bounds, path = checkpoint
    d, m = shape.d, shape.m
    # estimates only repeat a stamp (a jump back resets the controller, which then waits for a
    # new plan: test_fuzz.py's hand controller takes those), plans jump anywhere
    fz, fz_plans = Fuzz(11 + d, d, m, jumps=('repeat',)), Fuzz(15 + d, d, m)
    with ros_context() as (ctx, executor):
        node = ControllerNode(context=ctx, parameter_overrides=overrides(
            model_path=str(path), finger_names=NAMES, input_gains=[1.3, 0.8],
            estimate_watchdog=60.0, q_pos=8e5, q_vel=0.0, r=1e-6, **_bounds_params(bounds)))
        probe = Probe(ctx)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        est_pub = probe.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
        ref_pub = probe.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        for n in (node, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: linked(est_pub, node) and linked(ref_pub, node)
                          and linked(node.pub_cmd, probe), 20.0)
        cmds = probe.received[TORQUE_COMMANDS]
        ref_pub.publish(_good_plan(d))
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        for _ in range(4):          # estimates against the plan in force, then new plans
            _fuzz(executor, est_pub, lambda: fz.trajectory(1, ESTIMATE_FIELDS), node,
                  ('estimates', 'bad_estimate', 'old_estimate'), ('bad_estimate', 'old_estimate'),
                  fz, N_MESSAGES // 8)
            _fuzz(executor, ref_pub, lambda: fz_plans.trajectory(
                points=int(fz_plans.rng.integers(0, 6))), node, ('references', 'bad_reference'),
                ('bad_reference',), fz_plans, N_MESSAGES // 8)
        c = node.diag.counters
        assert c['bad_reference'] >= fz_plans.bad > 20
        assert c['bad_estimate'] + c['old_estimate'] >= fz.bad > 20
        assert spin_until(executor, lambda: len(cmds) == c['estimates'] > 25, 5.0)
        assert _within(_commands(cmds, m, bounds), bounds)
        # a clean restart of time: the controller resets and answers within the bounds
        ref_pub.publish(_good_plan(d))
        n = len(cmds)
        for k in range(2):
            est_pub.publish(cv.estimate_to_msg(k * MS, np.zeros((2, d)), np.zeros((2, d)),
                                               NAMES))
        assert spin_until(executor, lambda: len(cmds) > n, 5.0)
        assert _within(_commands(cmds, m, bounds), bounds)
        _record(f'controller_d{d}m{m}', 'state_estimate + grasp_reference (200 each)',
                c['bad_reference'] + c['bad_estimate'] + c['old_estimate'], fz.bad + fz_plans.bad,
                f'; {len(cmds)} commands, none outside [{bounds}]')


def test_fuzzed_tips_never_reach_the_composed_controllers_commands(checkpoint):
    """``controller --with-estimator`` of either finger: hostile tips (z included where the
    tip is 3-D) are refused by its filter; its commands stay finite and within the bounds."""
    shape, bounds, path = checkpoint
    d, m = shape.d, shape.m
    fz = Fuzz(21 + d, d, m, jumps=('repeat',))     # a jump back resets: the plan is needed again
    with ros_context() as (ctx, executor):
        est, ctl, probe, tip_pub, ref_pub = make_composed(
            ctx, executor, task_dim=d, model_path=str(path), finger_names=NAMES,
            estimate_watchdog=60.0, **_bounds_params(bounds))
        ref_pub.publish(_good_plan(d))
        assert spin_until(executor, lambda: ctl.diag.counters['references'] == 1)
        _fuzz(executor, tip_pub, fz.pose_array, est, MESSAGE_OUTCOMES, MESSAGE_OUTCOMES[1:], fz)
        assert _rejected(est, MESSAGE_OUTCOMES[1:]) >= fz.bad > 40
        cmds = probe.received[TORQUE_COMMANDS]
        assert spin_until(executor, lambda: len(cmds) > 40, 5.0)
        assert _within(_commands(cmds, m, bounds), bounds)
        # a clean restart of time: the controller resets and answers within the bounds
        ref_pub.publish(_good_plan(d))
        n = len(cmds)
        for k in range(2):
            tip_pub.publish(cv.tips_to_msg(k * MS, np.zeros((2, 3))))
        assert spin_until(executor, lambda: len(cmds) > n, 5.0)
        assert _within(_commands(cmds, m, bounds), bounds)
        _record(f'composed_d{d}m{m}', 'tip_positions', _rejected(est, MESSAGE_OUTCOMES[1:]),
                fz.bad, f'; {len(cmds)} commands, none outside [{bounds}]')


def test_fuzzed_3d_tips_never_reach_the_estimate_or_the_plan():
    """The estimator and the trajectory node on 3-D tips: a NaN in z is as bad as one in x."""
    fz = Fuzz(31, 3, 3)
    with ros_context() as (ctx, executor):
        est = EstimatorNode(context=ctx, parameter_overrides=overrides(task_dim=3,
                                                                      finger_names=NAMES))
        plan = TrajectoryNode(context=ctx, parameter_overrides=overrides(
            task_dim=3, finger_names=NAMES, grasp_fingers=[0, 1], direction=[0.0, 0.0, 1.0],
            start_when='tips'))
        probe = Probe(ctx)
        probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, deep(LOOP_QOS))
        probe.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
        pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        for n in (est, plan, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: linked(pub, est) and linked(pub, plan)
                          and linked(est.pub, probe) and linked(plan.pub, probe), 20.0)
        c = plan.diag.counters
        _fuzz(executor, pub, fz.pose_array, est, MESSAGE_OUTCOMES, MESSAGE_OUTCOMES[1:], fz)
        assert _rejected(est, MESSAGE_OUTCOMES[1:]) >= fz.bad > 40
        estimates = probe.received[STATE_ESTIMATE]
        assert estimates and all(np.isfinite(cv.msg_to_estimate(msg, NAMES, 3)[1]).all()
                                 for msg in estimates)
        # the trajectory node took the first well-formed tips it heard for its plan: finite
        assert spin_until(executor, lambda: c['references'] >= 1, 5.0)
        assert c['bad_message'] >= 1
        plans = probe.received[GRASP_REFERENCE]
        assert spin_until(executor, lambda: len(plans) >= 1, 5.0)
        for msg in plans:
            assert all(np.isfinite(a).all() for a in cv.msg_to_reference(msg, NAMES, 3)[2:])
        n = len(estimates)
        pub.publish(cv.tips_to_msg(10**15, np.zeros((2, 3))))
        assert spin_until(executor, lambda: len(estimates) > n, 5.0)
        _record('estimator_3d', 'tip_positions (3-D)', _rejected(est, MESSAGE_OUTCOMES[1:]),
                fz.bad, '; the plan made from the first well-formed tips, finite')


@pytest.mark.parametrize('plant', ['pneumatic1', 'trunk3'])
def test_fuzzed_commands_never_drive_the_plant_outside_its_bounds(plant):
    """The plant driver: a command it cannot read keeps the previous one in force, one with NaN
    or Inf puts the rest input in force, one outside the bounds is clipped into them; the plant
    is never stepped with anything else, and its tips stay finite."""
    with ros_context() as (ctx, executor):
        node = PlantDriverNode(context=ctx, parameter_overrides=overrides(
            plant=plant, finger_names=NAMES, rate=200.0))
        m, d = node.m, node.d
        fz = Fuzz(41 + m, d, m)
        lower, upper = node.lower, node.upper                      # (fingers, m)
        probe = Probe(ctx)
        probe.listen(PoseArray, TRUE_TIP_POSITIONS, deep(LOOP_QOS))
        truth = probe.received[TRUE_TIP_POSITIONS]
        pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        for n in (node, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: linked(pub, node)
                          and node.pub_truth.get_subscription_count() > 0, 20.0)
        applied = []
        tick = node._tick

        def watched_tick():
            tick()
            applied.append(np.array(node.applied, dtype=float))
        node._timer.callback = watched_tick
        _fuzz(executor, pub, lambda: fz.joint_state(lower, upper), node, ('commands',),
              ('nonfinite_commands', 'bad_commands'), fz)
        c = node.diag.counters
        assert c['nonfinite_commands'] + c['bad_commands'] >= fz.bad > 40
        assert c['clipped_commands'] > 20
        drain(executor, 0.2)                            # ticks on the last command too
        applied = np.array(applied)
        assert len(applied) > 40 and np.isfinite(applied).all()
        assert np.all(applied >= lower) and np.all(applied <= upper)
        tips = [cv.msg_to_tips(msg, 2)[1] for msg in truth]
        assert tips and np.isfinite(np.array(tips)).all()
        _record(f'plant_driver_{plant}', 'torque_commands',
                c['nonfinite_commands'] + c['bad_commands'], fz.bad,
                f'; {c["clipped_commands"]} clipped into the bounds', good=f'{len(applied)} ticks, '
                'every input applied within the bounds')


def test_fuzzed_poses_never_reach_the_mocap_tips():
    """The motion-capture node: hostile positions, quaternions (zero, NaN, not unit) and frames
    are refused and counted; the tips it publishes stay finite."""
    fz = Fuzz(51, 3, 1)
    topics = ['/vrpn_mocap/index_tip/pose', '/vrpn_mocap/thumb_tip/pose']
    with ros_context() as (ctx, executor):
        node = MocapTipsNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, pose_topics=topics, base_positions=[0.1, 0.0, 0.2, -0.1, 0.0, 0.2],
            base_orientations=[0.0, 0.0, 0.0, 1.0] * 2,
            world_frame='world', pose_timeout=0.3))
        driver = Probe(ctx, 'vrpn_mocap')
        bodies = [driver.create_publisher(PoseStamped, t, qos_profile_sensor_data)
                  for t in topics]
        reader = Probe(ctx, 'reader')
        reader.listen(PoseArray, TIP_POSITIONS, deep(LOOP_QOS))
        tips = reader.received[TIP_POSITIONS]
        for n in (node, driver, reader):
            executor.add_node(n)
        assert spin_until(executor, lambda: all(linked(b, node) for b in bodies)
                          and linked(node.pub, reader), 20.0)
        c = node.diag.counters
        for k in range(N_MESSAGES // 2):             # a frame: both bodies, 10 ms apart
            for body, name in zip(bodies, NAMES):
                before, refused = node.diag.counters[f'poses {name}'], c['bad_poses']
                body.publish(fz.pose_stamped('world', T0 + 10 * MS * k))
                assert spin_until(executor, lambda: node.diag.counters[f'poses {name}']
                                  > before, 5.0), k
                assert not fz.last_bad or c['bad_poses'] > refused, f'pose {k} with NaN taken'
        c = node.diag.counters
        assert c['bad_poses'] >= fz.bad > 40 and len(tips) > 20
        assert all(np.isfinite(cv.msg_to_tips(msg, 2)[1]).all() for msg in tips)
        n = len(tips)
        for body in bodies:
            msg = PoseStamped()
            msg.header.stamp, msg.header.frame_id = cv.to_time(T0 + 10**12), 'world'
            msg.pose.orientation.w = 1.0
            body.publish(msg)
        assert spin_until(executor, lambda: len(tips) > n, 5.0)
        _record('mocap_tips', 'PoseStamped (both bodies)', c['bad_poses'], fz.bad,
                f'; {len(tips)} tip messages published, all finite')


@pytest.mark.parametrize('m, upper', [(1, [60000.0]), (3, [4.0, 4.0, 4.0])])
def test_fuzzed_tips_never_push_the_excitation_outside_its_bounds(m, upper):
    """The excitation node playing one-sided inputs on tips timing: hostile tips (and the
    stamps they carry) are refused or end the run as a fault; every command it sends, including
    its last, is finite and within the bounds."""
    d = 2 if m == 1 else 3
    fz = Fuzz(61 + m, d, m, step=2 * MS, jumps=('repeat',))     # any other jump ends the run
    bounds = InputBounds([0.0] * m, upper)
    with ros_context() as (ctx, executor):
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, signals=['u1'], duration=2.0, settle_time=0.0,
            min_command_subscribers=1, amplitude=1.0, max_excursion=0.0, **_bounds_params(bounds)))
        probe = Probe(ctx)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        cmds = probe.received[TORQUE_COMMANDS]
        pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        for n in (node, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: linked(pub, node) and linked(node.pub_cmd, probe),
                          20.0)
        c = node.diag.counters
        for k in range(N_MESSAGES):
            if node.done:
                break
            refused = c['bad_tips'] + c['old_tips']
            before = c['tips'] + refused
            pub.publish(fz.pose_array())
            assert spin_until(executor, lambda: c['tips'] + c['bad_tips'] + c['old_tips'] > before
                              or node.done, 5.0), k
            assert not fz.last_bad or c['bad_tips'] + c['old_tips'] > refused, f'tips {k} taken'
        assert c['bad_tips'] >= fz.bad > 40 and not node.done
        assert spin_until(executor, lambda: len(cmds) >= c['tips'] > 100, 5.0)
        u = _commands(cmds, m, bounds)
        assert _within(u, bounds) and u.max() > 0.3 * max(upper)          # played, not idle
        _record(f'excitation_m{m}', 'tip_positions', c['bad_tips'] + c['old_tips'], fz.bad,
                f'; {len(cmds)} commands, none outside [{bounds}]', good='the well-formed tips '
                'answered with the plan\'s inputs throughout')


@pytest.fixture(scope='module')
def models(tmp_path_factory):
    """The hand's shipped model and a model trained on each known system, with their bounds
    (None: the hand's ±u_max)."""
    out = {'hand': (SDCModel(), None)}
    for d, m in KNOWN_SYSTEMS:
        _, bounds, path = trained_known_system(d, m, tmp_path_factory.mktemp(f'law_d{d}m{m}'))
        out[f'd{d}m{m}'] = (SDCModel(path), bounds)
    return out


@pytest.mark.parametrize('shape', ['hand', 'd2m1', 'd3m3'])
@pytest.mark.parametrize('law', graph_laws())      # the oracle laws need the true plant
@pytest.mark.parametrize('method', ['fast', 'reference'])
def test_every_law_answers_hostile_finite_states_within_its_bounds(models, shape, law, method):
    """Finite but hostile states and references (±1e300, subnormal, ±1e6 m among ordinary ones)
    drive a learned model's blocks, the Riccati solution or a lifting far off their range: every
    law of every shape it serves answers each step with a finite command within the bounds, and
    never raises; the SDRE laws with the compiled kernels (``fast``) and with numpy and scipy
    (``reference``)."""
    model, bounds = models[shape]
    d = model_shape(model).d
    weights = Weights(**DEFAULT_WEIGHTS) if bounds is None else Weights(q_pos=8e5, q_vel=0.0,
                                                                         r=1e-6)
    limit = 0.0625
    try:
        ctrl = make_law(law, model, weights, limit, n_fingers=2, method=method,
                        **({} if bounds is None else {'bounds': bounds}))
    except ShapeError:
        assert law.startswith('koopman') and shape != 'hand'
        pytest.skip('the Koopman laws are the hand\'s')
    except ValueError as exc:
        assert law == 'lqr' and 'no stabilising Riccati solution' in str(exc)
        pytest.skip('lqr needs a Riccati solution of the model at rest')
    sdre = getattr(ctrl, 'sdre', None)
    if sdre is not None and law != 'lqr':
        assert (sdre.fast or sdre.general_kernels) == (method == 'fast')
    within = InputBounds.symmetric(limit, 2) if bounds is None else bounds
    rng = np.random.default_rng(71)

    def value() -> float:
        if rng.random() < 0.1:
            return float(rng.choice([1e300, -1e300, 0.0, 5e-324, 1e6, -1e6]))
        return float(rng.normal(0.0, 0.005))
    for _ in range(200):
        rows = np.array([[value() for _ in range(5 * d)] for _ in range(2)])
        p, v, p_d, v_d, a_d = (rows[:, j * d:(j + 1) * d] for j in range(5))
        u = np.asarray(ctrl.compute(p, v, p_d, v_d, ref_acc=a_d).u)
        assert np.isfinite(u).all() and within.contains(u.reshape(-1, within.m), tol=1e-12)


def test_fuzzed_loop_messages_are_all_recorded_and_the_bag_reads_back(tmp_path):
    """The recorder of a 3-D, three-tendon gripper's loop: hostile tips, commands and estimates,
    their stamps jumping anywhere (zero, back, 1000 s ahead, 2⁶² ns) — every message lands in the
    bag as it came, a stamp far ahead counts as a jump and not as millions of lost messages, and
    the bag opens and reads back."""
    fz = Fuzz(81, 3, 3)
    out = tmp_path / 'bag'
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(out), topics=[TIP_POSITIONS, TORQUE_COMMANDS, STATE_ESTIMATE]))
        probe = Probe(ctx)
        pubs = {TIP_POSITIONS: (probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS),
                                fz.pose_array),
                TORQUE_COMMANDS: (probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS),
                                  lambda: fz.joint_state([0.0] * 3, [4.0] * 3)),
                STATE_ESTIMATE: (probe.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE,
                                                        LOOP_QOS),
                                 lambda: fz.trajectory(1, ESTIMATE_FIELDS))}
        for n in (rec, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: all(linked(pub, rec) for pub, _ in pubs.values()),
                          20.0)
        sent = dict.fromkeys(pubs, 0)
        for k in range(N_MESSAGES):
            topic = list(pubs)[k % 3]
            pub, make = pubs[topic]
            pub.publish(make())
            sent[topic] += 1
            assert spin_until(executor, lambda: rec.counts[f'/{topic}'] == sent[topic], 5.0), k
        # a stamp far ahead (1000 s, 2⁶² ns) is a jump, not up to 10¹² lost messages
        gaps = rec.gaps
        assert gaps[f'/{TIP_POSITIONS}'].jumps >= 1 and gaps[f'/{STATE_ESTIMATE}'].jumps >= 1
        assert all(0 <= g.lost < 10 * N_MESSAGES for g in gaps.values())
        rec.close()
    counts = topic_counts(out)
    assert counts == {f'/{t}': n for t, n in sent.items()}
    assert {t: len(m) for t, m in read_bag(out).items()} == counts
    record('fuzz_recorder', injected='hostile tip_positions, torque_commands and state_estimate '
           'messages (seeded), stamps jumping anywhere', times=N_MESSAGES, crashes=0,
           nonfinite_outputs=0, messages_lost=0, recovery_s=None,
           notes='every message in the bag as sent ('
                 + ', '.join(f'{t} {n}' for t, n in sent.items()) + '); the bag reads back')


def test_fuzzed_commands_for_two_of_the_hands_fingers_never_reach_the_physics():
    """The simulator exposing two of the hand's fingers (``hand_fingers`` 0 and 2): commands
    named for four fingers, for one input, unknown or duplicated, with NaN/Inf, stale or ahead of
    the period are refused one by one; the physics never steps with a non-finite torque."""
    fz = Fuzz(91, 2, 2)
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
            scene='hand', finger_names=NAMES, hand_fingers=[0, 2], startup_timeout=0.0,
            lockstep_timeout=60.0, noise_std=0.0))
        probe = Probe(ctx)
        probe.listen(PoseArray, TIP_POSITIONS, deep(LOOP_QOS))
        pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        for n in (sim, probe):
            executor.add_node(n)
        assert spin_until(executor, lambda: linked(pub, sim) and sim.stepping.started
                          and probe.received[TIP_POSITIONS], 20.0)
        refused = ('bad_command', 'stale_command', 'future_command')
        tips = probe.received[TIP_POSITIONS]
        _fuzz(executor, pub, lambda: fz.joint_state(       # mostly for the period in force
            [-0.1, -0.1], [0.1, 0.1], cv.from_time(tips[-1].header.stamp)), sim,
            ('commands', *refused), refused, fz)
        assert _rejected(sim, refused) >= fz.bad > 40 and sim.stepping.counters['steps'] > 20
        assert np.all(np.isfinite(sim.sim.truth().tip_pos))
        assert all(np.isfinite(cv.msg_to_tips(msg, NAMES)[1]).all() for msg in tips)
        _record('simulator_two_fingers', 'torque_commands', _rejected(sim, refused), fz.bad,
                good=f'{len(tips)} tip messages, all finite')
