"""The mocap_tips node over real DDS (loopback): a stand-in motion-capture driver (a real rclpy node
publishing one PoseStamped per body, sensor-data QoS as VRPN/OptiTrack drivers do) → per-finger
tips in each finger's base frame on ``tip_positions``, stamped with the measurement's stamp; bad
frames refused and counted, a missing finger pauses the message and is reported, bad parameters
refused naming them (exit 2)."""
import math
import os
import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
import numpy as np
import pytest
from rclpy.qos import qos_profile_sensor_data
from rosutil import Probe, deep, linked, overrides, ros_context, spin_until

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.mocap_tips import (
    MocapTipsNode,
    ParameterError,
    bases,
    pose_problem,
    quaternion_matrix,
)
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, LOOP_QOS, STREAM_QOS, TIP_POSITIONS

pytestmark = pytest.mark.ros

MS = 1_000_000
T0 = 1_767_225_600_000_000_000                  # the capture's stamps: wall time [ns]
S = math.sqrt(0.5)
#: left mounted at (0.1, 0, 0.2) unrotated; right at (-0.1, 0.05, 0.2) turned 90° about z
PARAMETERS = dict(finger_names=['left', 'right'],
                  pose_topics=['/vrpn_mocap/left_tip/pose', '/vrpn_mocap/right_tip/pose'],
                  base_positions=[0.1, 0.0, 0.2, -0.1, 0.05, 0.2],
                  base_orientations=[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, S, S],
                  world_frame='world', pose_timeout=0.3)


def pose(ns, xyz, quat=(0.0, 0.0, 0.0, 1.0), frame='world') -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp = cv.to_time(ns)
    msg.header.frame_id = frame
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, xyz)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = map(float, quat)
    return msg


def expected_tips(left_world, right_world) -> np.ndarray:
    """Each tip in its base frame: left only shifted; right shifted, then turned back by 90°."""
    left = np.subtract(left_world, (0.1, 0.0, 0.2))
    dx, dy, dz = np.subtract(right_world, (-0.1, 0.05, 0.2))
    return np.array([left, (dy, -dx, dz)])


def test_quaternions_and_bases():
    np.testing.assert_allclose(quaternion_matrix((0.0, 0.0, S, S)) @ [1.0, 0.0, 0.0],
                               [0.0, 1.0, 0.0], atol=1e-12)
    origins, rotations = bases(['a'], [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0005])
    assert origins.tolist() == [[1.0, 2.0, 3.0]]
    np.testing.assert_allclose(rotations[0], np.eye(3), atol=1e-12)     # normalised


@pytest.mark.parametrize('positions, orientations, needle', [
    ([0.0] * 5, [0, 0, 0, 1.0] * 2, "'base_positions': 3 numbers per finger, 6 for 2 fingers"),
    ([0.0] * 6, [0, 0, 0, 1.0] * 3, "'base_orientations': 4 numbers per finger, 8 for 2"),
    ([0.0, math.nan, 0, 0, 0, 0], [0, 0, 0, 1.0] * 2, "'base_positions': every number must be "
     'finite'),
    ([0.0] * 6, [0, 0, 0, 1.0, 0, 0, 0, 0.9], "'base_orientations': b's quaternion has norm 0.9"),
    ([0.0] * 6, [0, 0, 0, 1.0, 0, 0, 0, math.inf], "'base_orientations': every number"),
])
def test_bad_bases_are_refused_naming_the_parameter(positions, orientations, needle):
    with pytest.raises(ParameterError, match=needle.replace('(', r'\(')):
        bases(['a', 'b'], positions, orientations)


@pytest.mark.parametrize('msg, needle', [
    (pose(T0, (math.nan, 0, 0)), 'not finite'),
    (pose(T0, (0, 0, 0), (0, 0, math.inf, 1)), 'not finite'),
    (pose(T0, (0, 0, 0), (0, 0, 0, 0)), 'orientation norm 0, not 1'),
    (pose(T0, (0, 0, 0), (0, 0, 0, 1.1)), 'orientation norm 1.1'),
    (pose(0, (0, 0, 0)), 'unset stamp'),
    (pose(T0, (0, 0, 0), frame='camera'), "frame_id 'camera', not the world_frame 'world'"),
])
def test_bad_frames_are_named(msg, needle):
    assert needle in pose_problem(msg, 'world')
    assert pose_problem(pose(T0, (1, 2, 3), (0, 0, S, S)), 'world') is None
    assert pose_problem(pose(T0, (1, 2, 3), frame='any'), '') is None


