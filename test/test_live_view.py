"""The simulator's live 3-D view over DDS: the hand's markers and robot_description, recorded by
the recorder node into MCAP and read back with rosbags' reader (no rclpy on the reading side)."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from rosutil import Probe, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes.live_view import MARKERS, ROBOT_DESCRIPTION
from soft_gripper_sdre.nodes.recorder import RecorderNode
from soft_gripper_sdre.nodes.simulator import SimulatorNode
from soft_gripper_sdre.nodes.topics import JOINT_STATES, LOOP_QOS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.hand_description import HandKinematics, tip_link

pytestmark = pytest.mark.ros
STORE = get_typestore(Stores.ROS2_JAZZY)
DURATION = 0.6


def _read(bag) -> dict[str, list]:
    """topic → [(stamp ns, message)] read with rosbags alone."""
    out: dict[str, list] = {}
    with Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            msg = STORE.deserialize_cdr(raw, conn.msgtype)
            out.setdefault(conn.topic.lstrip('/'), []).append(msg)
    return out


def test_markers_and_robot_description_reach_an_mcap_bag(tmp_path):
    bag = tmp_path / 'bag'
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(bag), topics=[MARKERS, ROBOT_DESCRIPTION, JOINT_STATES]))
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
            mode='realtime', duration=DURATION, marker_rate=20.0, marker_references=True,
            min_tip_subscribers=0, startup_timeout=60.0))
        executor.add_node(rec)
        executor.add_node(sim)
        # the recorder has matched all three before the simulator may start (a command writer)
        assert spin_until(executor, lambda: min(
            sim.live.pub_markers.get_subscription_count(),
            sim.live.pub_description.get_subscription_count(),
            sim.state_out.pub_joints.get_subscription_count()) > 0, 30.0)
        probe = Probe(ctx)
        probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        executor.add_node(probe)
        assert spin_until(executor, lambda: sim.done, 30.0)
        assert spin_until(executor, lambda: rec.counts.get(f'/{MARKERS}', 0) >= 3
                          and rec.counts.get(f'/{ROBOT_DESCRIPTION}', 0) == 1, 10.0), rec.counts
        rec.close()
    assert (bag / 'metadata.yaml').is_file() and list(bag.glob('*.mcap'))
    topics = _read(bag)
    (description,) = topics[ROBOT_DESCRIPTION]
    robot = ET.fromstring(description.data)
    revolute = [j.get('name') for j in robot.findall('joint') if j.get('type') == 'revolute']
    states = topics[JOINT_STATES]
    assert all(list(s.name) == revolute for s in states)
    kin = HandKinematics(description.data)
    stamps = np.array([s.header.stamp.sec * 10**9 + s.header.stamp.nanosec for s in states])
    markers = topics[MARKERS]
    assert len(markers) >= 3
    for msg in markers:
        by_ns = {}
        for m in msg.markers:
            by_ns.setdefault(m.ns, []).append(m)
        assert len(by_ns['links']) == len(kin.visuals) and len(by_ns['cube']) == 1
        assert {m.header.frame_id for m in msg.markers} == {'hand'}
        stamp = msg.markers[0].header.stamp.sec * 10**9 + msg.markers[0].header.stamp.nanosec
        state = states[int(np.argmin(np.abs(stamps - stamp)))]
        poses = kin.link_poses(dict(zip(state.name, state.position)))
        expected = [poses[tip_link(f'finger_{i}')][:3, :3] @ kin.com[tip_link(f'finger_{i}')]
                    + poses[tip_link(f'finger_{i}')][:3, 3] for i in range(4)]
        tips = [[p.x, p.y, p.z] for p in by_ns['tips'][0].points]
        np.testing.assert_allclose(tips, expected, atol=1e-4)   # a joint state within 5 ms
        cube = by_ns['cube'][0].pose.position
        assert abs(cube.z - 0.1125) < 1e-3                       # resting on the palm


def test_no_markers_at_rate_zero_and_no_description_for_the_finger_scene():
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(marker_rate=0.0,
                                                                       startup_timeout=0.0))
        topics = {pub.topic_name for pub in sim.publishers}
        assert f'/{ROBOT_DESCRIPTION}' in topics and f'/{MARKERS}' not in topics
        sim.close()
        sim.destroy_node()
        finger = SimulatorNode(context=ctx, parameter_overrides=overrides(
            scene='finger', finger_names=['finger_0'], hand_fingers=[0], startup_timeout=0.0))
        topics = {pub.topic_name for pub in finger.publishers}
        assert f'/{ROBOT_DESCRIPTION}' not in topics and f'/{MARKERS}' not in topics
        finger.close()
        finger.destroy_node()
