"""The trajectory node: publishes the planned grasp as a whole, once per plan.

Subscribes ``tip_positions`` only until it has a rest pose (``rest_samples`` messages, one by
default), and ``/clock`` (100 Hz of sim time) to notice a restarted simulator; publishes
``grasp_reference`` and ``/diagnostics``. The rest pose of
:class:`~soft_gripper_sdre.control.trajectory.GraspTrajectory` is the first tip message (as in
:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`), the mean of the first
``rest_samples`` of them, or the ``rest_pose`` parameter. One message carries the tips' noise
into the whole plan: a rest pose 0.1 mm off where a finger rests is a hold the law must pull or
bend the finger to (a tendon or chamber at rest is slack, so it cannot push back), and on the
three-tendon segment that first command bent a finger by 1.2 mm at the plan's start. The mean
of N messages has 1/√N of that noise; training's ``params.yaml`` asks for a quarter second of
tips. The plan then goes out at once, on a transient-local topic (a controller
or recorder that starts later still gets it), and the tip subscription is dropped: the node
receives nothing per control period.

**The plan starts when its controller can answer** (``start_when``). With ``controller`` (the
default) the rest pose and the origin are taken from the first tips heard once the graph shows a
controller ready to answer: a node named ``controller_node`` in this node's namespace subscribes
the plan (the controller opens its topics only after its model is loaded and its kernels compiled)
and ``state_estimate`` has a writer (an estimator, or the controller's own with
``--with-estimator``). The controller answers nothing before it has a plan, so the node cannot wait
for a command; it waits for that subscription instead, and the controller's first command follows
the plan's origin by the loop's latency. Tips heard before are not planned from (``early_tips``),
except the newest of them once the controller shows up before newer ones come (the graph is
looked at again every ``RECHECK_S`` of wall time while the plan waits); the wait goes to the
log (at the start, then a WARN every ``WAIT_WARN_S`` of wall time) and to /diagnostics
(``start_when``, ``waiting_for``, ``waited_s``). With ``tips`` the plan starts at the first tips
whatever the graph holds (a test without a controller, a controller of another name). In the
simulator's lockstep graph both give the same plan: the simulator sends its first tips only once
every node is wired (docs/design/loop_rules.md, "Start"), so the controller is there and the
plan starts at 0 (from those tips, held, when this node learns the controller's name a little
after its subscription matched). With ``rest_pose`` the plan goes out at once either way.

**Time comes from the data.** The plan starts at its origin: the stamp of the tips the rest pose
is taken from (the last of them), whatever clock the driver stamps with (sim time from 0, or wall
time), or the ``start_at`` parameter; with ``rest_pose`` and without ``start_at`` the origin is
0. The plan holds the points at the times origin + k·``horizon_step`` up to the first grid time
at or after the grasp's end, where the fingers are back at rest: header stamp = the origin,
``time_from_start`` = k·``horizon_step``, positions / velocities / accelerations from
``GraspTrajectory.sample`` at k·``horizon_step``. After its last point the reference stays there
(:func:`soft_gripper_sdre.control.horizon.sample_plan`). The simulator's first tips are stamped 0,
so its plan starts at 0.

A ``/clock`` stamp more than ``reset_on_jump`` behind the newest one means the simulator
restarted: the node takes a new rest pose from the next tips, and a new origin: the time
/clock jumped back to, the new run's start (the tip subscription, made again only now, misses the
new run's first tips). With ``rest_pose`` it publishes its plan again. The controller forgets a
plan made for the old run. A ``start_at`` that was given stays. Malformed tip or clock messages
(wrong number of poses, NaN/Inf) are rejected with a throttled warning and counted.

**The finger's shape.** ``task_dim`` is the tips' task dimension d: 2 plans in (X, Y) (the
tips' z ignored), 3 in (X, Y, Z) (the plan then carries z). The grasping fingers close along
``direction`` (d values; [0.0] = +Y), or through the waypoints of ``close_path`` (d values per
point, relative to rest; [0.0] = none; e.g. the curve a one-input finger's tip can reach, taken
from its data), and the others open along −``direction``
(:class:`~soft_gripper_sdre.control.trajectory.GraspTrajectory`).

A node restarted mid-run (after a crash) must not take the tips it first sees as the rest pose
and their stamp as the start: the fingers are wherever the grasp left them. Pass the values the
first instance published in its ``/diagnostics`` (``rest_pose`` and ``start_at``) as parameters;
it then publishes the very same plan at once, without a tip. With ``start_at`` and without
``rest_pose``, a first tip message more than ``t_start`` after ``start_at`` is flagged
(``late_start``, WARN).
"""
from __future__ import annotations

