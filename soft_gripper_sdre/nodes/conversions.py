"""numpy ↔ message conversions for every topic of the graph, with validation.

Stamps are int nanoseconds of sim time. Every ``msg_to_*`` raises :class:`MessageError` naming
the problem (non-finite values, wrong sizes, unknown / duplicate / missing names); nodes count
and log those instead of computing with the message.
"""
from __future__ import annotations

import functools
import re
from typing import Sequence

from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Pose, PoseArray, PoseStamped, Transform, Twist
import numpy as np
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint

from soft_gripper_sdre import FINGER_NAMES

NS = 1_000_000_000


class MessageError(ValueError):
    """A message cannot be used; the text says why."""


# -- time ------------------------------------------------------------------------------------

def to_time(ns: int) -> Time:
    return Time(sec=int(ns // NS), nanosec=int(ns % NS))


def set_time(stamp: Time, ns: int) -> None:
    """Write ``ns`` into an existing stamp (a message reused every period allocates nothing)."""
    stamp.sec, stamp.nanosec = divmod(int(ns), NS)


def from_time(stamp) -> int:
    return int(stamp.sec) * NS + int(stamp.nanosec)


def to_duration(ns: int) -> Duration:
    return Duration(sec=int(ns // NS), nanosec=int(ns % NS))


def clock_msg(ns: int) -> Clock:
    msg = Clock()
    set_time(msg.clock, ns)
    return msg


# -- names -----------------------------------------------------------------------------------

#: most fingers one message carries (the hand's four)
MAX_FINGERS = len(FINGER_NAMES)
_FINGER_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')

#: the fingers of a message: a count (named ``finger_0``.. in order) or the names themselves
Fingers = int | Sequence[str]


def finger_names(fingers: Fingers) -> tuple[str, ...]:
    """The finger names ``fingers`` stands for: ``n`` → ``finger_0 .. finger_<n-1>``; names as
    given."""
    if isinstance(fingers, (int, np.integer)):
        return FINGER_NAMES[:int(fingers)]
    return tuple(fingers)


def finger_names_problem(names: Sequence[str]) -> str | None:
    """Why ``names`` cannot name the fingers of the graph, or None.

    One rule for every node: the number of fingers is the number of names, 1 to
    :data:`MAX_FINGERS`; each name is a ROS name token (letters, digits, underscores, not
    starting with a digit), used as is in ``state_estimate`` / ``grasp_reference`` joint names
    and as ``<name>/ax0`` … ``<name>/ax<m−1>`` in ``torque_commands``; no name twice.
    """
    names = list(names)
    if not 1 <= len(names) <= MAX_FINGERS:
        return f'needs 1 to {MAX_FINGERS} names (one per finger), got {len(names)}'
    bad = [n for n in names if not _FINGER_NAME.fullmatch(n)]
    if bad:
        return (f'{bad[0]!r} is not a valid finger name (letters, digits and underscores, '
                'not starting with a digit)')
    if len(set(names)) != len(names):
        return f'names must be distinct, got {names}'
    return None


def torque_names(fingers: Fingers, m: int = 2) -> list[str]:
    """``<finger>/ax0`` … ``<finger>/ax<m−1>`` for each finger (``m`` inputs each; the hand's 2),
    in the order of u.ravel()."""
    return list(_torque_names(finger_names(fingers), m))


@functools.lru_cache(maxsize=None)
def _torque_names(names: tuple[str, ...], m: int = 2) -> tuple[str, ...]:
    return tuple(f'{name}/ax{a}' for name in names for a in range(m))


def _order(names, expected, what: str) -> np.ndarray | slice:
    """Index of each expected name in ``names``; every name must be known and appear once.

    Names already in the expected order (what our own nodes send) give ``slice(None)``: the
    check is one list comparison and the data need not be gathered.
    """
    names = list(names)
    if names == list(expected):
        return slice(None)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise MessageError(f'{what}: duplicate names {dup}')
    unknown = sorted(set(names) - set(expected))
    if unknown:
        raise MessageError(f'{what}: unknown names {unknown[:4]} (expected {expected[:2]}…)')
    missing = [n for n in expected if n not in names]
    if missing:
        raise MessageError(f'{what}: missing names {missing[:4]}')
    pos = {n: i for i, n in enumerate(names)}
    return np.fromiter((pos[n] for n in expected), int, len(expected))


def check_finite(a: np.ndarray, what: str) -> np.ndarray:
    """``a`` if every value is finite.

    Raises:
        MessageError: '<what> contains NaN or Inf'.
    """
    if not np.all(np.isfinite(a)):
        raise MessageError(f'{what} contains NaN or Inf')
    return a


#: what :func:`check_finite` names in the loop messages (also on the raw CDR path, nodes/cdr.py)
TIPS_WHAT, TORQUES_WHAT, ESTIMATE_WHAT = 'tip_positions', 'torque_commands effort', 'state_estimate'


# -- tip positions (PoseArray) ---------------------------------------------------------------

def tips_to_msg(ns: int, tips: np.ndarray, frame_id: str = 'finger_bases') -> PoseArray:
    """(n, 3) tip positions [m] → PoseArray; pose i is finger i's tip in its own base frame
    ((n, 2) planar tips: z = 0)."""
    msg = PoseArray()
    msg.header.frame_id = frame_id
    msg.poses = [Pose() for _ in range(len(tips))]
    fill_tips(msg, ns, tips)
    return msg


def fill_tips(msg: PoseArray, ns: int, tips: np.ndarray) -> None:
    """Overwrite the stamp and the positions of a PoseArray from :func:`tips_to_msg` in place."""
    set_time(msg.header.stamp, ns)
    tips = np.asarray(tips, dtype=float)
    if tips.shape[-1] == 2:
        tips = np.asarray(_pad3(tips))
    for pose, (x, y, z) in zip(msg.poses, tips.tolist()):
        p = pose.position
        p.x, p.y, p.z = x, y, z


def msg_to_tips(msg: PoseArray, fingers: Fingers) -> tuple[int, np.ndarray]:
    """PoseArray → (stamp ns, (n, 3) tips [m]); pose i is finger i's, any frame_id and
    orientation. A finger of task dimension d uses the first d columns (z only when d = 3)."""
    n_fingers = len(finger_names(fingers))
    if len(msg.poses) != n_fingers:
        raise MessageError(f'tip_positions: expected {n_fingers} poses, got {len(msg.poses)}')
    tips = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses], dtype=float)
    return from_time(msg.header.stamp), check_finite(tips, TIPS_WHAT)


# -- torque commands (JointState effort) -----------------------------------------------------

def torques_to_msg(ns: int, u: np.ndarray, fingers: Fingers | None = None) -> JointState:
    """(n, m) inputs (torques [N·m], or each input's SI unit) → JointState named
    ``<finger>/ax0`` … ``<finger>/ax<m−1>`` with efforts (``fingers``: the names, default
    finger_0..)."""
    u = np.asarray(u, dtype=float)
    msg = JointState()
    set_time(msg.header.stamp, ns)
    msg.name = list(_torque_names(finger_names(u.shape[0] if fingers is None else fingers),
                                  u.shape[1]))
    msg.effort = u.ravel().tolist()
    return msg


def msg_to_torques(msg: JointState, fingers: Fingers, m: int = 2) -> tuple[int, np.ndarray]:
    """JointState → (stamp ns, (n, m) efforts [N·m or the inputs' SI unit]) of fingers with
    ``m`` inputs each, ordered by name whatever the message order."""
    names = finger_names(fingers)
    n_fingers = len(names)
    if len(msg.effort) != len(msg.name):
        raise MessageError(f'torque_commands: {len(msg.name)} names but {len(msg.effort)} efforts')
    idx = _order(msg.name, _torque_names(names, m), 'torque_commands')
    effort = np.asarray(msg.effort, dtype=float)[idx].reshape(n_fingers, m)
    return from_time(msg.header.stamp), check_finite(effort, TORQUES_WHAT)


# -- joint states, contacts and the cube ----------------------------------------------------

def joint_states_msg(ns: int, names: list[str], q: np.ndarray, qd: np.ndarray) -> JointState:
    msg = JointState()
    msg.header.stamp = to_time(ns)
    msg.name = names
    msg.position = np.asarray(q, dtype=float).ravel().tolist()
    msg.velocity = np.asarray(qd, dtype=float).ravel().tolist()
    return msg


def contacts_msg(ns: int, force: np.ndarray, fingers: Fingers | None = None) -> JointState:
    """Normal contact force of each finger on the cube [N] as JointState efforts named by finger."""
    msg = JointState()
    msg.header.stamp = to_time(ns)
    msg.name = list(finger_names(len(force) if fingers is None else fingers))
    msg.effort = np.asarray(force, dtype=float).tolist()
    return msg


def cube_pose_msg(ns: int, pose: np.ndarray) -> PoseStamped:
    """The cube's pose [x, y, z, qx, qy, qz, qw] in the hand frame at ``ns``."""
    msg = PoseStamped()
    msg.header.stamp = to_time(ns)
    msg.header.frame_id = 'hand'
    c = pose.tolist()
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = c[:3]
    (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
     msg.pose.orientation.w) = c[3:]
    return msg


# -- state estimate / reference (MultiDOFJointTrajectory) ------------------------------------

def _point(pos, vel, acc, from_start_ns: int) -> MultiDOFJointTrajectoryPoint:
    pt = MultiDOFJointTrajectoryPoint()
    transforms, velocities, accelerations = [], [], []
    for i in range(len(pos)):
        tf = Transform()
        tf.translation.x, tf.translation.y, tf.translation.z = pos[i]
        tf.rotation.w = 1.0
        transforms.append(tf)
        tw = Twist()
        tw.linear.x, tw.linear.y, tw.linear.z = vel[i]
        velocities.append(tw)
        if acc is not None:
            ta = Twist()
            ta.linear.x, ta.linear.y, ta.linear.z = acc[i]
            accelerations.append(ta)
    pt.transforms = transforms
    pt.velocities = velocities
    pt.accelerations = accelerations
    pt.time_from_start = to_duration(from_start_ns)
    return pt


def _pad3(a: np.ndarray) -> list:
    a = np.asarray(a, dtype=float)
    if a.shape[-1] == 2:
        a = np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)
    return a.tolist()


def estimate_to_msg(ns: int, pos: np.ndarray, vel: np.ndarray,
                    fingers: Fingers | None = None) -> MultiDOFJointTrajectory:
    """(n, 2|3) positions [m] and velocities [m/s] → one-point MultiDOFJointTrajectory whose joint
    names are the fingers' (default finger_0..)."""
    msg = MultiDOFJointTrajectory()
    msg.header.stamp = to_time(ns)
    msg.joint_names = list(finger_names(len(pos) if fingers is None else fingers))
    msg.points = [_point(_pad3(pos), _pad3(vel), None, 0)]
    return msg


def msg_to_estimate(msg: MultiDOFJointTrajectory, fingers: Fingers,
                    d: int = 2) -> tuple[int, np.ndarray]:
    """One-point MultiDOFJointTrajectory → (stamp ns, (n, 2d) [p; ṗ]: [X, Y, Ẋ, Ẏ] for d = 2,
    [X, Y, Z, Ẋ, Ẏ, Ż] for d = 3) in the order of ``fingers``, whatever the message's joint
    order."""
    idx = _order(msg.joint_names, list(finger_names(fingers)), 'state_estimate')
    if len(msg.points) != 1:
        raise MessageError(f'state_estimate: expected 1 point, got {len(msg.points)}')
    pt = msg.points[0]
    if len(pt.transforms) != len(msg.joint_names) or len(pt.velocities) != len(msg.joint_names):
        raise MessageError('state_estimate: transforms/velocities do not match joint_names')
    if d == 2:
        x = np.array([(tf.translation.x, tf.translation.y, tw.linear.x, tw.linear.y)
                      for tf, tw in zip(pt.transforms, pt.velocities)], dtype=float)[idx]
    else:
        x = np.array([(tf.translation.x, tf.translation.y, tf.translation.z,
                       tw.linear.x, tw.linear.y, tw.linear.z)
                      for tf, tw in zip(pt.transforms, pt.velocities)], dtype=float)[idx]
    return from_time(msg.header.stamp), check_finite(x, ESTIMATE_WHAT)


def reference_to_msg(ns: int, offsets_ns, pos, vel, acc,
                     fingers: Fingers | None = None) -> MultiDOFJointTrajectory:
    """Horizon of h points (offsets from the stamp) × n fingers: pos, vel, acc (h, n, 2|3)
    (z = 0 for planar tips)."""
    msg = MultiDOFJointTrajectory()
    msg.header.stamp = to_time(ns)
    msg.joint_names = list(finger_names(np.asarray(pos).shape[1] if fingers is None else fingers))
    msg.points = [_point(_pad3(p), _pad3(v), _pad3(a), int(o))
                  for o, p, v, a in zip(offsets_ns, pos, vel, acc)]
    return msg


def msg_to_reference(msg: MultiDOFJointTrajectory, fingers: Fingers, d: int = 2):
    """Horizon message → (stamp ns, times ns (h,), pos, vel, acc (h, n, d)), fingers in the order
    of ``fingers``; d = 3 reads z too."""
    idx = _order(msg.joint_names, list(finger_names(fingers)), 'grasp_reference')
    if not msg.points:
        raise MessageError('grasp_reference: no points')
    m = len(msg.joint_names)
    stamp = from_time(msg.header.stamp)
    times, data = [], []
    for pt in msg.points:
        if len(pt.transforms) != m or len(pt.velocities) != m or len(pt.accelerations) != m:
            raise MessageError('grasp_reference: a point does not hold one entry per finger')
        times.append(stamp + pt.time_from_start.sec * NS + pt.time_from_start.nanosec)
        if d == 2:
            data.append([(tf.translation.x, tf.translation.y, tw.linear.x, tw.linear.y,
                          ta.linear.x, ta.linear.y)
                         for tf, tw, ta in zip(pt.transforms, pt.velocities, pt.accelerations)])
        else:
            data.append([(tf.translation.x, tf.translation.y, tf.translation.z, tw.linear.x,
                          tw.linear.y, tw.linear.z, ta.linear.x, ta.linear.y, ta.linear.z)
                         for tf, tw, ta in zip(pt.transforms, pt.velocities, pt.accelerations)])
    times = np.asarray(times, dtype=np.int64)
    if np.any(np.diff(times) <= 0):
        raise MessageError('grasp_reference: point times are not increasing')
    a = check_finite(np.asarray(data, dtype=float)[:, idx], 'grasp_reference')
    return stamp, times, a[..., 0:d], a[..., d:2 * d], a[..., 2 * d:3 * d]


# -- efforts for a ros2_control forward_command_controller (Float64MultiArray) ---------------

def effort_array_order(joints: Sequence[str], fingers: Fingers, m: int = 2) -> np.ndarray:
    """Index into ``u.ravel()`` of the input each of ``joints`` carries, in that order.

    ``joints`` names, for each joint of a ros2_control ``forward_command_controller`` (effort
    interface) in the order of its ``joints`` list, the input that drives it: ``<finger>/ax<k>``,
    k < ``m``. Every input of ``fingers`` appears exactly once.

    Raises:
        ValueError: an unknown or repeated torque name, or a torque left out.
    """
    torques = _torque_names(finger_names(fingers), m)
    joints = list(joints)
    unknown = [j for j in joints if j not in torques]
    if unknown:
        raise ValueError(f'{unknown[0]!r} is not a torque of these fingers (the torques are '
                         f'{", ".join(torques)})')
    repeated = sorted({j for j in joints if joints.count(j) > 1})
    if repeated:
        raise ValueError(f'{repeated[0]!r} appears more than once')
    missing = [t for t in torques if t not in joints]
    if missing:
        raise ValueError(f'no joint carries {", ".join(missing)} (each torque drives one joint)')
    return np.array([torques.index(j) for j in joints], dtype=np.intp)
