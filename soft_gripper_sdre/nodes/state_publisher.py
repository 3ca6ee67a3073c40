"""What the simulator publishes of its plant, period by period: the measured tips of the exposed
fingers on ``tip_positions`` every period, ``/clock`` at ``clock_rate`` and the true state
(``joint_states``, ``cube_pose``, ``cube_contacts``) at ``state_rate``, both in sim time.

The tips start the loop's critical path, so they go out first, as CDR bytes written at fixed
offsets (nodes/cdr.py), and the time they go out is the loop latency's start
(:class:`~soft_gripper_sdre.nodes.common.SteppingTiming`). The node calls
:meth:`StatePublisher.tips`, arms its wait for the command, then calls
:meth:`StatePublisher.streams`.
"""
from __future__ import annotations

from geometry_msgs.msg import PoseArray, PoseStamped
import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import SteppingTiming
from soft_gripper_sdre.nodes.topics import (
    CLOCK,
    CLOCK_QOS,
    CUBE_CONTACTS,
    CUBE_POSE,
    JOINT_STATES,
    LOOP_QOS,
    STREAM_QOS,
    TIP_POSITIONS,
)
from soft_gripper_sdre.sim.finger import N_JOINTS
from soft_gripper_sdre.sim.hand import GripperSim

_NO_VALUES = np.empty(0)       # /clock carries only its stamp


def periods_between(rate: float, control_period: float) -> int:
    """Control periods from one message at ``rate`` [Hz of sim time] to the next (at least 1)."""
    return max(1, int(round(1.0 / (rate * control_period))))


class StatePublisher:
    """The plant's topics on ``node``.

    Args:
        node: the simulator node that owns the publishers.
        sim: the plant.
        names, mounted: the exposed fingers' names and their indices in ``sim``.
        clock_every, state_every: periods between two /clock messages, between two states.
        timing: told when each period's tips went out.
    """

    def __init__(self, node: Node, sim: GripperSim, names, mounted: np.ndarray, *,
                 clock_every: int, state_every: int, timing: SteppingTiming) -> None:
        self.sim, self.names, self.mounted, self.timing = sim, tuple(names), mounted, timing
        self.clock_every, self.state_every = clock_every, state_every
        self.joint_names = [f'{name}/joint_{j}' for name in self.names for j in range(N_JOINTS)]
        self.cdr_clock = cdr.clock_codec()
        self.cdr_tips = cdr.tips_codec(self.names)
        self.pub_clock = node.create_publisher(Clock, CLOCK, CLOCK_QOS)
        self.pub_tips = node.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        self.pub_joints = node.create_publisher(JointState, JOINT_STATES, STREAM_QOS)
        self.pub_cube = node.create_publisher(PoseStamped, CUBE_POSE, STREAM_QOS)
        self.pub_contacts = node.create_publisher(JointState, CUBE_CONTACTS, STREAM_QOS)

    def tips(self, k: int, ns: int) -> None:
        """The measured tips of period ``k``, stamped ``ns``."""
        tips = self.cdr_tips.encode(ns, self.sim.measure()[self.mounted])
        self.timing.tips_sent(k)
        self.pub_tips.publish(tips)

    def streams(self, k: int, ns: int) -> None:
        """/clock and the true state, in the periods they are due."""
        if k % self.clock_every == 0:
            self.pub_clock.publish(self.cdr_clock.encode(ns, _NO_VALUES))
        if k % self.state_every == 0:
            truth = self.sim.truth()
            on = self.mounted        # the exposed fingers
            self.pub_joints.publish(cv.joint_states_msg(ns, self.joint_names, truth.q[on],
                                                        truth.qd[on]))
            if truth.cube_pose is not None:
                self.pub_cube.publish(cv.cube_pose_msg(ns, truth.cube_pose))
                self.pub_contacts.publish(cv.contacts_msg(ns, truth.contact_force[on], self.names))
