"""The hand's URDF and the MarkerArray drawn from it: the URDF parses, its joints are the
simulator's joint_states names, its kinematics put every link where PyBullet has it, and the
markers' bytes decode (rosbags and rclpy) to the simulator's own tips and cube."""
from __future__ import annotations

from pathlib import Path
import xml.etree.ElementTree as ET

import numpy as np
import pybullet as pb
import pytest

from soft_gripper_sdre.nodes.markers import HandMarkers, decode
from soft_gripper_sdre.sim.finger import N_JOINTS
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.hand_description import (
    URDF_FILE,
    HandKinematics,
    hand_urdf,
    link_name,
    tip_link,
)
from soft_gripper_sdre.sim.units import LENGTH_SCALE

ROOT_DIR = Path(__file__).resolve().parents[1]
NAMES = [f'finger_{i}' for i in range(4)]


@pytest.fixture(scope='module')
def sim_state():
    """The hand after 0.3 s of torques that bend every finger both ways."""
    u = np.array([[-0.03, 0.01], [0.02, -0.01], [-0.03, -0.01], [0.01, 0.02]])
    with GripperSim(SimConfig()) as sim:
        for _ in range(300):
            sim.step(u)
        truth = sim.truth()
        links = {(i, j): pb.getLinkState(body, j, computeForwardKinematics=1,
                                         physicsClientId=sim.physics_client)
                 for i, body in enumerate(sim.finger_bodies) for j in range(N_JOINTS)}
        yield sim, truth, links


def test_the_installed_urdf_is_the_generated_one():
    assert (ROOT_DIR / URDF_FILE).read_text() == hand_urdf()


def test_urdf_parses_and_its_joints_are_the_joint_states_names(sim_state):
    sim, _, _ = sim_state
    robot = ET.fromstring(hand_urdf())
    joints = [j for j in robot.findall('joint') if j.get('type') == 'revolute']
    assert [j.get('name') for j in joints] == sim.joint_names
    assert sorted(j.get('name') for j in robot.findall('joint') if j.get('type') == 'fixed') == \
        [f'{n}/mount' for n in NAMES]
    links = {link.get('name') for link in robot.findall('link')}
    for j in robot.findall('joint'):
        assert j.find('parent').get('link') in links and j.find('child').get('link') in links
    # SI: a segment box is 0.46 x 0.34 x 0.20 sim units = 23 x 17 x 10 mm
    box = robot.find(f"link[@name='{link_name('finger_0', 1)}']/visual/geometry/box")
    np.testing.assert_allclose([float(v) for v in box.get('size').split()], [0.023, 0.017, 0.01])
    # the fingertip's collision sphere is drawn too
    assert robot.find(f"link[@name='{tip_link('finger_0')}']/visual/geometry/sphere") is not None


def test_urdf_for_renamed_fingers():
    robot = ET.fromstring(hand_urdf(['left', 'right'], [0, 2]))
    names = [j.get('name') for j in robot.findall('joint') if j.get('type') == 'revolute']
    assert names == [f'{n}/joint_{j}' for n in ('left', 'right') for j in range(N_JOINTS)]
    mount = robot.find("joint[@name='right/mount']/origin")
    np.testing.assert_allclose([float(v) for v in mount.get('xyz').split()], [0, 0.035, 0])
    with pytest.raises(ValueError, match='finger names'):
        hand_urdf(['left'], [0, 2])


def test_kinematics_put_every_link_where_pybullet_has_it(sim_state):
    sim, truth, links = sim_state
    kin = HandKinematics(hand_urdf())
    poses = kin.link_poses(dict(zip(sim.joint_names, truth.q.ravel().tolist())))
    for (i, j), state in links.items():
        T = poses[link_name(NAMES[i], j)]
        np.testing.assert_allclose(T[:3, 3], np.array(state[4]) / LENGTH_SCALE, atol=1e-9)
        R = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        np.testing.assert_allclose(T[:3, :3], R, atol=1e-6)     # PyBullet agrees to ~3e-8 here


def test_markers_decode_to_the_simulators_tips_and_cube(sim_state):
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    sim, truth, links = sim_state
    markers = HandMarkers(hand_urdf(), NAMES, range(4), with_references=True)
    refs = truth.tip_pos[:, :2] + [0.0, 0.002]
    data = markers.encode(1_234_000_000, truth.q, truth.cube_pose, refs)
    msg = decode(data)
    assert len(msg.markers) == markers.count == len(markers.kin.visuals) + 3
    assert {m.header.frame_id for m in msg.markers} == {'hand'}
    assert {(m.header.stamp.sec, m.header.stamp.nanosec) for m in msg.markers} == {(1, 234_000_000)}
    by_ns = {}
    for m in msg.markers:
        by_ns.setdefault(m.ns, []).append(m)
    tips = np.array([[p.x, p.y, p.z] for p in by_ns['tips'][0].points])
    np.testing.assert_allclose(tips, [np.array(links[(i, 9)][0]) / LENGTH_SCALE for i in range(4)],
                               atol=1e-9)
    cube = by_ns['cube'][0].pose
    np.testing.assert_allclose([cube.position.x, cube.position.y, cube.position.z,
                                cube.orientation.x, cube.orientation.y, cube.orientation.z,
                                cube.orientation.w], truth.cube_pose)
    # references: 2 mm along each finger's +Y from its tip
    ref_pts = np.array([[p.x, p.y, p.z] for p in by_ns['references'][0].points])
    _, rot = sim.base_poses
    np.testing.assert_allclose(ref_pts - tips, 0.002 * rot[:, :, 1], atol=1e-9)
    # every link box sits where its link is, with a unit quaternion
    for m in by_ns['links']:
        q = [m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w]
        assert abs(np.linalg.norm(q) - 1) < 1e-9
    # rclpy reads the same bytes
    typed = deserialize_message(data, MarkerArray)
    assert len(typed.markers) == len(msg.markers)
    assert typed.markers[-2].points[1].x == pytest.approx(tips[1, 0])


def test_markers_keep_a_reference_that_is_not_finite(sim_state):
    _, truth, _ = sim_state
    markers = HandMarkers(hand_urdf(), NAMES, range(4), with_references=True)
    first = decode(markers.encode(0, truth.q, truth.cube_pose, truth.tip_pos[:, :2]))
    refs = np.full((4, 2), np.nan)
    second = decode(markers.encode(10_000_000, truth.q, None, refs))
    assert first.markers[-1].points[0].x == second.markers[-1].points[0].x
