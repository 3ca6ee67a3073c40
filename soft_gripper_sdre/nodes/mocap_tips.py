"""The mocap_tips node: fingertip positions from a motion-capture system, as ``tip_positions``.

Motion-capture drivers (VRPN, OptiTrack/NatNet and others) publish one geometry_msgs/PoseStamped
per tracked body, in the capture's world frame. This node subscribes one pose topic per finger
(``pose_topics[i]``, the rigid body on finger ``finger_names[i]``'s tip), takes each finger's
base pose in the world (``base_positions``, ``base_orientations``: where the finger is mounted,
measured once) and publishes ``tip_positions``: pose i is finger i's tip in its base frame,
``R_iᵀ (p_world − t_i)`` [m], all three coordinates (a planar finger's model reads x and y, a
3-D finger's z too), identity orientation, frame ``finger_bases``.

**Sets.** A message goes out once every finger has a new pose since the previous message, each
pose used once, and is stamped with the newest stamp of the set: the measurement's time, not the
time of arrival. The stamps of one set lie within ``max_spread`` of each other (a capture frame
stamps its bodies alike); a pose older than that behind the newest is of an earlier frame and is
dropped (``behind``), its finger's next pose awaited. A set whose stamp is not after the previous
message's is dropped (``out_of_order``), so the stamps of ``tip_positions`` always increase. A
finger's pose replaced by a newer one before its set was complete counts ``superseded``.
/diagnostics carries the spread of the published sets (``spread_us_p50/p99/max``).

**Bad frames** are refused and counted (``bad_poses``, and per finger ``bad_poses <finger>``),
with a throttled warning naming the finger and why: a NaN or Inf in the position or the
orientation, an orientation whose norm is off 1 by more than ``QUATERNION_TOLERANCE`` (an all-zero
quaternion is what some drivers send for a body they lost), an unset stamp (0), and a
``header.frame_id`` other than ``world_frame`` when that is set. The finger's previous pose
stays pending.

**A missing finger** (no good pose for ``pose_timeout`` of wall time) pauses the whole message:
a PoseArray holds every finger or none, and the loop's nodes refuse a message with fewer poses or
a NaN. The node WARNs naming the finger (log, throttled, and /diagnostics at WARN with
``missing`` listing the fingers), counts the episode (``missing_events``), and publishes again at
the next complete set once the finger is back. The estimator bridges a short pause
(``max_bridge``) and resets after a longer one. /diagnostics is also at WARN while bad poses
arrive or while every finger sends poses but no set completes (stamps more than ``max_spread``
apart: the drivers' clocks disagree).

Bad parameters stop the node at start-up naming them (exit status 2): one pose topic per
finger, three base coordinates and four quaternion components (x, y, z, w) per finger, finite,
each base quaternion of norm 1 within 1e-3 (then normalised).
"""
from __future__ import annotations

import math
import time

from geometry_msgs.msg import PoseArray, PoseStamped
import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import (
    OK,
    WARN,
    Diagnostics,
    LatencyWindow,
    ThrottledLogger,
    run,
)
from soft_gripper_sdre.nodes.params import (
    RELIABILITIES,
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    with_reliability,
)
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS

#: a pose's orientation may be off unit norm by this much (the capture's own rounding)
QUATERNION_TOLERANCE = 0.01
#: a base orientation parameter may be off unit norm by this much (typed decimals); it is then
#: normalised
BASE_QUATERNION_TOLERANCE = 1e-3
#: the frame_id of the published tips (each pose in its own finger's base frame)
TIPS_FRAME = 'finger_bases'

_FOUR = 4                                   # the default finger_names' count

PARAMS = (
    finger_names_param('the fingers in message order: pose i of tip_positions is finger '
                       'finger_names[i]'),
    Param('pose_topics', [f'mocap/finger_{i}/pose' for i in range(_FOUR)],
          'the geometry_msgs/PoseStamped topic of the body on each finger\'s tip, one per '
          'finger in the order of finger_names (VRPN: /vrpn_mocap/<body>/pose)', read_only=True),
    Param('base_positions', [0.0] * (3 * _FOUR), "each finger's base origin in the capture's "
          'world frame: x, y, z per finger, in the order of finger_names', 'm', read_only=True),
    Param('base_orientations', [0.0, 0.0, 0.0, 1.0] * _FOUR, "each finger's base orientation in "
          'the world frame: a unit quaternion x, y, z, w per finger, in the order of '
          'finger_names', read_only=True),
    Param('world_frame', '', "the header.frame_id the poses must carry; '' = any", read_only=True),
    Param('max_spread', 0.005, 'the stamps of one published set lie within this of each other; '
          'an older pose is of an earlier capture frame and is dropped', 's', 0.0, 1.0,
          read_only=True),
    Param('pose_timeout', 0.2, 'a finger without a good pose for this long (wall time) is missing: '
          'tip_positions pauses and the node warns', 's', 0.001, 60.0, read_only=True),
    Param('tips_reliability', 'reliable', "reliability of the tip_positions publisher: 'reliable' "
          "(every reader matches) or 'best_effort' (the sensor-data QoS of a driver; only "
          "readers with tips_reliability:=best_effort match)", choices=RELIABILITIES,
          read_only=True),
)