from dataclasses import fields
import decimal
import math
import re
import time

from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.trajectory import OTHERS_MODES, GraspProfile, GraspTrajectory
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import Diagnostics, run
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    numbers,
    numbers_param,
    on_runtime_change,
    tips_reliability_param,
    with_reliability,
)
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec
from soft_gripper_sdre.nodes.topics import (
    CLOCK,
    CLOCK_QOS,
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
)

_DEFAULTS = GraspProfile()     # the parameters' defaults
PROFILE_FIELDS = tuple(f.name for f in fields(GraspProfile))
#: most points a plan may hold: it is one message (about 640 bytes a point for four fingers)
MAX_PLAN_POINTS = 20_000
#: start_when controller: a WARN in the log every this much wall time while the plan waits [s]
WAIT_WARN_S = 10.0
#: start_when controller: while the plan waits, the graph is looked at again this often [s] of
#: wall time, so the newest tips heard are planned from once the controller shows up even when
#: no newer ones come (a lockstep simulator waits for its first tips to be answered)
RECHECK_S = 0.01

def _node_name_problem(name: str) -> str | None:
    """Why ``name`` is not a ROS node name (a letter, then letters, digits and '_'), or None."""
    if re.fullmatch(r'[A-Za-z][A-Za-z0-9_]*', name):
        return None
    return f'{name!r} is not a node name (a letter, then letters, digits and _)'


