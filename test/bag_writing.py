"""Small real rosbag2 recordings for the bag-training tests, written with rosbags' Writer.

The messages are the graph's (``geometry_msgs/PoseArray`` tips, ``sensor_msgs/JointState``
torques named ``finger_i/axj``), built and serialised with rosbags' Jazzy types, as
``ros2 bag record`` or the recorder would store them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

MS = 1_000_000
STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
POSE_ARRAY, JOINT_STATE = 'geometry_msgs/msg/PoseArray', 'sensor_msgs/msg/JointState'


def _header(ns: int, frame_id: str = ''):
    return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=int(ns) // 10**9,
                                                                           nanosec=int(ns) % 10**9),
                                    frame_id=frame_id)


def tips_messages(stamps_ns, tips) -> list:
    """(stamp, PoseArray) per row of ``tips`` (T, n, 3) [m]."""
    out = []
    for ns, tip in zip(stamps_ns, np.asarray(tips, dtype=float)):
        poses = [T['geometry_msgs/msg/Pose'](
                     position=T['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
                     orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
                 for p in tip.tolist()]
        out.append((int(ns), T[POSE_ARRAY](header=_header(ns, 'finger_bases'), poses=poses)))
    return out


def torque_messages(stamps_ns, torques, names=None) -> list:
    """(stamp, JointState) per row of ``torques`` (C, n, 2) [N·m]; ``names`` replaces the joint
    names."""
    out = []
    for ns, u in zip(stamps_ns, np.asarray(torques, dtype=float)):
        joint = names or [f'finger_{i}/ax{a}' for i in range(u.shape[0]) for a in range(2)]
        out.append((int(ns), T[JOINT_STATE](header=_header(ns), name=list(joint),
                                            position=np.empty(0), velocity=np.empty(0),
                                            effort=u.ravel().copy())))
    return out


def write_bag(path: Path, topics: dict[str, list]) -> Path:
    """A rosbag2 directory holding, per topic name, the (bag timestamp ns, message) pairs given,
    each topic typed by its first message (an empty list: a JointState topic)."""
    writer = Writer(Path(path), version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        for topic, messages in topics.items():
            msgtype = messages[0][1].__msgtype__ if messages else JOINT_STATE
            conn = writer.add_connection(topic, msgtype, typestore=STORE)
            for ns, msg in messages:
                writer.write(conn, int(ns), STORE.serialize_cdr(msg, msgtype))
    finally:
        writer.close()
    return Path(path)


def excitation_bag(path: Path, seconds: float = 2.0, period_ns: int = MS, n_fingers: int = 1,
                   tips_topic: str = '/tip_positions',
                   torques_topic: str = '/torque_commands') -> Path:
    """A clean recording: tips and commands every ``period_ns`` for ``seconds``, a smooth motion
    under a sine torque."""
    stamps = np.arange(int(round(seconds * 1e9 / period_ns))) * period_ns
    t = stamps / 1e9
    tips = np.zeros((len(t), n_fingers, 3))
    tips[..., 0] = 1e-3 * np.sin(2 * np.pi * t)[:, None]
    tips[..., 1] = -0.01 + 2e-3 * np.sin(3 * np.pi * t)[:, None]
    torques = np.zeros((len(t), n_fingers, 2))
    torques[..., 0] = 0.02 * np.sin(np.pi * t)[:, None]
    torques[..., 1] = 0.01 * np.cos(np.pi * t)[:, None]
    return write_bag(path, {tips_topic: tips_messages(stamps, tips),
                            torques_topic: torque_messages(stamps, torques)})