class Mocap:
    """The mocap node, a stand-in capture driver publishing the bodies' poses, and a reader of
    tip_positions and /diagnostics, in one context."""

    def __init__(self, ctx, executor, reliability='reliable', **params):
        self.executor = executor
        self.node = MocapTipsNode(context=ctx, parameter_overrides=overrides(
            **{**PARAMETERS, 'tips_reliability': reliability, **params}))
        self.driver = Probe(ctx, 'vrpn_mocap')
        self.bodies = {name: self.driver.create_publisher(PoseStamped, topic,
                                                          qos_profile_sensor_data)
                       for name, topic in zip(('left', 'right'), PARAMETERS['pose_topics'])}
        self.reader = Probe(ctx, 'reader')
        qos = LOOP_QOS if reliability == 'reliable' else qos_profile_sensor_data
        self.reader.listen(PoseArray, TIP_POSITIONS, deep(qos))
        self.reader.listen(DiagnosticArray, DIAGNOSTICS, deep(STREAM_QOS))
        for node in (self.node, self.driver, self.reader):
            executor.add_node(node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in
                                                self.bodies.values())
                          and self.node.pub.get_subscription_count(), 20.0)
        self.tips = self.reader.received[TIP_POSITIONS]

    def send(self, body, msg, settle=True):
        count = self.node.diag.counters[f'poses {body}']
        self.bodies[body].publish(msg)
        if settle:
            assert spin_until(self.executor,
                              lambda: self.node.diag.counters[f'poses {body}'] > count, 5.0)

    def frame(self, ns, left, right):
        self.send('left', pose(ns, left))
        self.send('right', pose(ns, right, (0.0, 0.0, S, S)))

    def wait_tips(self, n):
        assert spin_until(self.executor, lambda: len(self.tips) >= n, 5.0), len(self.tips)

    def status(self) -> DiagnosticStatus:
        diags = self.reader.received[DIAGNOSTICS]
        n = len(diags)
        self.node.diag.publish()
        assert spin_until(self.executor, lambda: len(diags) > n, 5.0)
        return next(s for m in reversed(diags) for s in m.status if s.name == '/mocap_tips')


def _value(status, key):
    return next((kv.value for kv in status.values if kv.key == key), None)


@pytest.mark.parametrize('reliability', ['reliable', 'best_effort'])
def test_each_frame_becomes_tips_in_the_base_frames_with_the_measurements_stamp(reliability):
    rng = np.random.default_rng(5)
    with ros_context() as (ctx, executor):
        m = Mocap(ctx, executor, reliability)
        sent = []
        for k in range(6):
            left, right = rng.normal(0.0, 0.05, 3), rng.normal(0.0, 0.05, 3)
            m.frame(T0 + 10 * k * MS, left, right)
            sent.append((T0 + 10 * k * MS, expected_tips(left, right)))
            m.wait_tips(k + 1)
        assert len(m.tips) == 6
        for msg, (ns, tips) in zip(m.tips, sent):
            assert cv.from_time(msg.header.stamp) == ns and msg.header.frame_id == 'finger_bases'
            got = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses])
            np.testing.assert_allclose(got, tips, atol=1e-12)          # z kept
        status = m.status()
        assert status.level == DiagnosticStatus.OK, status.message
        assert _value(status, 'published') == '6' and _value(status, 'spread_us_max') == '0'


def test_a_set_takes_the_newest_stamp_and_reports_the_spread():
    with ros_context() as (ctx, executor):
        m = Mocap(ctx, executor)
        m.send('left', pose(T0, (0.1, 0.0, 0.3)))
        m.send('right', pose(T0 + 3 * MS, (-0.1, 0.05, 0.2), (0, 0, S, S)))
        m.wait_tips(1)
        assert cv.from_time(m.tips[0].header.stamp) == T0 + 3 * MS
        assert _value(m.status(), 'spread_us_max') == '3000'
        # right's pose of the next frame first: left's of the frame before is 10 ms behind it,
        # dropped, and the set waits for left's of this frame
        m.send('left', pose(T0 + 10 * MS, (0.1, 0.0, 0.3)))
        m.send('right', pose(T0 + 20 * MS, (-0.1, 0.05, 0.2), (0, 0, S, S)))
        assert m.node.diag.counters['behind'] == 1 and len(m.tips) == 1
        m.send('left', pose(T0 + 20 * MS, (0.1, 0.0, 0.3)))
        m.wait_tips(2)
        assert cv.from_time(m.tips[1].header.stamp) == T0 + 20 * MS
        # a pose replaced before its set completes; a set older than the last message
        m.send('left', pose(T0 + 30 * MS, (0.1, 0.0, 0.3)))
        m.send('left', pose(T0 + 31 * MS, (0.1, 0.0, 0.3)))
        assert m.node.diag.counters['superseded'] == 1
        m.frame(T0 + 32 * MS, (0.1, 0.0, 0.3), (-0.1, 0.05, 0.2))      # completes with 31+32
        m.wait_tips(3)
        m.frame(T0 + 5 * MS, (0.1, 0.0, 0.3), (-0.1, 0.05, 0.2))
        assert m.node.diag.counters['out_of_order'] == 1
        executor.spin_once(timeout_sec=0.05)
        assert len(m.tips) == 3


