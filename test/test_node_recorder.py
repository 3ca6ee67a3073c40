"""The recorder node and the echo tool over real DDS (loopback), writing and reading real bags."""
import os
import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosgraph_msgs.msg import Clock
from rosutil import Probe, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
import yaml

from soft_gripper_sdre.analysis.bag import read_bag, topic_counts
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes import recorder as recorder_module
from soft_gripper_sdre.nodes.cdr import leading_stamp
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.recorder import RecorderNode, topic_qos
from soft_gripper_sdre.nodes.topics import (
    CLOCK,
    CUBE_CONTACTS,
    DIAGNOSTICS,
    STREAM_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.tools.graph import echo

pytestmark = pytest.mark.ros

MS = 1_000_000
N = 15
rng = np.random.default_rng(7)
TIPS = rng.normal(0.0, 0.05, (N, 4, 3))
TORQUES = rng.normal(0.0, 0.05, (N, 4, 2))
FORCES = np.abs(rng.normal(0.0, 1.0, (N, 4))) * (rng.random((N, 4)) > 0.5)


def start_recorder(ctx, executor, tmp_path, topics):
    """A RecorderNode on ``topics`` and a probe publishing each of them, discovery done."""
    rec = RecorderNode(context=ctx, parameter_overrides=overrides(output=str(tmp_path / 'bag'),
                                                                  topics=list(topics)))
    probe = Probe(ctx)
    pubs = {t: probe.create_publisher(msg_type, t, topic_qos(t)) for t, msg_type in topics.items()}
    executor.add_node(rec)
    executor.add_node(probe)
    assert spin_until(executor,
                      lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20.0)
    return rec, pubs


def publish_and_wait(executor, rec, pub, msg, topic):
    n = rec.counts[topic]
    pub.publish(msg)
    assert spin_until(executor, lambda: rec.counts[topic] == n + 1, 5.0), f'{topic} not received'


def test_bag_holds_exactly_the_published_messages(tmp_path):
    topics = {CLOCK: Clock, TIP_POSITIONS: PoseArray, TORQUE_COMMANDS: JointState,
              CUBE_CONTACTS: JointState}
    with ros_context() as (ctx, executor):
        rec, pubs = start_recorder(ctx, executor, tmp_path, topics)
        for k in range(N):
            ns = k * MS
            for topic, msg in ((CLOCK, cv.clock_msg(ns)),
                               (TIP_POSITIONS, cv.tips_to_msg(ns, TIPS[k])),
                               (TORQUE_COMMANDS, cv.torques_to_msg(ns, TORQUES[k])),
                               (CUBE_CONTACTS, cv.contacts_msg(ns, FORCES[k]))):
                publish_and_wait(executor, rec, pubs[topic], msg, '/' + topic.lstrip('/'))
        assert rec.diag.counters['messages /tip_positions'] == N
        rec.close()
        rec.close()                                       # idempotent (common.run may close again)
        pubs[TIP_POSITIONS].publish(cv.tips_to_msg(N * MS, TIPS[0]))    # after close: ignored
        for _ in range(20):
            executor.spin_once(timeout_sec=0.01)

    bag = tmp_path / 'bag'
    assert (bag / 'metadata.yaml').is_file() and len(list(bag.glob('*.mcap'))) == 1
    assert topic_counts(bag) == {'/clock': N, '/cube_contacts': N, '/tip_positions': N,
                                 '/torque_commands': N}
    data = read_bag(bag)
    stamps = [k * MS for k in range(N)]
    clock = data['/clock']
    assert [cv.from_time(m.clock) for _, m in clock] == stamps
    tips = data['/tip_positions']
    assert [t for t, _ in tips] == stamps                   # entry time = header stamp (sim time)
    for (_, m), expected in zip(tips, TIPS):
        assert m.header.frame_id == 'finger_bases'
        np.testing.assert_array_equal([(p.position.x, p.position.y, p.position.z) for p in m.poses],
                                      expected)
    torques = data['/torque_commands']
    for (_, m), expected in zip(torques, TORQUES):
        assert list(m.name) == cv.torque_names(4)
        np.testing.assert_array_equal(m.effort, expected.ravel())
    contacts = data['/cube_contacts']
    assert [cv.from_time(m.header.stamp) for _, m in contacts] == stamps
    np.testing.assert_array_equal([m.effort for _, m in contacts], FORCES)


def test_entry_times_stay_in_sim_time(tmp_path):
    """Before /clock: held back; wall-time or unset stamps: the latest /clock value."""
    topics = {CLOCK: Clock, TIP_POSITIONS: PoseArray, CUBE_CONTACTS: JointState,
              DIAGNOSTICS: DiagnosticArray}
    now = 2500 * MS
    with ros_context() as (ctx, executor):
        rec, pubs = start_recorder(ctx, executor, tmp_path, topics)
        wall = DiagnosticArray()
        wall.header.stamp = cv.to_time(time.time_ns())
        publish_and_wait(executor, rec, pubs[DIAGNOSTICS], wall, DIAGNOSTICS)  # before /clock
        publish_and_wait(executor, rec, pubs[TIP_POSITIONS], cv.tips_to_msg(now - MS, TIPS[0]),
                         '/tip_positions')
        publish_and_wait(executor, rec, pubs[CLOCK], cv.clock_msg(now), CLOCK)
        unset = cv.contacts_msg(0, FORCES[0])
        publish_and_wait(executor, rec, pubs[CUBE_CONTACTS], unset, '/cube_contacts')
        publish_and_wait(executor, rec, pubs[DIAGNOSTICS], wall, DIAGNOSTICS)  # after /clock
        rec.close()
    data = read_bag(tmp_path / 'bag')
    assert [t for t, _ in data['/diagnostics']] == [now, now]
    assert [t for t, _ in data['/tip_positions']] == [now - MS]
    assert [t for t, _ in data['/cube_contacts']] == [now]
    assert [t for t, _ in data['/clock']] == [now]


WALL_NS = 1_767_225_600_000_000_000           # a wall-time stamp [ns]


def test_a_best_effort_driver_stamping_wall_time_is_recorded_without_a_clock(tmp_path):
    """The default topics (/clock among them) in a graph without /clock: a driver publishing tips
    with the sensor-data QoS at wall-time stamps is heard with tips_reliability:=best_effort, and
    every message goes into the bag at its own stamp, the diagnostics held before it too."""
    from rclpy.qos import qos_profile_sensor_data
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), tips_reliability='best_effort'))
        probe = Probe(ctx)
        tips = probe.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
        diags = probe.create_publisher(DiagnosticArray, DIAGNOSTICS, topic_qos(DIAGNOSTICS))
        executor.add_node(rec)
        executor.add_node(probe)
        assert spin_until(executor, lambda: tips.get_subscription_count() > 0
                          and diags.get_subscription_count() > 0, 20.0)
        now = time.time_ns()                                 # the driver stamps with wall time
        diag = DiagnosticArray()
        diag.header.stamp = cv.to_time(now - 3 * MS)
        publish_and_wait(executor, rec, diags, diag, DIAGNOSTICS)
        assert rec._pending                                  # held: a /clock may still come
        stamps = [now + 5 * MS * k for k in range(N)]        # 200 Hz
        for k, ns in enumerate(stamps):
            publish_and_wait(executor, rec, tips, cv.tips_to_msg(ns, TIPS[k]), '/tip_positions')
            assert rec._pending is None                      # the graph runs on wall time
        rec.close()
    data = read_bag(tmp_path / 'bag')
    assert [t for t, _ in data['/diagnostics']] == [now - 3 * MS]
    assert [t for t, _ in data['/tip_positions']] == stamps
    assert [cv.from_time(m.header.stamp) for _, m in data['/tip_positions']] == stamps
    assert topic_counts(tmp_path / 'bag')['/tip_positions'] == N


