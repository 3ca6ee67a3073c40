"""analysis.bag.extract_run on recordings of fingers unlike the hand: a 3-D tip with one input
and a planar tip with three, as the graph's codecs write them (real rosbag2 files)."""
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from soft_gripper_sdre.analysis.bag import extract_run
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec

pytestmark = pytest.mark.ros          # the codecs learn their layouts through rclpy

MS = 1_000_000
STORE = get_typestore(Stores.ROS2_JAZZY)
NAMES = ('index', 'thumb')
TYPES = {'tip_positions': 'geometry_msgs/msg/PoseArray',
         'state_estimate': 'trajectory_msgs/msg/MultiDOFJointTrajectory',
         'torque_commands': 'sensor_msgs/msg/JointState',
         'grasp_reference': 'trajectory_msgs/msg/MultiDOFJointTrajectory'}


def _write(path: Path, topics: dict[str, list[tuple[int, bytes]]]) -> Path:
    writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        for topic, messages in topics.items():
            conn = writer.add_connection(topic, TYPES[topic], typestore=STORE)
            for ns, raw in messages:
                writer.write(conn, ns, raw)
    finally:
        writer.close()
    return path


def _run(d: int, m: int, steps: int = 40):
    """The arrays of a run of two fingers of shape (d, m), and their CDR bytes per topic."""
    rng = np.random.default_rng(10 * d + m)
    stamps = MS * np.arange(steps)
    tips = rng.normal(scale=0.01, size=(steps, 2, 3))
    if d == 2:
        tips[..., 2] = 0.1                              # a planar driver's fixed z
    x = rng.normal(scale=0.01, size=(steps, 2, 2 * d))
    u = rng.random((steps, 2, m))
    h = 11
    offsets = 10 * MS * np.arange(h)
    pos = np.linspace(0, 0.01, h)[:, None, None] * np.ones((h, 2, d))
    vel = np.full((h, 2, d), 0.01 / (h - 1) / 0.01)
    tips_c, est_c, cmd_c = (cdr.tips_codec(NAMES), cdr.estimate_codec(NAMES, d),
                            cdr.torques_codec(NAMES, m))
    topics = {
        'tip_positions': [(int(s), tips_c.encode(int(s), t)) for s, t in zip(stamps, tips)],
        'state_estimate': [(int(s), est_c.encode(int(s), e)) for s, e in zip(stamps, x)],
        'torque_commands': [(int(s), cmd_c.encode(int(s), c)) for s, c in zip(stamps, u)],
        'grasp_reference': [(0, PlanCodec(NAMES, d).encode(0, offsets, pos, vel,
                                                           np.zeros_like(pos)))],
    }
    return stamps, tips, x, u, (offsets, pos, vel), topics


@pytest.mark.parametrize('d, m', [(3, 1), (2, 3), (2, 2)])
def test_a_run_is_read_with_its_shape(tmp_path, d, m):
    stamps, tips, x, u, (offsets, pos, vel), topics = _run(d, m)
    run = extract_run(_write(tmp_path / 'bag', topics))
    assert (run.task_dim, run.n_inputs, run.finger_names) == (d, m, NAMES)
    np.testing.assert_array_equal(run.tips.t, stamps / 1e9)
    np.testing.assert_array_equal(run.tips.values, tips[..., :d])
    np.testing.assert_array_equal(run.estimate.values, x)
    np.testing.assert_array_equal(run.torques.values, u)
    assert run.reference.values.shape == (len(stamps), 2, 2 * d)
    want_pos = np.stack([np.interp(stamps, offsets, pos[:, 0, 0])] * d, axis=-1)
    np.testing.assert_allclose(run.reference.values[:, 0, :d], want_pos, atol=1e-15)
    np.testing.assert_allclose(run.reference.values[:, 1, d:],
                               np.broadcast_to(vel[0, 1], (len(stamps), d)), atol=1e-15)


def test_commands_of_another_input_count_than_the_first_are_skipped_and_counted(tmp_path):
    stamps, tips, x, u, _, topics = _run(2, 1)
    two = cdr.torques_codec(NAMES, 2)
    topics['torque_commands'].append((int(stamps[-1]) + MS,
                                      two.encode(int(stamps[-1]) + MS, np.zeros((2, 2)))))
    run = extract_run(_write(tmp_path / 'bag', topics))
    assert run.n_inputs == 1 and run.skipped == {'torque_commands': 1}
    np.testing.assert_array_equal(run.torques.values, u)
    assert cv.torque_names(NAMES, 1) == ['index/ax0', 'thumb/ax0']