def test_bad_frames_are_counted_and_publish_nothing():
    with ros_context() as (ctx, executor):
        m = Mocap(ctx, executor)
        m.send('left', pose(T0, (0.1, 0.0, 0.3)))
        for bad in (pose(T0, (math.nan, 0, 0), (0, 0, S, S)), pose(T0, (0, 0, 0), (0, 0, 0, 0)),
                    pose(T0, (0, 0, 0), (0, 0, S, S), frame='camera'),
                    pose(0, (0, 0, 0), (0, 0, S, S))):
            m.send('right', bad)
        assert m.node.diag.counters['bad_poses'] == 4
        assert m.node.diag.counters['bad_poses right'] == 4
        status = m.status()
        assert status.level == DiagnosticStatus.WARN
        assert '4 bad pose(s) refused' in status.message
        assert not m.tips
        m.send('right', pose(T0, (-0.1, 0.05, 0.2), (0, 0, S, S)))
        m.wait_tips(1)
        got = [(p.position.x, p.position.y, p.position.z) for p in m.tips[0].poses]
        assert all(math.isfinite(v) for xyz in got for v in xyz)


def test_a_missing_finger_pauses_the_tips_and_is_reported_until_it_is_back():
    with ros_context() as (ctx, executor):
        m = Mocap(ctx, executor)
        m.frame(T0, (0.1, 0.0, 0.3), (-0.1, 0.05, 0.2))
        m.wait_tips(1)
        start = time.monotonic()
        k = 1
        while time.monotonic() - start < 0.6:              # right's body lost for 0.6 s
            m.send('left', pose(T0 + 10 * k * MS, (0.1, 0.0, 0.3)))
            k += 1
            executor.spin_once(timeout_sec=0.01)
        assert len(m.tips) == 1
        assert m.node.missing == ('right',)
        status = m.status()
        assert status.level == DiagnosticStatus.WARN
        assert 'no good pose of right for over 0.3 s: tip_positions paused' in status.message
        assert _value(status, 'missing') == 'right' and _value(status, 'missing_events') == '1'
        m.frame(T0 + 10 * k * MS, (0.1, 0.0, 0.3), (-0.1, 0.05, 0.2))   # right back
        m.wait_tips(2)
        assert spin_until(executor, lambda: m.node.missing == (), 1.0)
        assert m.status().level == DiagnosticStatus.OK


@pytest.mark.parametrize('args, needle', [
    (['-p', 'finger_names:=[a,b]'], "parameter 'pose_topics': one topic per finger, 2 for "
     "['a', 'b'], got 4"),
    (['-p', 'finger_names:=[a]', '-p', 'pose_topics:=[x]', '-p', 'base_positions:=[0.0]'],
     "parameter 'base_positions': 3 numbers per finger, 3 for 1 fingers ['a'], got 1"),
    (['-p', 'finger_names:=[a]', '-p', 'pose_topics:=[x]', '-p', 'base_positions:=[0.,0.,0.]',
      '-p', 'base_orientations:=[0.,0.,0.,2.]'],
     "parameter 'base_orientations': a's quaternion has norm 2, not 1"),
    (['-p', 'finger_names:=[a,b]', '-p', 'pose_topics:=[x,x]'], "parameter 'pose_topics': a "
     'topic per finger, each once'),
    (['-p', 'pose_topics:=[a,b,c,"1 bad"]'], "parameter 'pose_topics': '1 bad' is not a topic "
     'name'),
    (['-p', 'max_spread:=-1.0'], "parameter 'max_spread'"),
    (['-p', 'pose_timeout:=abc'], "parameter 'pose_timeout'"),
    (['-p', 'tips_reliability:=sometimes'], "parameter 'tips_reliability'"),
])
def test_bad_parameters_stop_the_node_naming_them(args, needle, tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    out = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.mocap_tips',
                          '--ros-args', *args], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    assert needle in out.stderr
    assert 'Traceback' not in out.stderr