PARAMS = (
    finger_names_param('the fingers: pose i of tip_positions is finger i; the joint names of '
                       'grasp_reference'),
    Param('t_start', _DEFAULTS.t_start, 'hold at rest before the fingers move', 's', 0.0, 1e4,
          read_only=True),
    Param('t_close', _DEFAULTS.t_close, 'duration of the closing motion', 's', 1e-3, 1e4,
          read_only=True),
    Param('t_hold', _DEFAULTS.t_hold, 'time spent closed', 's', 0.0, 1e4, read_only=True),
    Param('t_open', _DEFAULTS.t_open, 'duration of the opening motion', 's', 1e-3, 1e4,
          read_only=True),
    Param('task_dim', 2, "the tips' task dimension: 2 plans in (X, Y), the tips' z ignored; 3 "
          'plans in (X, Y, Z)', '', 2, 3, read_only=True),
    numbers_param('direction', 'the direction the grasping fingers close along, task_dim '
                  "values [x, y(, z)] (normalised); '' (the default) = +Y, toward the cube"),
    numbers_param('close_path', 'waypoints the grasping fingers close through instead of the '
                  'straight move, relative to rest: task_dim values per point, [x0, y0, x1, y1, '
                  "…] (the last is the closed pose; e.g. the curve a one-input finger's tip can "
                  "reach); '' (the default) = the straight move along direction", 'm'),
    Param('close_distance', _DEFAULTS.close_distance, 'travel of the grasping fingers along +Y '
          '(direction; toward the cube)', 'm', -0.1, 0.1, read_only=True),
    Param('side_distance', _DEFAULTS.side_distance, 'travel of the grasping fingers along X while '
          'closing', 'm', -0.1, 0.1, read_only=True),
    Param('open_distance', _DEFAULTS.open_distance, "travel of the other fingers along −Y when "
          "others = 'open'", 'm', -0.1, 0.1, read_only=True),
    Param('close_to', '', "where the grasping fingers close to along Y in their base frames, "
          "anchoring the closed pose to the hand: each travels close_to − its rest Y (e.g. the "
          "learned model's rest Y + close_distance, so a finger that rests elsewhere still reaches "
          "the cube); '' = close_distance from rest", 'm', read_only=True),
    Param('contact_distance', _DEFAULTS.contact_distance, 'travel along +Y at which a grasping tip '
          'touches the cube (scoring only)', 'm', -0.1, 0.1, read_only=True),
    Param('contact_margin', _DEFAULTS.contact_margin, 'clearance from the cube below which a phase '
          'is no longer free space (scoring only)', 'm', 0.0, 0.1, read_only=True),
    Param('grasp_fingers', list(_DEFAULTS.grasp_fingers), 'indices into finger_names of the '
          'fingers that close on the object (two opposite ones in the hand)', read_only=True),
    Param('others', 'open', 'what the non-grasping fingers do', choices=OTHERS_MODES,
          read_only=True),
    Param('horizon_step', 0.005, 'spacing of the absolute time grid of the plan\'s points', 's',
          1e-4, 1.0, read_only=True),
    Param('rest_pose', '', "rest tips as 'x0, y0, x1, y1, …' (finger base frames; x, y, z of each "
          "with task_dim 3); '' = the first "
          "tip message. Give it when restarting the node mid-run: the tips then are not at rest",
          'm', read_only=True),
    Param('rest_samples', 1, 'tip messages averaged for the rest pose: their mean is the plan\'s '
          'rest, the last one\'s stamp its origin (each message\'s noise averaged down by the '
          'square root of their number); 1 = the first tip message', '', 1, 100000,
          read_only=True),
    Param('start_at', '', "when the plan starts (its origin), an absolute time in s on the "
          "clock of the tip stamps, e.g. '1767225600.25'; '' = the stamp of the tips the rest "
          "pose is taken from, or 0 with rest_pose. Give it, with rest_pose, when restarting the "
          'node mid-run', 's', read_only=True),
    Param('reset_on_jump', 0.1, 'a backwards /clock jump larger than this (a restarted simulator) '
          'takes a new rest pose', 's', 1e-3, 1e3),
    Param('start_when', 'controller', "when the plan starts: 'controller' at the first tips heard "
          'once a controller (controller_node) subscribes the plan and state_estimate has a '
          "writer; 'tips' at the first tips, whatever the graph holds", choices=('controller',
                                                                                  'tips'),
          read_only=True),
    Param('controller_node', 'controller', "start_when controller: the name of the controller "
          "node in this node's namespace", rule=_node_name_problem, read_only=True),
    tips_reliability_param(),
)


def _rest_pose(text: str, n: int, d: int = 2) -> np.ndarray | None:
    """The (n, d) rest pose of the ``rest_pose`` parameter, or None if it is empty."""
    if not text.strip():
        return None
    try:
        values = np.array([float(v) for v in text.replace(',', ' ').split()])
    except ValueError:
        raise ParameterError(f"parameter 'rest_pose': {text!r} is not a list of numbers") from None
    if values.size != d * n or not np.all(np.isfinite(values)):
        axes = 'x, y' if d == 2 else 'x, y, z'
        raise ParameterError(f"parameter 'rest_pose': needs {d * n} finite numbers ({axes} of "
                             f'each finger), got {text!r}')
    return values.reshape(n, d)


def _close_to(text: str) -> float | None:
    """The ``close_to`` parameter [m], or None if it is empty."""
    if not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and abs(value) <= 0.1):
        raise ParameterError(f"parameter 'close_to': {text!r} is not a coordinate in "
                             "[-0.1, 0.1] m (or '')")
    return value