def quaternion_matrix(q) -> np.ndarray:
    """The rotation matrix of the unit quaternion ``q`` = (x, y, z, w)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def bases(names, positions, orientations) -> tuple[np.ndarray, np.ndarray]:
    """The base origins (n, 3) [m] and rotations (n, 3, 3) from the parameters.

    Raises:
        ParameterError: naming the parameter: a wrong length, a non-finite value, or a
            quaternion whose norm is off 1 by more than ``BASE_QUATERNION_TOLERANCE``.
    """
    n = len(names)
    for name, values, per in (('base_positions', positions, 3),
                              ('base_orientations', orientations, 4)):
        if len(values) != per * n:
            raise ParameterError(f'parameter {name!r}: {per} numbers per finger, {per * n} for '
                                 f'{n} fingers {list(names)}, got {len(values)}')
        if not all(math.isfinite(v) for v in values):
            raise ParameterError(f'parameter {name!r}: every number must be finite, got '
                                 f'{list(values)}')
    quats = np.asarray(orientations, dtype=float).reshape(n, 4)
    norms = np.linalg.norm(quats, axis=1)
    for finger, norm in zip(names, norms):
        if abs(norm - 1.0) > BASE_QUATERNION_TOLERANCE:
            raise ParameterError(f"parameter 'base_orientations': {finger}'s quaternion has norm "
                                 f'{norm:.6g}, not 1 (x, y, z, w)')
    rotations = np.stack([quaternion_matrix(q / nq) for q, nq in zip(quats, norms)])
    return np.asarray(positions, dtype=float).reshape(n, 3), rotations


def pose_problem(msg: PoseStamped, world_frame: str) -> str | None:
    """Why a mocap pose is refused (module doc), or None."""
    p, q = msg.pose.position, msg.pose.orientation
    values = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in values):
        return f'not finite: position {(p.x, p.y, p.z)}, orientation {(q.x, q.y, q.z, q.w)}'
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        return f'orientation norm {norm:.4g}, not 1 (a lost body?)'
    if msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 0:
        return 'unset stamp (0)'
    if world_frame and msg.header.frame_id != world_frame:
        return f"frame_id {msg.header.frame_id!r}, not the world_frame {world_frame!r}"
    return None


class MocapTipsNode(Node):
    """Per-finger mocap poses → ``tip_positions`` in each finger's base frame (module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('mocap_tips', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.names = tuple(p['finger_names'])
        n = len(self.names)
        if len(p['pose_topics']) != n:
            raise ParameterError(f"parameter 'pose_topics': one topic per finger, {n} for "
                                 f'{list(self.names)}, got {len(p["pose_topics"])}')
        topics = []
        for topic in p['pose_topics']:
            try:
                topics.append(self.resolve_topic_name(topic))
            except Exception as exc:            # noqa: BLE001 — rclpy raises its RCLError here
                raise ParameterError(f"parameter 'pose_topics': {topic!r} is not a topic name: "
                                     f'{str(exc).splitlines()[0]}') from None
        if len(set(topics)) != n:
            raise ParameterError(f"parameter 'pose_topics': a topic per finger, each once, got "
                                 f'{list(p["pose_topics"])}')
        self.origins, self.rotations = bases(self.names, p['base_positions'],
                                             p['base_orientations'])
        self.timeout = p['pose_timeout']
        self.spread_ns = int(round(p['max_spread'] * 1e9))
        #: per finger, the pending pose: (stamp [ns], world position (3,)) or None
        self.pending: list[tuple[int, np.ndarray] | None] = [None] * n
        now = time.monotonic()
        self.last_good = [now] * n              # monotonic time of each finger's last good pose
        self.last_stamp = 0                     # the stamp of the previous message [ns]
        self.missing: tuple[str, ...] = ()
        self.spread = LatencyWindow(2000)
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self, hardware_id='mocap_tips')
        for name in ('published', 'bad_poses', 'superseded', 'behind', 'out_of_order',
                     'missing_events'):
            self.diag.counters[name] = 0
        self._reported = {'published': 0, 'bad_poses': 0}
        self._poses_since_report = 0
        self.diag.before_publish.append(self._refresh_diagnostics)
        self.msg = cv.tips_to_msg(0, np.zeros((n, 3)), frame_id=TIPS_FRAME)
        self.pub = self.create_publisher(PoseArray, TIP_POSITIONS,
                                         with_reliability(LOOP_QOS, p['tips_reliability']))
        self.subs = [self.create_subscription(
            PoseStamped, topic, lambda msg, i=i: self.on_pose(i, msg), qos_profile_sensor_data)
            for i, topic in enumerate(topics)]
        self._timer = self.create_timer(min(0.05, self.timeout / 2), self._check_missing)
        self.diag.set_status(OK, f'waiting for the poses of {", ".join(self.names)}')
        self.get_logger().info('tips of ' + ', '.join(
            f'{name} from {topic}' for name, topic in zip(self.names, topics))
            + f' to {self.pub.topic_name} ({p["tips_reliability"]})')

    # -- poses -------------------------------------------------------------------------------
    def on_pose(self, i: int, msg: PoseStamped) -> None:
        """Take finger ``i``'s pose, refused if bad; publish once the set is complete."""
        name = self.names[i]
        self.diag.count(f'poses {name}')
        self._poses_since_report += 1
        why = pose_problem(msg, self.p['world_frame'])
        if why:
            self.diag.count('bad_poses')
            self.diag.count(f'bad_poses {name}')
            self.log.warn(f'bad {name}', f'{name}: pose refused: {why}')
            return
        if self.pending[i] is not None:
            self.diag.count('superseded')
        p = msg.pose.position
        self.pending[i] = (cv.from_time(msg.header.stamp), np.array([p.x, p.y, p.z]))
        self.last_good[i] = time.monotonic()
        self._try_publish()

    def _try_publish(self) -> None:
        if any(pose is None for pose in self.pending):
            return
        stamps = [pose[0] for pose in self.pending]
        newest = max(stamps)
        behind = [i for i, s in enumerate(stamps) if newest - s > self.spread_ns]
        if behind:
            for i in behind:
                self.pending[i] = None
            self.diag.count('behind', len(behind))
            return
        pending, self.pending = self.pending, [None] * len(self.names)
        if newest <= self.last_stamp:
            self.diag.count('out_of_order')
            return
        world = np.stack([pose[1] for pose in pending])
        tips = np.einsum('nji,nj->ni', self.rotations, world - self.origins)     # Rᵀ (p − t)
        cv.fill_tips(self.msg, newest, tips)
        self.pub.publish(self.msg)
        self.last_stamp = newest
        self.spread.add((newest - min(stamps)) * 1e-9)
        self.diag.count('published')

    # -- missing fingers and the status ------------------------------------------------------
    def _check_missing(self) -> None:
        now = time.monotonic()
        missing = tuple(name for name, t in zip(self.names, self.last_good)
                        if now - t > self.timeout)
        if missing and missing != self.missing:
            self.diag.count('missing_events')
        if missing:
            self.log.warn('missing', f'no good pose of {", ".join(missing)} for over '
                          f'{self.timeout:g} s: tip_positions paused until every finger has one')
        elif self.missing:
            self.get_logger().info(f'{", ".join(self.missing)} back: tip_positions resumes')
        self.missing = missing

    def _refresh_diagnostics(self) -> None:
        self.diag.values['missing'] = ', '.join(self.missing)
        self.diag.values.update(self.spread.summary('spread_us'))
        published = self.diag.counters['published'] - self._reported['published']
        bad = self.diag.counters['bad_poses'] - self._reported['bad_poses']
        if self.missing:
            self.diag.set_status(WARN, f'no good pose of {", ".join(self.missing)} for over '
                                 f'{self.timeout:g} s: tip_positions paused')
        elif bad:
            self.diag.set_status(WARN, f'{bad} bad pose(s) refused since the last report')
        elif self._poses_since_report and not published:
            self.diag.set_status(WARN, 'poses arrive but no set completes: their stamps lie '
                                 f'more than max_spread ({self.p["max_spread"]:g} s) apart')
        elif published:
            self.diag.set_status(OK, f'publishing the tips of {len(self.names)} fingers')
        self._reported = {'published': self.diag.counters['published'],
                          'bad_poses': self.diag.counters['bad_poses']}
        self._poses_since_report = 0


def main(args=None) -> int:
    return run(MocapTipsNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
