"""The trajectory node: publishes the grasp reference as short horizons, driven by sim time.

Subscribes ``tip_positions``; publishes ``grasp_reference`` and ``/diagnostics``. The first tip
message is the rest pose of :class:`~soft_gripper_sdre.control.trajectory.GraspTrajectory` (as in
:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`), and a horizon is published at once; after
that one is published on each tip message whose stamp has reached the next multiple of
``publish_period``. Publication is event-driven on tip stamps, never on wall timers, so a
lockstep run is deterministic.

A horizon published for stamp t holds the points at the ABSOLUTE times k·``horizon_step`` from
floor(t / step)·step up to the first grid time ≥ t + ``horizon``: header stamp = the first of
them, ``time_from_start`` = each point's offset from it, positions / velocities / accelerations
from ``GraspTrajectory.sample``. Two horizons therefore hold identical points wherever they
overlap, and the controller's sample (:func:`soft_gripper_sdre.control.horizon.sample_horizon`) does not
depend on which one it uses.

Malformed tip messages (wrong number of poses, NaN/Inf) and stamps not newer than the last are
rejected with a throttled warning and counted; a backwards jump of more than ``reset_on_jump``
seconds (a simulator restart) starts over: the next message is the rest pose again.

A node restarted mid-run (after a crash) must not take the tips it first sees as the rest pose:
they are wherever the grasp left them. Pass the rest pose the first instance used (its
``/diagnostics`` value ``rest_pose``) as the ``rest_pose`` parameter; a first tip message after
``t_start`` without it is flagged (``late_start``, WARN).
"""
from __future__ import annotations

from dataclasses import fields

from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.node import Node
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import cdr, conversions as cv
from soft_gripper_sdre.nodes.common import Diagnostics, run
from soft_gripper_sdre.nodes.params import Param, ParameterError, declare_all, on_runtime_change
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, LOOP_QOS, REFERENCE_QOS, TIP_POSITIONS
from soft_gripper_sdre.control.trajectory import OTHERS_MODES, GraspProfile, GraspTrajectory

_DEFAULTS = GraspProfile()     # the parameters' defaults
PROFILE_FIELDS = tuple(f.name for f in fields(GraspProfile))

PARAMS = (
    Param('n_fingers', 4, 'fingers in each tip_positions message', '', 1, 4, read_only=True),
    Param('t_start', _DEFAULTS.t_start, 'hold at rest before the fingers move', 's', 0.0, 1e4, read_only=True),
    Param('t_close', _DEFAULTS.t_close, 'duration of the closing motion', 's', 1e-3, 1e4, read_only=True),
    Param('t_hold', _DEFAULTS.t_hold, 'time spent closed', 's', 0.0, 1e4, read_only=True),
    Param('t_open', _DEFAULTS.t_open, 'duration of the opening motion', 's', 1e-3, 1e4, read_only=True),
    Param('close_distance', _DEFAULTS.close_distance, 'travel of the grasping fingers along +Y (toward '
          'the cube)', 'm', -0.1, 0.1, read_only=True),
    Param('side_distance', _DEFAULTS.side_distance, 'travel of the grasping fingers along X while closing',
          'm', -0.1, 0.1, read_only=True),
    Param('open_distance', _DEFAULTS.open_distance, "travel of the other fingers along −Y when others = "
          "'open'", 'm', -0.1, 0.1, read_only=True),
    Param('contact_distance', _DEFAULTS.contact_distance, 'travel along +Y at which a grasping tip touches '
          'the cube (scoring only)', 'm', -0.1, 0.1, read_only=True),
    Param('contact_margin', _DEFAULTS.contact_margin, 'clearance from the cube below which a phase is no '
          'longer free space (scoring only)', 'm', 0.0, 0.1, read_only=True),
    Param('grasp_fingers', list(_DEFAULTS.grasp_fingers), 'indices of the two opposite fingers that grasp',
          read_only=True),
    Param('others', 'open', 'what the non-grasping fingers do', choices=OTHERS_MODES, read_only=True),
    Param('horizon', 0.1, 'reference time covered beyond each publishing stamp (>= 2 × '
          'publish_period)', 's', 1e-3, 60.0, read_only=True),
    Param('horizon_step', 0.005, 'spacing of the absolute time grid of the horizon points (<= '
          'horizon)', 's', 1e-4, 1.0, read_only=True),
    Param('publish_period', 0.02, 'sim time between published horizons', 's', 1e-4, 30.0,
          read_only=True),
    Param('rest_pose', '', "rest tips as 'x0, y0, x1, y1, …' (finger base frames); '' = the first "
          "tip message. Give it when restarting the node mid-run: the tips then are not at rest", 'm',
          read_only=True),
    Param('reset_on_jump', 0.1, 'a backwards stamp jump larger than this restarts from a new rest '
          'pose', 's', 1e-3, 1e3),
)


def _rest_pose(text: str, n: int) -> np.ndarray | None:
    """The (n, 2) rest pose of the ``rest_pose`` parameter, or None if it is empty."""
    if not text.strip():
        return None
    try:
        values = np.array([float(v) for v in text.replace(',', ' ').split()])
    except ValueError:
        raise ParameterError(f"parameter 'rest_pose': {text!r} is not a list of numbers") from None
    if values.size != 2 * n or not np.all(np.isfinite(values)):
        raise ParameterError(f"parameter 'rest_pose': needs {2 * n} finite numbers (x, y of each "
                             f'finger), got {text!r}')
    return values.reshape(n, 2)