def _start_at(text: str) -> int | None:
    """The ``start_at`` parameter as an exact time [ns], or None if it is empty."""
    if not text.strip():
        return None
    try:
        value = decimal.Decimal(text.strip())
    except decimal.InvalidOperation:
        value = decimal.Decimal('NaN')
    if not (value.is_finite() and 0 <= value < 2**62 // cv.NS):
        raise ParameterError(f"parameter 'start_at': {text!r} is not a time >= 0 in s (or '')")
    return int(value * cv.NS)


def format_time(ns: int) -> str:
    """``ns`` as exact seconds, the way ``start_at`` reads it ('1767225600.250000000')."""
    sign, ns = ('-', -ns) if ns < 0 else ('', ns)
    return f'{sign}{ns // cv.NS}.{ns % cv.NS:09d}'


def _profile(p: dict) -> GraspProfile:
    """The GraspProfile of the parameters; ParameterError names the offending one."""
    values = {name: p[name] for name in PROFILE_FIELDS}
    values['grasp_fingers'] = tuple(int(i) for i in values['grasp_fingers'])
    values['close_to'] = _close_to(values['close_to'])
    d = int(p['task_dim'])
    for name, per in (('direction', 'values'), ('close_path', 'values per waypoint')):
        given = numbers(values[name], name)
        if given is None:
            values[name] = None
            continue
        if len(given) % d or (name == 'direction' and len(given) != d):
            raise ParameterError(f'parameter {name!r}: needs task_dim = {d} {per}, got {given}')
        values[name] = tuple(given)
    try:
        profile = GraspProfile(**values)
    except ValueError as exc:
        name = next((f for f in PROFILE_FIELDS if str(exc).startswith(f)), 'grasp profile')
        raise ParameterError(f'parameter {name!r}: {exc}') from None
    names = p['finger_names']
    if any(i >= len(names) for i in profile.grasp_fingers):
        raise ParameterError(f"parameter 'grasp_fingers': {list(profile.grasp_fingers)} are not "
                             f'all indices into finger_names {names} (0 to {len(names) - 1})')
    try:
        GraspTrajectory(np.zeros((len(names), d)), profile, d)
    except ValueError as exc:
        name = next((f for f in ('close_path', 'direction') if str(exc).startswith(f)),
                    'grasp profile')
        raise ParameterError(f'parameter {name!r}: {exc}') from None
    return profile


def plan_offsets(duration: float, step_ns: int, limit: int | None = None) -> np.ndarray:
    """Point times [ns] of a plan after its origin: the grid k·``step_ns`` from 0 to the first
    point at or after ``duration`` [s] (the grasp's end: the reference is at rest from there on);
    at most ``limit``."""
    points = max(-(-int(round(duration * cv.NS)) // step_ns) + 1, 2)
    return step_ns * np.arange(points if limit is None else min(points, limit), dtype=np.int64)


class TrajectoryNode(Node):
    """The planned grasp on ``grasp_reference``, once per rest pose (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('trajectory', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        self.d = int(p['task_dim'])
        self.profile = _profile(p)
        self.step_ns = int(round(p['horizon_step'] * cv.NS))
        points = len(plan_offsets(self.profile.duration, self.step_ns, limit=MAX_PLAN_POINTS + 1))
        if points > MAX_PLAN_POINTS:
            raise ParameterError("parameter 'horizon_step': a grasp of "
                                 f"{self.profile.duration:g} s on a {p['horizon_step']:g} s grid "
                                 f'needs more than {MAX_PLAN_POINTS} points '
                                 '(one message); take a coarser grid')
        self.jump_ns = int(round(p['reset_on_jump'] * cv.NS))
        self.fixed_rest = _rest_pose(p['rest_pose'], self.n, self.d)
        self.fixed_start = _start_at(p['start_at'])
        self.tips_qos = with_reliability(LOOP_QOS, p['tips_reliability'])
        self.origin_ns: int | None = None       # the plan's origin, once planned
        self.run_start: int | None = None       # where /clock jumped back to (a new run's start)
        self.waiting_since: float | None = None  # wall time the plan began to wait
        self._early: tuple[int, np.ndarray] | None = None  # the newest tips (stamp, tips) heard
                                                # while the plan waits
        self._warned_at = 0.0                   # wall time of the last WARN about that wait
        on_runtime_change(self, PARAMS, apply=self._apply)

        self.traj: GraspTrajectory | None = None
        self.clock_ns = -1                      # newest /clock stamp
        self.sub = None                         # the tip subscription, while a rest pose is wanted
        self._rest_tips: list[np.ndarray] = []  # the tips gathered for the rest pose so far
        self.cdr_tips = cdr.tips_codec(self.names)  # CDR bytes read at fixed offsets (nodes/cdr.py)
        self.cdr_clock = cdr.clock_codec()
        self.cdr_plan = PlanCodec(self.names, self.d)
        self.pub = self.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        self.sub_clock = self.create_subscription(Clock, CLOCK, self.on_clock, CLOCK_QOS, raw=True)
        # the tip subscription is dropped outside its own callback, by this timer
        self._drop_timer = self.create_timer(0.001, self._drop_tips, autostart=False)
        self._recheck_timer = self.create_timer(RECHECK_S, self._recheck, autostart=False)
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_tips, self.cdr_clock)
        self.diag.values['start_when'] = p['start_when']
        self.estimate_topic = self.resolve_topic_name(STATE_ESTIMATE)
        pr = self.profile
        self.get_logger().info(
            f'grasp with fingers {[self.names[i] for i in pr.grasp_fingers]}, others {pr.others}: '
            f'start {pr.t_start:g} s, '
            f'close {pr.t_close:g} s, hold {pr.t_hold:g} s, open {pr.t_open:g} s; planned on a '
            f'{1e3 * p["horizon_step"]:g} ms grid')
        if self.fixed_rest is None:
            self._want_tips()
        else:
            self._plan(self.fixed_rest, 'given', self._given_origin())

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.jump_ns = int(round(self.p['reset_on_jump'] * cv.NS))

    # -- inputs ------------------------------------------------------------------------------
    def on_tips(self, data: bytes) -> None:
        if self.traj is not None:  # already planned: the subscription is on its way out
            return
        try:
            stamp, tips = self.cdr_tips.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_message', f'rejected: {exc}')
            return
        self.diag.count('tips')
        self._take(stamp, tips)

    def _take(self, stamp: int, tips: np.ndarray) -> None:
        """Tips at ``stamp``, decoded and counted: planned from, gathered toward the rest pose,
        or (the controller not ready) held while the plan waits."""
        if self.p['start_when'] == 'controller':
            problem = self.controller_problem()
            if problem is not None:
                self._early = (stamp, tips)
                if self._recheck_timer.is_canceled():
                    self._recheck_timer.reset()
                self._wait(problem, stamp)
                return
            self._early = None
            self._recheck_timer.cancel()
            if self.waiting_since is not None:
                waited = time.monotonic() - self.waiting_since
                self.diag.values['waited_s'] = f'{waited:.3f}'
                self.get_logger().info(f'the controller is ready after {waited:.3f} s of wall '
                                       f'time: planning from the tips at t = '
                                       f'{format_time(stamp)} s')
            self.waiting_since = None
            self.diag.values['waiting_for'] = ''
        origin = self.fixed_start
        if origin is None:
            origin = stamp if self.run_start is None else min(self.run_start, stamp)
        if not self._rest_tips and stamp > origin + int(self.profile.t_start * cv.NS):
            self.diag.problem('late_start', f'first tip_positions at t = {format_time(stamp)} s, '
                              f'after the grasp began (start_at {format_time(origin)} s + '
                              't_start): taking them as the rest pose (give rest_pose when '
                              'restarting mid-run)')
        self._rest_tips.append(tips[:, :self.d])
        wanted = self.p['rest_samples']
        if len(self._rest_tips) < wanted:
            self.diag.values['rest_samples'] = f'{len(self._rest_tips)} of {wanted}'
            return
        rest = np.mean(self._rest_tips, axis=0)       # of one message: that message, exactly
        self._rest_tips = []
        if wanted == 1:
            source = f'from the tips at t = {format_time(stamp)} s'
        else:
            source = f'the mean of {wanted} tip messages up to t = {format_time(stamp)} s'
            self.diag.values['rest_samples'] = f'{wanted} of {wanted}'
        self._drop_timer.reset()
        self._plan(rest, source, origin)

    def controller_problem(self) -> str | None:
        """What the plan waits for with ``start_when: controller`` (the graph as this node sees
        it), or None: the controller is ready to answer."""
        name, ns = self.p['controller_node'], self.get_namespace()
        readers = self.get_subscriptions_info_by_topic(self.pub.topic_name)
        full = f'{ns.rstrip("/")}/{name}'
        if not any(r.node_name == name and r.node_namespace == ns for r in readers):
            return f'the controller {full} to subscribe {self.pub.topic_name}'
        if self.count_publishers(self.estimate_topic) == 0:
            return f'a writer of {self.estimate_topic} (the estimator)'
        return None

    def _recheck(self) -> None:
        """While the plan waits: once the controller shows up, plan from the newest tips heard
        (:data:`RECHECK_S`), without waiting for newer ones."""
        if self.traj is not None or self._early is None:
            self._recheck_timer.cancel()
            return
        if self.controller_problem() is None:
            self._take(*self._early)

    def _wait(self, problem: str, stamp: int) -> None:
        """Tips at ``stamp`` heard while the controller is not ready: not planned from; the wait
        in /diagnostics and the log."""
        now = time.monotonic()
        self.diag.count('early_tips')
        self.diag.values['waiting_for'] = problem
        if self.waiting_since is None:
            self.waiting_since = self._warned_at = now
            self.get_logger().info(f'tip_positions at t = {format_time(stamp)} s: the plan waits '
                                   f'for {problem} (start_when controller)')
        elif now - self._warned_at >= WAIT_WARN_S:
            self._warned_at = now
            self.get_logger().warning(f'the plan has waited {now - self.waiting_since:.1f} s of '
                                      f'wall time for {problem}; start the controller, or set '
                                      'start_when tips')
        self.diag.values['waited_s'] = f'{now - self.waiting_since:.3f}'

    def on_clock(self, data: bytes) -> None:
        try:
            stamp, _ = self.cdr_clock.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_clock', f'rejected: {exc}')
            return
        if stamp >= self.clock_ns - self.jump_ns or self.clock_ns < 0:
            self.clock_ns = max(self.clock_ns, stamp)
            self.diag.good('ticks', 'planned')
            return
        self.diag.count('ticks')
        self.diag.problem('resets', f'/clock jumped back from {self.clock_ns / cv.NS:.4f} s to '
                          f'{stamp / cv.NS:.4f} s: a restarted simulator; '
                          + ('planning again' if self.fixed_rest is not None
                             else 'taking a new rest pose'))
        self.clock_ns = self.run_start = stamp
        if self.fixed_rest is not None:
            self._plan(self.fixed_rest, 'given', self._given_origin())
        else:
            self.traj = None
            self._rest_tips = []
            self._want_tips()

    def _given_origin(self) -> int:
        """The origin of a plan from the given ``rest_pose``: ``start_at``, else 0."""
        return 0 if self.fixed_start is None else self.fixed_start

    # -- the tip subscription ----------------------------------------------------------------
    def _want_tips(self) -> None:
        self._drop_timer.cancel()
        if self.sub is None:
            self.sub = self.create_subscription(PoseArray, TIP_POSITIONS, self.on_tips,
                                                self.tips_qos, raw=True)

    def _drop_tips(self) -> None:
        self._drop_timer.cancel()
        if self.sub is not None and self.traj is not None:
            self.destroy_subscription(self.sub)
            self.sub = None

    # -- the plan ----------------------------------------------------------------------------
    def _plan(self, rest: np.ndarray, source: str, origin: int) -> None:
        """Plan the grasp from ``rest`` starting at ``origin`` [ns] and publish it (``source`` says
        where the rest came from)."""
        self.traj = GraspTrajectory(rest, self.profile, self.d)
        self.origin_ns = origin
        # both round-trip: a node restarted with these values plans the very same points
        self.diag.values['rest_pose'] = ', '.join(repr(v) for v in self.traj.rest.ravel().tolist())
        self.diag.values['start_at'] = format_time(origin)
        self.diag.publish()      # at once, not at the next 1 s tick: a restart is given these
        offsets = plan_offsets(self.profile.duration, self.step_ns)
        ref = self.traj.sample(offsets / cv.NS)          # relative times: the same at any origin
        self.pub.publish(self.cdr_plan.encode(origin, offsets, ref.pos, ref.vel, ref.acc))
        self.diag.count('references')
        mm = ', '.join('(' + ', '.join(f'{1e3 * v:.2f}' for v in row) + ')'
                       for row in self.traj.rest.tolist())
        self.get_logger().info(f'planned {len(offsets)} points from t = {format_time(origin)} s '
                               f'over {offsets[-1] / cv.NS:g} s from the rest pose {source} [mm]: '
                               f'{mm}')


def main(args=None) -> int:
    return run(TrajectoryNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