def test_the_executable_serves_a_stand_in_capture_over_dds(tmp_path):
    """The node as its own process, as ``ros2 run soft_gripper_sdre mocap_tips`` starts it."""
    path = tmp_path / 'mocap.yaml'
    path.write_text('/**/mocap_tips:\n  ros__parameters:\n'
                    '    finger_names: [left, right]\n'
                    f'    pose_topics: {PARAMETERS["pose_topics"]}\n'
                    f'    base_positions: {PARAMETERS["base_positions"]}\n'
                    f'    base_orientations: {PARAMETERS["base_orientations"]}\n'
                    '    world_frame: world\n    tips_reliability: best_effort\n')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.mocap_tips',
                             '--ros-args', '--params-file', str(path)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with ros_context() as (ctx, executor):
            driver = Probe(ctx, 'vrpn_mocap')
            bodies = [driver.create_publisher(PoseStamped, t, qos_profile_sensor_data)
                      for t in PARAMETERS['pose_topics']]
            driver.listen(PoseArray, TIP_POSITIONS, deep(qos_profile_sensor_data))
            executor.add_node(driver)
            tips = driver.received[TIP_POSITIONS]
            assert spin_until(executor, lambda: all(b.get_subscription_count() for b in bodies)
                              and driver.count_publishers(TIP_POSITIONS), 60.0), \
                proc.stderr.read() if proc.poll() is not None else 'no match'
            time.sleep(0.5)                 # the node's reader of our tips matched too
            executor.spin_once(timeout_sec=0.1)
            for k in range(20):
                ns = T0 + 10 * k * MS
                bodies[0].publish(pose(ns, (0.1, 0.0, 0.2 + 0.001 * k)))
                bodies[1].publish(pose(ns, (-0.1, 0.06, 0.2), (0, 0, S, S)))
                spin_until(executor, lambda: len(tips) > k, 1.0)
            assert len(tips) >= 18              # best effort on loopback: next to none lost
            for msg in tips:
                k = (cv.from_time(msg.header.stamp) - T0) // (10 * MS)
                got = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses])
                np.testing.assert_allclose(got, [[0.0, 0.0, 0.001 * k], [0.01, 0.0, 0.0]],
                                           atol=1e-12)
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err


def test_the_estimator_takes_the_mocap_tips_at_the_captures_rate():
    """A 120 Hz capture of two bodies → mocap_tips → the estimator of two fingers: one estimate
    per frame on the frame's stamp, every message accepted, the estimates on the tips in the
    base frames."""
    from trajectory_msgs.msg import MultiDOFJointTrajectory

    from soft_gripper_sdre.nodes.estimator import MESSAGE_OUTCOMES, EstimatorNode
    from soft_gripper_sdre.nodes.topics import STATE_ESTIMATE

    period = int(round(1e9 / 120))
    rng = np.random.default_rng(2)
    with ros_context() as (ctx, executor):
        m = Mocap(ctx, executor)
        est = EstimatorNode(context=ctx, parameter_overrides=overrides(
            finger_names=['left', 'right'], control_period=1.0 / 120))
        m.reader.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, deep(LOOP_QOS))
        executor.add_node(est)
        # each reader matched (at least: an earlier test's reader may linger on the domain)
        assert spin_until(executor, lambda: linked(m.node.pub, m.reader, est)
                          and linked(est.pub, m.reader), 20.0)
        frames = []
        for k in range(60):
            left = np.array([0.1, 0.0, 0.2]) + [0.002 * math.sin(k / 10), 0.03, 0.0]
            right = np.array([-0.1, 0.05, 0.2]) + [0.0, 0.03, 0.001 * k]
            left += rng.normal(0.0, 2e-5, 3)
            ns = T0 + k * period
            m.frame(ns, left, right)
            frames.append((ns, expected_tips(left, right)))
            assert spin_until(executor, lambda: est.diag.counters['estimates'] > k, 5.0)
        e = est.diag.counters
        assert e['received'] == 60 == sum(e[key] for key in MESSAGE_OUTCOMES) == e['estimates']
        got = m.reader.received[STATE_ESTIMATE]
        assert spin_until(executor, lambda: len(got) == 60, 5.0)
        estimates = [cv.msg_to_estimate(msg, ['left', 'right']) for msg in got]
        assert [s for s, _ in estimates] == [ns for ns, _ in frames]
        x = np.array([x for _, x in estimates])
        np.testing.assert_allclose(x[:, :, :2], [t[:, :2] for _, t in frames], atol=2e-4)
