"""The simulator's live 3-D view of the hand (docs/visualization.md): its URDF on
``robot_description`` once (transient local, for a viewer that joins late), and the hand as
``markers`` on a wall timer at ``marker_rate`` while someone subscribes, with each finger's
reference from the newest plan when asked (the MarkerArray is laid out once: nodes/markers.py).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import String
from trajectory_msgs.msg import MultiDOFJointTrajectory
from visualization_msgs.msg import MarkerArray

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.markers import HandMarkers
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, REFERENCE_QOS, STREAM_QOS
from soft_gripper_sdre.sim.hand_description import hand_urdf

MARKERS, ROBOT_DESCRIPTION = 'markers', 'robot_description'
DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)


class LiveView:
    """The view's publishers, timer and plan subscription on ``node``.

    Args:
        node: the simulator node that owns them.
        names, mounted: the exposed fingers' names and their indices in the hand.
        marker_rate: markers per second of wall time (0: the URDF only).
        with_cube, with_references: draw the cube; draw each finger's reference (subscribes
            to ``grasp_reference``).
        now: () → (sim time [ns], the plant's truth) of what the markers show.
    """

    def __init__(self, node: Node, names, mounted, *, marker_rate: float, with_cube: bool,
                 with_references: bool, now: Callable[[], tuple[int, object]]) -> None:
        self.names, self.mounted, self._now = list(names), list(mounted), now
        self._markers = self._reference_raw = None
        urdf = hand_urdf(self.names, self.mounted)
        self.pub_description = node.create_publisher(String, ROBOT_DESCRIPTION, DESCRIPTION_QOS)
        self.pub_description.publish(String(data=urdf))
        if marker_rate <= 0:
            return
        self._markers = HandMarkers(urdf, self.names, self.mounted, with_cube=with_cube,
                                    with_references=with_references)
        self.pub_markers = node.create_publisher(MarkerArray, MARKERS, STREAM_QOS)
        if with_references:
            node.create_subscription(MultiDOFJointTrajectory, GRASP_REFERENCE,
                                     self._on_reference, REFERENCE_QOS, raw=True)
        node.create_timer(1.0 / marker_rate, self.publish)

    def _on_reference(self, data: bytes) -> None:
        self._reference_raw = data          # decoded only when the markers go out

    def _reference_at(self, ns: int) -> np.ndarray | None:
        """Each exposed finger's reference X, Y [m] at sim time ``ns`` from the newest plan."""
        if self._reference_raw is None:
            return None
        try:
            _, times, pos, _, _ = cv.msg_to_reference(
                deserialize_message(self._reference_raw, MultiDOFJointTrajectory), self.names)
        except (cv.MessageError, ValueError):
            return None
        return pos[int(np.clip(np.searchsorted(times, ns), 0, len(times) - 1))]

    def publish(self) -> None:
        """The hand's markers now, if anyone subscribes."""
        if self._markers is None or self.pub_markers.get_subscription_count() == 0:
            return
        ns, truth = self._now()
        self.pub_markers.publish(self._markers.encode(ns, truth.q[self.mounted], truth.cube_pose,
                                                      self._reference_at(ns)))