def _profile(p: dict) -> GraspProfile:
    """The GraspProfile of the parameters; ParameterError names the offending one."""
    values = {name: p[name] for name in PROFILE_FIELDS}
    values['grasp_fingers'] = tuple(int(i) for i in values['grasp_fingers'])
    try:
        profile = GraspProfile(**values)
    except ValueError as exc:
        name = next((f for f in PROFILE_FIELDS if str(exc).startswith(f)), 'grasp profile')
        raise ParameterError(f'parameter {name!r}: {exc}') from None
    if any(i >= p['n_fingers'] for i in profile.grasp_fingers):
        raise ParameterError(f"parameter 'grasp_fingers': {list(profile.grasp_fingers)} out of range "
                             f"for n_fingers = {p['n_fingers']}")
    return profile


class TrajectoryNode(Node):
    """Grasp reference horizons on ``grasp_reference``, stepped by tip stamps (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('trajectory', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.n = p['n_fingers']
        self.profile = _profile(p)
        self.horizon_ns = int(round(p['horizon'] * cv.NS))
        self.step_ns = int(round(p['horizon_step'] * cv.NS))
        self.period_ns = int(round(p['publish_period'] * cv.NS))
        if self.horizon_ns < 2 * self.period_ns:
            raise ParameterError(f"parameter 'horizon': {p['horizon']} s must be >= 2 × publish_period "
                                 f"({p['publish_period']} s) so a horizon always covers the next one")
        if self.step_ns > self.horizon_ns:
            raise ParameterError(f"parameter 'horizon_step': {p['horizon_step']} s must be <= horizon "
                                 f"({p['horizon']} s)")
        self.jump_ns = int(round(p['reset_on_jump'] * cv.NS))
        self.fixed_rest = _rest_pose(p['rest_pose'], self.n)
        on_runtime_change(self, PARAMS, apply=self._apply)

        self.traj: GraspTrajectory | None = None
        self.last_ns = -1                       # stamp of the last accepted tip message
        self.next_pub_ns = 0                    # next publish instant (multiple of publish_period)

        self.cdr_tips = cdr.tips_codec(self.n)     # CDR bytes read at fixed offsets (nodes/cdr.py)
        self.pub = self.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        self.sub = self.create_subscription(PoseArray, TIP_POSITIONS, self.on_tips, LOOP_QOS, raw=True)
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_tips)
        pr = self.profile
        self.get_logger().info(
            f'grasp with fingers {list(pr.grasp_fingers)}, others {pr.others}: start {pr.t_start:g} s, '
            f'close {pr.t_close:g} s, hold {pr.t_hold:g} s, open {pr.t_open:g} s; horizons of '
            f'{p["horizon"]:g} s every {p["publish_period"]:g} s on a {1e3 * p["horizon_step"]:g} ms grid')

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.jump_ns = int(round(self.p['reset_on_jump'] * cv.NS))

    def on_tips(self, data: bytes) -> None:
        try:
            stamp, tips = self.cdr_tips.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_message', f'rejected: {exc}')
            return
        if self.traj is not None and stamp <= self.last_ns:
            if self.last_ns - stamp <= self.jump_ns:
                self.diag.problem('stale', f'rejected: tip_positions stamp {stamp} ns is not newer '
                                  f'than the last {self.last_ns} ns')
                return
            self.diag.problem('resets', f'tip_positions stamp jumped back from '
                              f'{self.last_ns / cv.NS:.4f} s to {stamp / cv.NS:.4f} s; taking a new rest pose')
            self.traj = None
        self.last_ns = stamp
        self.diag.good('tips', 'publishing')
        if self.traj is None:
            rest = self.fixed_rest
            if rest is None:
                rest = tips
                if stamp > int(self.profile.t_start * cv.NS):
                    self.diag.problem('late_start', f'first tip_positions at t = {stamp / cv.NS:.4f} s, '
                                      'after the grasp began: taking them as the rest pose (give '
                                      'rest_pose when restarting mid-run)')
            self.traj = GraspTrajectory(rest, self.profile)
            self.diag.values['rest_pose'] = ', '.join(f'{v:.6g}' for v in self.traj.rest.ravel().tolist())
            self.diag.publish()      # at once, not at the next 1 s tick: a restart is given this value
            rest = ', '.join(f'({1e3 * x:.2f}, {1e3 * y:.2f})' for x, y in self.traj.rest.tolist())
            self.get_logger().info(f'rest pose at t = {stamp / cv.NS:.4f} s [mm]: {rest}')
            self.publish(stamp)
        elif stamp >= self.next_pub_ns:
            self.publish(stamp)

    def publish(self, stamp: int) -> None:
        """Publish the horizon for ``stamp`` and schedule the next publish instant."""
        start = stamp // self.step_ns * self.step_ns
        count = -(-(stamp + self.horizon_ns - start) // self.step_ns) + 1     # ceil, both ends
        offsets = self.step_ns * np.arange(count, dtype=np.int64)
        ref = self.traj.sample((start + offsets) / cv.NS)
        self.pub.publish(cv.reference_to_msg(start, offsets, ref.pos, ref.vel, ref.acc))
        self.next_pub_ns = (stamp // self.period_ns + 1) * self.period_ns
        self.diag.count('references')


def main(args=None) -> int:
    return run(TrajectoryNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