def test_messages_held_for_a_clock_that_never_comes_are_written_after_the_clock_wait(
        tmp_path, monkeypatch):
    monkeypatch.setattr(recorder_module, 'CLOCK_WAIT_S', 0.3)
    with ros_context() as (ctx, executor):
        rec, pubs = start_recorder(ctx, executor, tmp_path, {CLOCK: Clock,
                                                              DIAGNOSTICS: DiagnosticArray})
        diag = DiagnosticArray()
        diag.header.stamp = cv.to_time(WALL_NS)
        publish_and_wait(executor, rec, pubs[DIAGNOSTICS], diag, DIAGNOSTICS)
        assert rec._pending
        assert spin_until(executor, lambda: rec._pending is None, 5.0)
        publish_and_wait(executor, rec, pubs[DIAGNOSTICS], diag, DIAGNOSTICS)
        rec.close()
    assert [t for t, _ in read_bag(tmp_path / 'bag')['/diagnostics']] == [WALL_NS, WALL_NS]


def test_topics_under_other_names_are_recorded_with_their_type_and_offered_qos(tmp_path):
    """A remapped table topic, and names the recorder does not know, whose type and QoS it takes
    from the graph: a best-effort PoseStamped, a transient-local String sent before the recorder
    subscribed (it still gets it, as ros2 bag record does)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from std_msgs.msg import String
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx,
                           cli_args=['--ros-args', '-r', 'tip_positions:=/driver/tips'],
                           parameter_overrides=overrides(output=str(tmp_path / 'bag'), topics=[
                               'tip_positions', 'mocap/body', '/left_hand/cube_pose', 'notes']))
        assert set(rec.counts) == {'/driver/tips'}                 # the others: once published
        probe = Probe(ctx)
        tips = probe.create_publisher(PoseArray, '/driver/tips', topic_qos(TIP_POSITIONS))
        body = probe.create_publisher(PoseStamped, 'mocap/body', qos_profile_sensor_data)
        cube = probe.create_publisher(PoseStamped, '/left_hand/cube_pose', STREAM_QOS)
        notes = probe.create_publisher(String, 'notes', latched)
        notes.publish(String(data='sent before the recorder listened'))
        executor.add_node(rec)
        executor.add_node(probe)
        pubs = (tips, body, cube, notes)
        assert spin_until(executor, lambda: all(p.get_subscription_count() > 0 for p in pubs), 20.0)
        assert spin_until(executor, lambda: rec.counts.get('/notes') == 1, 5.0)
        subs = rec._subs
        assert subs['/mocap/body'].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        assert subs['/left_hand/cube_pose'].qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert subs['/notes'].qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        for k in range(3):
            publish_and_wait(executor, rec, tips, cv.tips_to_msg(k * MS, TIPS[k]), '/driver/tips')
            pose = PoseStamped()
            pose.header.stamp = cv.to_time(k * MS)
            pose.pose.position.x = float(k)
            publish_and_wait(executor, rec, body, pose, '/mocap/body')
            publish_and_wait(executor, rec, cube, pose, '/left_hand/cube_pose')
        rec.close()
    bag = tmp_path / 'bag'
    assert topic_counts(bag) == {'/driver/tips': 3, '/mocap/body': 3, '/left_hand/cube_pose': 3,
                                 '/notes': 1}
    data = read_bag(bag)
    assert [(t, m.pose.position.x) for t, m in data['/mocap/body']] == [(k * MS, k)
                                                                        for k in range(3)]
    assert type(data['/mocap/body'][0][1]).__msgtype__ == 'geometry_msgs/msg/PoseStamped'
    assert [t for t, _ in data['/driver/tips']] == [k * MS for k in range(3)]
    assert data['/notes'][0][1].data == 'sent before the recorder listened'
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    types = {t['topic_metadata']['name']: t['topic_metadata']['type']
             for t in info['topics_with_message_count']}
    assert types['/notes'] == 'std_msgs/msg/String'
    assert types['/left_hand/cube_pose'] == 'geometry_msgs/msg/PoseStamped'


def test_leading_stamp_reads_the_time_of_any_stamped_message_and_survives_junk():
    from rclpy.serialization import serialize_message
    assert leading_stamp(serialize_message(cv.tips_to_msg(3 * cv.NS + 7, TIPS[0]))) == 3 * cv.NS + 7
    assert leading_stamp(serialize_message(cv.clock_msg(12))) == 12
    assert leading_stamp(serialize_message(cv.clock_msg(0))) == 0
    assert leading_stamp(b'\x00\x01') is None
    assert leading_stamp(b'\x00\x01\x00\x00'
                         + bytes.fromhex('ffffffff00000000')) is None  # sec = -1


def _run_node(args, **kwargs):
    return subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.recorder', '--ros-args',
                             *args],
                            env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, **kwargs)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_recorder_process_stopped_by_signal_leaves_a_readable_bag(tmp_path, sig):
    bag = tmp_path / 'bag'
    proc = _run_node(['-p', f'output:={bag}', '-p', 'topics:=[tip_positions, /diagnostics]'])
    try:
        with ros_context() as (ctx, executor):
            probe = Probe(ctx)
            probe.listen(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
            diags = probe.received[DIAGNOSTICS]
            pub = probe.create_publisher(PoseArray, TIP_POSITIONS, topic_qos(TIP_POSITIONS))
            executor.add_node(probe)
            assert spin_until(executor, lambda: pub.get_subscription_count() > 0,
                              20.0), 'recorder not up'
            for k in range(5):
                pub.publish(cv.tips_to_msg(k * MS, TIPS[k]))

            def recorded_all() -> bool:       # the recorder's own count, from its /diagnostics
                return any(kv.key == 'messages /tip_positions' and kv.value == '5'
                           for msg in diags for s in msg.status if s.name == '/recorder'
                           for kv in s.values)
            assert spin_until(executor, recorded_all, 20.0)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert (bag / 'metadata.yaml').is_file()
    tips = read_bag(bag, ['tip_positions'])['/tip_positions']
    assert [cv.from_time(m.header.stamp) for _, m in tips] == [k * MS for k in range(5)]
    assert topic_counts(bag)['/tip_positions'] == 5


@pytest.mark.parametrize('case', ['output', 'topics'])
def test_recorder_process_refuses_bad_parameters(tmp_path, case):
    args = {'output': ['-p', f'output:={tmp_path}'],
            'topics': ['-p', f'output:={tmp_path / "bag"}',
                       '-p', 'topics:=[tip_positions, 9lives]']}[case]
    proc = _run_node(args)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert f"parameter '{case}'" in err
    assert not (tmp_path / 'bag').exists()


@pytest.mark.parametrize('params, match', [
    (dict(topics=['tip_positions', 'cmd vel']), "'topics'.*cmd vel"),
    (dict(tips_reliability='sometimes'), 'tips_reliability'),
    (dict(topics=[]), 'topics'),
    (dict(storage='rosbag'), 'storage'),
    (dict(output='{tmp}'), "'output'.*already exists"),
    (dict(output='{tmp}/file/bag'), "'output'.*not a writable directory"),
])
def test_bad_parameters_fail_at_startup_naming_the_parameter(tmp_path, params, match):
    (tmp_path / 'file').write_text('not a directory')
    params = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in params.items()}
    params.setdefault('output', str(tmp_path / 'bag'))
    with ros_context() as (ctx, executor):
        with pytest.raises(ParameterError, match=match):
            RecorderNode(context=ctx, parameter_overrides=overrides(**params))


# -- echo ------------------------------------------------------------------------------------

def test_echo_once_prints_the_message_as_yaml():
    proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.tools.graph.echo',
                             'cube_contacts', '--once', '--timeout', '30'], env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with ros_context() as (ctx, executor):
            probe = Probe(ctx)
            pub = probe.create_publisher(JointState, CUBE_CONTACTS, topic_qos(CUBE_CONTACTS))
            executor.add_node(probe)
            msg = cv.contacts_msg(3 * cv.NS + 5, np.array([0.0, 0.25, 1.5, 0.0]))
            deadline = time.monotonic() + 30.0
            while proc.poll() is None and time.monotonic() < deadline:   # until echo has matched us
                pub.publish(msg)
                spin_until(executor, lambda: proc.poll() is not None, 0.1)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    doc = yaml.safe_load(out.split('---')[0])
    assert doc['header']['stamp'] == {'sec': 3, 'nanosec': 5}
    assert doc['name'] == ['finger_0', 'finger_1', 'finger_2', 'finger_3']
    assert doc['effort'] == [0.0, 0.25, 1.5, 0.0] and doc['position'] == []


@pytest.mark.parametrize('rate', [False, True], ids=['echo', 'rate'])
def test_echo_node_stops_after_count(capsys, rate):
    with ros_context() as (ctx, executor):
        node = echo.EchoNode('/clock', rate=rate, count=3, context=ctx)
        probe = Probe(ctx)
        pub = probe.create_publisher(Clock, CLOCK, topic_qos(CLOCK))
        executor.add_node(node)
        executor.add_node(probe)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0)
        for k in range(1, 4):
            pub.publish(cv.clock_msg(k * MS))
            assert spin_until(executor, lambda: node.received == k, 5.0)
        assert node.done
    out = capsys.readouterr().out
    assert out.count('---') == (0 if rate else 3)
    if not rate:
        assert 'nanosec: 3000000' in out


def test_echo_unknown_topic_exits_2_listing_the_known_ones(capsys):
    assert echo.main(['cmd_vel', '--once']) == 2
    err = capsys.readouterr().err
    assert "unknown topic 'cmd_vel'" in err and 'tip_positions' in err and '/clock' in err
