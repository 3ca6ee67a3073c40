"""The controller node: tracking of every finger with the learned SDC model.

The control law is the ``law`` parameter (:mod:`soft_gripper_sdre.control.laws`): ``sdre_ff``
(default: SDRE feedback plus model-inversion feedforward, with integral action unless
``integral_gain`` is 0), ``sdre`` (the paper's law), or any other law the law files register for
the graph (:data:`~soft_gripper_sdre.control.laws.GRAPH_LAWS`). Each law file declares the
parameters its law reads (:class:`~soft_gripper_sdre.control.laws.registry.LawParam`); this
node's :data:`PARAMS` take them from the registry, so ``--help``, docs/parameters.md and
config/controller.yaml list them with their units, ranges and whether they may change at runtime.

Subscribes ``state_estimate`` (one message per control period, keeping only the newest) and
``grasp_reference`` (the planned grasp, once per plan); publishes ``torque_commands`` (one per
estimate; with ``effort_topic`` also the same efforts as a ``std_msgs/Float64MultiArray`` in the
joint order of a ros2_control ``forward_command_controller``, ``effort_joints``) and
``/diagnostics`` (solves, Riccati check failures, fallbacks, saturation, compute
time, skipped estimates).

**The finger's shape comes from the model.** The checkpoint's task dimension d (2: a planar tip,
3: a 3-D tip, read from the estimates' and the plan's z) and number of inputs m make the messages:
``torque_commands`` names ``<finger>/ax0`` … ``<finger>/ax<m−1>``. Each input k is bounded by
``[input_lower[k], input_upper[k]]`` (one value per input, in the input's SI unit; a pneumatic
chamber 0..p_max, a tendon 0..T_max); both [0.0] (unset) bound each of the model's inputs by
±``torque_limit``. Lists that do not give one value per input, or an empty interval, end the node
at start-up naming the parameters. /diagnostics shows the shape, the bounds and, for a finger
whose inputs cannot reach every direction (m < d), the largest part of the plan's acceleration
no input can reach (``unreachable_max``, m/s²). The controller asks each node publishing its
estimates or plans for its ``task_dim`` (:mod:`~soft_gripper_sdre.nodes.peer_shape`); while one
has another, it reports ERROR naming the node (``task_dim_mismatch``) and refuses estimates
(``wrong_task_dim``); a trajectory node of another has its plans refused and the plan held dropped.

**Fingers that share one model** are not alike: ``input_gains`` gives per finger how much more
strongly its inputs act than the model's (training reads it from each finger's recordings:
:func:`~soft_gripper_sdre.analysis.finger_fits.input_gains`). The law then runs in the model's
units, bounded by what every finger can deliver
(:meth:`~soft_gripper_sdre.sim.shape.InputBounds.through_gains`), and each finger receives the
law's command divided by its gain, clipped into the actuators' bounds.

Which estimate is answered, and when, is decided by
:class:`~soft_gripper_sdre.control.command_gate.CommandGate`: each estimate is answered with the
plan once one covers its stamp; when estimates stop the controller sends nothing (the simulator
steps safely on its own) and a wall-time watchdog reports ERROR after ``estimate_watchdog``, or,
when the last estimate was at or past the plan's end, the run's end at INFO
(docs/design/loop_rules.md). The law the parameters build, and its retuning, are
:class:`~soft_gripper_sdre.nodes.law_tuning.LawTuning`'s; the arithmetic from an answered
estimate to its torque (the plan sampled, each finger in the model's frame, the law timed) is
:class:`~soft_gripper_sdre.nodes.tracking_step.TrackingStep`'s. This module is the ROS side:
parameters, topics, conversions, status and logs.

**Tuning at runtime.** The laws' runtime parameters (``q_pos``, ``q_vel``, ``r``, ``integral_gain``,
``integral_band``, ``pd_kp``, ``pd_kd``, …: :data:`~soft_gripper_sdre.nodes.law_tuning.TUNABLE`)
may be changed while the node runs (``ros2 param set /controller q_pos 2.0e+6``). A
change is checked by building the law with the new values: a refused one returns its reason and
the old values stay in force. An accepted one takes effect at the next estimate: parameter
changes are executor callbacks like the estimates, so they never run inside a control step. The
law is built again with the new values and handed the state that keeps the command continuous
(the roll-off's last output, the integral's torque:
:func:`~soft_gripper_sdre.control.laws.hand_over`); the SDRE solves afresh, as after a
reset. The change is logged, and /diagnostics shows the values
in force (``weights``, ``integral``, ``pd_gains``, …). A value the law does not use (``pd_kp`` for
``sdre_ff``) is taken and has no effect.

**Falling behind is loud.** An estimate the controller never saw (its reader keeps only the
newest, so a controller starved of CPU skips to the present) shows as a gap in the estimates'
stamps, counted as ``skipped_estimates``; a forward jump over ``reset_on_jump`` is counted as
``estimate_jumps`` instead, with a throttled warning. At each /diagnostics report, when more than
:data:`SKIP_WARN_SHARE` of the periods since the previous report (and at least
:data:`SKIP_WARN_MIN`) were skipped, the status goes to WARN and the log warns with the counts
(``skipped_estimates`` in the window and in all; the cure: give the loop its cores,
docs/faults.md); a report without that goes back to OK. A few lost messages upstream (a driver
dropping 1 % of its tips) stay below it.

Nothing bad reaches the actuators: malformed, non-finite, wrong-size or old messages are rejected
(throttled warning, counted) and produce no torque; the SDRE core falls back to the last valid
gains when a Riccati check fails and saturates at ``torque_limit``; a torque that is still not
finite is replaced by zero and counted. A missing or bad model file ends the node at start-up with
a message and a non-zero status.
"""
from __future__ import annotations

from pathlib import Path
import sys
import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.control.command_gate import Change, CommandGate, Notice, Outcome, Plan
from soft_gripper_sdre.control.kernels import warm_up
from soft_gripper_sdre.control.laws import DEFAULT_LAW, GRAPH_LAWS, LAW_REGISTRY
from soft_gripper_sdre.control.laws.registry import LawParam, law_params, node_description
from soft_gripper_sdre.control.riccati import Check
from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, roll_off_corner_hz, shape_of
from soft_gripper_sdre.learning.model import ModelFileError, SDCModel, set_torch_threads
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.cli import format_help, wants_help
from soft_gripper_sdre.nodes.common import ERROR, OK, WARN, Diagnostics, ThrottledLogger, run
from soft_gripper_sdre.nodes.composition import (
    WITH_ESTIMATOR,
    composed_help,
    composed_params,
    with_estimator,
)
from soft_gripper_sdre.nodes.law_tuning import LawTuning
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    numbers,
    numbers_param,
    on_runtime_change,
)
from soft_gripper_sdre.nodes.peer_shape import PeerShapes
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    NEWEST_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.nodes.tracking_step import TrackingStep
from soft_gripper_sdre.sim.shape import HAND_SHAPE, INPUT_GAIN_RANGE, InputBounds, ShapeError


def _node_params(shared: bool) -> tuple[Param, ...]:
    """The node parameters the graph laws read, as their files declare them
    (:func:`~soft_gripper_sdre.control.laws.registry.law_params`): ``shared`` the settings every
    law is built from (the SDRE weights), else the law-specific ones; runtime ones tunable."""
    return tuple(_declared(p) for p in law_params() if (not p.option) == shared)


def _declared(p: LawParam) -> Param:
    return Param(p.name, p.default, node_description(p), p.units, p.min, p.max, p.choices,
                 read_only=not p.runtime)


PARAMS = (
    Param('model_path', '', 'SDC model checkpoint (.pt); empty = the model shipped with the '
          'package', read_only=True),
    finger_names_param('the fingers controlled together: the joint names of state_estimate and '
                       'grasp_reference; torque_commands names <finger>/ax0 … <finger>/ax<m-1> '
                       "(m: the model's inputs)"),
    *_node_params(shared=True),
    Param('torque_limit', 0.0625, 'saturation of each torque (0.0625 N·m = 25 sim units, the '
          'stable range of the physics step) when input_lower and input_upper are unset', 'N·m',
          1e-6, 1.0, read_only=True),
    numbers_param('input_lower', 'lower bound of each input in its SI unit (N·m, Pa, N), one '
                  "per input of the model, a list [u0, u1, …]; '' with input_upper '' = "
                  "±torque_limit on each of the model's inputs"),
    numbers_param('input_upper', 'upper bound of each input, a list [u0, u1, …], each above its '
                  "lower bound; '' with input_lower '' = ±torque_limit"),
    numbers_param('input_gains', 'per finger, in the order of finger_names, how much more '
                  "strongly its inputs act than the model's (training reads it from each "
                  "finger's recordings): the law runs in the model's units and the finger "
                  'receives its command divided by its gain, within input_lower/input_upper; '
                  "each in [0.5, 2]; '' = 1 for every finger"),
    Param('torque_lowpass_hz', DEFAULT_LOWPASS_HZ, 'first-order roll-off of the torque command '
          '(keeps the loop out of the finger\'s ~59 Hz bending mode; 0 = off); its corner is '
          'capped at a tenth of the control rate, 0.1 / control_period (10 Hz at 10 ms)', 'Hz',
          0.0, 500.0, read_only=True),
    Param('control_period', 0.001, 'period of the estimates (the roll-off filter\'s step)', 's',
          1e-4, 0.05, read_only=True),
    Param('solver', 'fast', 'Riccati solver: warm-started Newton–Kleinman or scipy reference',
          choices=('fast', 'reference'), read_only=True),
    Param('law', DEFAULT_LAW, 'control law (soft_gripper_sdre.control.laws); ' + '; '.join(
        f'{name}: {LAW_REGISTRY[name].summary}' for name in GRAPH_LAWS) + '; the oracle needs '
        "the plant's joint state and runs in-process only (tools/judging/evaluate.py)",
        choices=GRAPH_LAWS, read_only=True),
    *_node_params(shared=False),
    Param('estimate_watchdog', 0.5, 'wall time without a state_estimate after which the controller '
          'reports ERROR, or the run\'s end once the estimates passed the plan\'s end (it sends '
          'nothing without an estimate: the simulator steps safely on its own)', 's', 1e-2, 600.0),
    Param('reset_on_jump', 0.1, 'a state_estimate stamp this far behind the last one (a simulator '
          'restart) resets the controller instead of being rejected; one this far ahead is '
          'counted (estimate_jumps) and warned about. The estimator resets its filter on a jump '
          'either way (its own reset_on_jump)', 's', 1e-3, 1e6, read_only=True),
    Param('effort_topic', '', 'also publish each command as std_msgs/Float64MultiArray here, as a '
          'ros2_control forward_command_controller with the effort interface reads it '
          "(/<controller_name>/commands); '' = off", read_only=True),
    Param('effort_joints', cv.torque_names(FINGER_NAMES), 'effort_topic: for each joint of the '
          "forward_command_controller, in the order of its 'joints' list, the input that drives "
          "it (<finger>/ax<k>, k below the model's inputs m); every input once", read_only=True),
)


#: a /diagnostics window in which more than this share of the periods was skipped is a WARN
SKIP_WARN_SHARE = 0.1
#: ... and at least this many estimates skipped in it
SKIP_WARN_MIN = 10


class ControllerNode(Node):
    """SDRE tracking controller on topics (see module doc)."""

    def __init__(self, *, subscribe_estimates: bool = True, **kwargs) -> None:
        """``subscribe_estimates=False``: no ``state_estimate`` subscription; the estimates come
        by :meth:`take_estimate` (an estimator node in the same process)."""
        super().__init__('controller', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        set_torch_threads(1)
        self.model = load_model(p['model_path'])
        self.shape = shape_of(self.model)
        #: the bounds in force, and those the law is given besides its ±limit (None: the
        #: symmetric bounds of input_lower / input_upper, or ±torque_limit, are that limit)
        self.bounds = input_bounds(p, self.shape.m)
        self.law_bounds = self.bounds
        limit = p['torque_limit']
        if self.bounds is None:
            self.bounds = InputBounds.symmetric(limit, self.shape.m)
        elif self.bounds.symmetric_limit is not None:
            limit, self.law_bounds = self.bounds.symmetric_limit, None
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        #: per finger the strength of its inputs against the model's (None: all the model's)
        self.gains = input_gains(p, self.n)
        if self.gains is not None:
            # the law in the model's units, within what every finger delivers
            try:
                seen = self.bounds.through_gains(self.gains)
            except ShapeError as exc:
                raise ParameterError(f"parameters 'input_gains', 'input_lower', 'input_upper': "
                                     f'{exc}') from None
            if self.law_bounds is None:
                limit = seen.symmetric_limit
            else:
                self.law_bounds = seen
        self.effort_order = None            # index into u.ravel() of each effort_topic entry
        if p['effort_topic']:
            try:
                self.effort_order = cv.effort_array_order(p['effort_joints'], self.names,
                                                          self.shape.m)
            except ValueError as exc:
                raise ParameterError(f'parameter \'effort_joints\': {exc}') from None
        try:
            self.tuning = LawTuning(self.model, self.n, {**p, 'torque_limit': limit},
                                    bounds=self.law_bounds)
        except ValueError as exc:
            names = '/'.join(['law', *(q.name for q in LAW_REGISTRY[p['law']].params)])
            raise ParameterError(f'{names}: {exc}') from None
        on_runtime_change(self, PARAMS, validate=self.tuning.check, apply=self._apply)
        warm_up()       # compiled (or loaded from the cache) before any topic shows the node ready
        self.step = TrackingStep(self.model, self.names, self.shape,
                                 self.law_bounds if self.gains is None else self.bounds,
                                 input_gains=self.gains)
        self.done = False
        self.exit_code = 0
        self._open_topics(subscribe_estimates)
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        self.gate = CommandGate(_ns(p['control_period']), _ns(p['reset_on_jump']),
                                p['estimate_watchdog'], counters=self.diag.counters)
        self._show_settings()
        self.peers = PeerShapes(self, self.shape.d,
                                [s.topic_name for s in (self.sub_est, self.sub_ref) if s],
                                on_change=self._peer_shapes)
        self._watchdog = self.create_timer(
            0.05, lambda: self._act(self.gate.on_wall_time(time.monotonic())))
        self._log_start()

    def _open_topics(self, subscribe_estimates: bool) -> None:
        """The publishers and subscriptions; the per-period messages travel as CDR bytes read /
        written at fixed offsets (nodes/cdr.py)."""
        self.cdr_estimate = cdr.estimate_codec(self.names, self.shape.d)
        self.cdr_cmd = cdr.torques_codec(self.names, self.shape.m)
        self.cdr_plan = PlanCodec(self.names, self.shape.d)
        self.pub_cmd = self.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        self.pub_effort = self._effort_msg = None
        if self.effort_order is not None:
            self.pub_effort = self.create_publisher(Float64MultiArray, self.p['effort_topic'],
                                                    LOOP_QOS)
            self._effort_msg = Float64MultiArray()      # layout: no dims, data_offset 0
        self.sub_est = None
        if subscribe_estimates:
            self.sub_est = self.create_subscription(MultiDOFJointTrajectory, STATE_ESTIMATE,
                                                    self.on_estimate, NEWEST_QOS, raw=True)
        self.sub_ref = self.create_subscription(MultiDOFJointTrajectory, GRASP_REFERENCE,
                                                self.on_reference, REFERENCE_QOS, raw=True)

    def _show_settings(self) -> None:
        """The model, the law and its values in force, in /diagnostics (compute times too, as
        they come)."""
        p, values = self.p, self.diag.values
        cdr.watch(self.diag, self.cdr_estimate, self.cdr_plan)
        values['model'] = str(self.model.path)
        values['shape'] = str(self.shape)
        values['input_bounds'] = str(self.bounds)
        if self.gains is not None:
            values['input_gains'] = ', '.join(f'{name} {g:g}'
                                              for name, g in zip(self.names, self.gains))
            values['law_bounds'] = (str(self.law_bounds) if self.law_bounds is not None else
                                    f'±{self.tuning.params["torque_limit"]:g}')
        values['law'] = p['law']
        values.update(self.tuning.shown())
        corner = roll_off_corner_hz(p['torque_lowpass_hz'], p['control_period'])
        values['roll_off_hz'] = f'{corner:g}'
        self.diag.before_publish.append(self._compute_stats)
        self.diag.before_publish.append(self._judge_skips)
        self._window = (0, 0)           # (estimates, skipped_estimates) at the previous report
        self._behind = False            # the WARN in /diagnostics is the skipped estimates'

    def _log_start(self) -> None:
        """One line of what runs: the model, the weights, the limit, the law, the fingers."""
        p, model = self.p, self.model
        integral_note = (f'; integral gain {p["integral_gain"]:g}'
                         if self.tuning.uses('integral_gain') else '')
        rest = ', '.join(f'{1e3 * v:.1f}' for v in model.rest_tip[:self.shape.d])
        shape = '' if self.shape == HAND_SHAPE else f'{self.shape}; '
        limit = (f'limit {self.tuning.params["torque_limit"]:g} N·m' if self.law_bounds is None
                 else f'inputs {self.bounds}')
        self.get_logger().info(
            f'model {model.path.name} ({shape}rest tip {rest} mm'
            f'{"; each finger at its own" if self.step.rest_shift is not None else ""}); '
            f'{self.diag.values["weights"]}; '
            f'{limit}, rolled off at {self.diag.values["roll_off_hz"]} Hz; '
            f'{p["solver"]} solver; law {p["law"]}'
            f'{" with Q(x)" if p["state_weights"] else ""}{integral_note}; '
            f'fingers {", ".join(self.names)}'
            + (f' (input gains {self.diag.values["input_gains"]}; the law within '
               f'{self.diag.values["law_bounds"]} in the model\'s units)'
               if self.gains is not None else '')
            + (f'; efforts also on {self.pub_effort.topic_name} for {", ".join(p["effort_joints"])}'
               if self.pub_effort is not None else ''))

    # -- inputs ------------------------------------------------------------------------------
    def on_reference(self, data: bytes) -> None:
        try:
            _, times, pos, vel, acc = self.cdr_plan.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_reference', str(exc))
            return
        if self.sub_ref.topic_name in self.peers.wrong_topics:    # maybe that node's
            self.diag.count('wrong_task_dim')
            return
        self._act(self.gate.on_plan(times, pos, vel, acc), GRASP_REFERENCE)

    def on_estimate(self, data: bytes) -> None:
        try:
            stamp, x = self.cdr_estimate.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_estimate', str(exc))
            return
        self._estimate(stamp, x)

    def take_estimate(self, stamp: int, x: np.ndarray) -> None:
        """The estimate (n, 2d) stamped ``stamp`` [ns], handed over in-process by an estimator
        node of the same process and executor: answered as if it had come on the topic."""
        self._estimate(stamp, x)

    def _estimate(self, stamp: int, x: np.ndarray) -> None:
        if self.peers.problem is not None:          # an estimator or plan of another task_dim
            self.diag.count('wrong_task_dim')
            self.gate.last_heard = time.monotonic()     # heard: the watchdog keeps the ERROR
            return
        last = self.gate.last_estimate_ns
        self._act(self.gate.on_estimate(stamp, x, time.monotonic()), STATE_ESTIMATE)
        if last >= 0 and stamp - last > self.gate.reset_jump_ns:
            self.diag.count('estimate_jumps')
            self.log.warn('estimate_jumps', f'state_estimate stamps jumped forward by '
                          f'{(stamp - last) / 1e6:.1f} ms (more than reset_on_jump) to t = '
                          f'{stamp / cv.NS:.4f} s: no estimate came in between (a stalled '
                          f'driver, estimator or controller); '
                          f'{self.diag.counters["estimate_jumps"]} such jump(s) in all')

    def _reject(self, key: str, why: str) -> None:
        self.diag.problem(key, f'rejected: {why}')

    # -- outputs -----------------------------------------------------------------------------
    def _act(self, outcome: Outcome, topic: str = '') -> None:
        """Report the gate's notices, then publish its answer or refuse the message."""
        for notice in outcome.notices:
            self._report(notice, topic)
        if outcome.refused:
            self._reject(outcome.refused, outcome.reason)
        answer = outcome.answer
        if answer is not None:
            self._control(answer.stamp, answer.estimate, answer.plan)

    def _report(self, notice: Notice, topic: str) -> None:
        change, t = notice.change, notice.t_ns / cv.NS
        if change is Change.RESET:
            self.get_logger().warning(f'{topic}: time jumped back to {t:.3f} s; resetting')
            self.tuning.law.reset()
        elif change is Change.ESTIMATES_LOST:
            self._error(f'no state_estimate for {self.p["estimate_watchdog"]:g} s of wall time, '
                        f'the last stamped t = {t:.4f} s: commanding nothing')
        elif change is Change.RUN_ENDED:
            why = (f'the run is over: no state_estimate for {self.p["estimate_watchdog"]:g} s of '
                   f'wall time, the last stamped t = {t:.4f} s, at or past the plan\'s end; '
                   'commanding nothing')
            self.diag.set_status(OK, why)
            self.get_logger().info(why)
        elif change is Change.ESTIMATES_BACK:
            self.diag.set_status(OK, 'estimates are back; tracking')
            self.get_logger().info(f'state estimates are back at t = {t:.4f} s; tracking resumes')

    def _peer_shapes(self, problem: str | None) -> None:
        """A publisher of estimates or plans of another ``task_dim`` appeared (``problem``, named
        with the fix: ERROR, estimates and plans refused and counted as ``wrong_task_dim``), or
        the last one left (None: OK, tracking again once estimates come). The plan held is
        dropped when a planner of another task_dim appears (it may be that node's; a planner of
        the model's task_dim keeps it), and the run restarts from the next estimate that
        passes."""
        self.gate.pending = None
        self.gate.last_estimate_ns = -1
        self.tuning.law.reset()
        if self.sub_ref.topic_name in self.peers.wrong_topics:
            self.gate.plan = None
        if problem is not None:
            self.diag.values['task_dim_mismatch'] = problem
            self._error(f'{problem}; commanding nothing until it does')
            return
        self.diag.values.pop('task_dim_mismatch', None)
        why = 'every publisher of estimates and plans matches the model\'s task_dim'
        if self.gate.estimates_lost:
            self.get_logger().info(f'{why}; waiting for estimates')
        else:
            self.diag.set_status(OK, why)
            self.get_logger().info(f'{why}: tracking again')

    def _error(self, why: str) -> None:
        """Enter ERROR with ``why`` (status and log)."""
        self.diag.set_status(ERROR, why)
        self.get_logger().error(why)

    def _control(self, stamp: int, x: np.ndarray, plan: Plan) -> None:
        command = self.step.command(self.tuning.law, stamp, x, plan)
        if command.replaced:
            self.diag.count('nonfinite_torque')
        if command.clipped:
            self.diag.count('clipped_command')
        u = command.u
        self.pub_cmd.publish(self.cdr_cmd.encode(stamp, u))
        if self.pub_effort is not None:  # the same efforts in the joint order of ros2_control
            self._effort_msg.data = u.ravel()[self.effort_order].tolist()
            self.pub_effort.publish(self._effort_msg)
        self.diag.good('commands', 'tracking')
        count_solve(self.diag, self.log, command.out, stamp)

    # -- tuning and statistics ---------------------------------------------------------------
    def _apply(self, new: dict) -> None:
        """An accepted runtime change: the watchdog, and the law retuned (logged, shown)."""
        self.p.update(new)
        self.gate.watchdog = self.p['estimate_watchdog']
        note = self.tuning.apply(new)
        if note is not None:
            self.get_logger().info(note)
            self.diag.values.update(self.tuning.shown())

    def _compute_stats(self) -> None:
        """Mean and max compute time [µs] since the last /diagnostics, into its values."""
        times = self.step.take_compute_us()
        if times is not None:
            self.diag.values['compute_us_mean'] = f'{times[0]:.0f}'
            self.diag.values['compute_us_max'] = f'{times[1]:.0f}'
        unreachable = self.step.take_unreachable()
        if unreachable is not None:
            self.diag.values['unreachable_max'] = f'{unreachable:.3g}'


    def _judge_skips(self) -> None:
        """Before each /diagnostics: WARN with the counts when the estimates skipped since the
        previous report pass :data:`SKIP_WARN_SHARE` of the periods (module doc), OK again
        after a report without that."""
        c = self.diag.counters
        estimates, skipped = c['estimates'], c['skipped_estimates']
        new_estimates, new_skipped = estimates - self._window[0], skipped - self._window[1]
        self._window = (estimates, skipped)
        periods = new_estimates + new_skipped
        behind = new_skipped >= SKIP_WARN_MIN and new_skipped > SKIP_WARN_SHARE * periods
        self.diag.values['skipped_share'] = f'{new_skipped / periods:.3f}' if periods else '0'
        if behind:
            why = (f'falling behind: {new_skipped} of {periods} estimates skipped since the last '
                   f'report ({skipped} in all), running {self.diag.values["scheduling"]}; give the '
                   f'loop its cores or real-time priority (docs/faults.md, '
                   f'docs/performance.md "Real-time priority")')
            self.get_logger().warning(why)
            if self.diag.level != ERROR:
                self.diag.set_status(WARN, why)
                self._behind = True
        elif self._behind:
            self._behind = False
            if self.diag.level == WARN:
                self.diag.set_status(OK, f'tracking; {skipped} estimates skipped earlier')


def input_bounds(p: dict, m: int) -> InputBounds | None:
    """The bounds of ``input_lower`` / ``input_upper`` for a finger of ``m`` inputs; None when
    both are unset ('': ±``torque_limit`` on each input).

    Raises:
        ParameterError: not one value per input, a bound not finite, or an empty interval (the
            message names the parameters).
    """
    lower, upper = (numbers(p[name], name) for name in ('input_lower', 'input_upper'))
    if lower is None and upper is None:
        return None
    lower, upper = lower or [], upper or []
    try:
        return InputBounds.parse(lower, upper, m, "parameters 'input_lower', 'input_upper'")
    except ShapeError as exc:
        raise ParameterError(str(exc)) from None


def input_gains(p: dict, n: int) -> np.ndarray | None:
    """(n,) the ``input_gains`` of ``n`` fingers; None when unset or every gain is 1.

    Raises:
        ParameterError: not one gain per finger, or a gain outside [0.5, 2] (naming it).
    """
    gains = numbers(p['input_gains'], 'input_gains')
    if gains is None:
        return None
    if len(gains) != n:
        raise ParameterError(f"parameter 'input_gains': one gain per finger of finger_names "
                             f'({n}), got {len(gains)}: {gains}')
    lo, hi = INPUT_GAIN_RANGE
    bad = [g for g in gains if not lo <= g <= hi]
    if bad:
        raise ParameterError(f"parameter 'input_gains': each gain must lie in [{lo:g}, {hi:g}] "
                             f"(a finger further from the model is not the model's finger: "
                             f'train a model of its own), got {bad}')
    return None if all(g == 1.0 for g in gains) else np.asarray(gains, dtype=float)


def load_model(path: str) -> SDCModel:
    """The SDC model of the ``model_path`` parameter (empty: the shipped one).

    Raises:
        ParameterError: a missing or bad model file (the message names the file).
    """
    try:
        return SDCModel(Path(path).expanduser() if path else None)
    except ModelFileError as exc:
        raise ParameterError(f'model_path: {exc}') from None


def count_solve(diag: Diagnostics, log: ThrottledLogger, out, stamp: int) -> None:
    """Count in ``diag`` what the law's output ``out`` for the instant ``stamp`` reports: failed
    Riccati checks by kind, fallbacks (also a throttled warning), saturation, the largest
    residual."""
    if not out.ok.all():
        diag.count('check_failures', int((~out.ok).sum()))
        for flag in Check:
            hits = int(np.count_nonzero(out.failed_checks & flag))
            if hits:
                diag.count(f'failed_{flag.name.lower()}', hits)
    if out.fallback.any():
        diag.count('fallbacks', int(out.fallback.sum()))
        log.warn('fallback', f'Riccati checks failed for fingers '
                 f'{np.flatnonzero(out.fallback).tolist()} '
                 f'at t = {stamp / cv.NS:.3f} s; using the last valid gains')
    if out.saturated.any():
        diag.count('saturated', int(out.saturated.sum()))
    res = float(out.residual.max())
    if res > float(diag.values.get('max_residual', '0')):
        diag.values['max_residual'] = f'{res:.3g}'


def _ns(seconds: float) -> int:
    return int(round(seconds * cv.NS))


def composed(**kwargs) -> tuple[Node, Node]:
    """The estimator and the controller of ``controller --with-estimator``, two nodes of one
    process (``kwargs``: to both constructors, e.g. ``context=``).

    Raises:
        ParameterError: as either node raises it, or the estimator's ``task_dim`` is not the
            model's task dimension.
    """
    estimator, controller = with_estimator(
        lambda: ControllerNode(subscribe_estimates=False, **kwargs),
        lambda controller: controller.take_estimate, **kwargs)
    if estimator.d != controller.shape.d:
        ours, theirs = estimator.d, controller.shape.d
        estimator.destroy_node()
        controller.destroy_node()
        raise ParameterError(f"parameter 'task_dim': the estimator filters {ours}-D tips but the "
                             f'model is of {theirs}-D tips; give task_dim {theirs}')
    return estimator, controller


#: the summary of ``controller --help`` (with and without the flag)
HELP_SUMMARY = (f'{__doc__.strip().splitlines()[0]}\n{WITH_ESTIMATOR}: also run the estimator '
                "node in this process, handing it each estimate without a DDS hop (two nodes, "
                f"one process; 'controller {WITH_ESTIMATOR} --help' lists its parameters too).")


def main(args=None) -> int:
    """``controller [--with-estimator] [--ros-args ...]``; with the flag the process also runs the
    estimator node (:func:`~soft_gripper_sdre.nodes.composition.with_estimator`; ``-p`` reaches
    both nodes, each taking the names it declares, and each takes its own section of a
    parameters file). ``--help`` says so, and with the flag lists the estimator's parameters
    too."""
    argv = list(sys.argv if args is None else args)
    composed_run = WITH_ESTIMATOR in argv
    if composed_run:
        argv.remove(WITH_ESTIMATOR)
    if wants_help(argv[1:]):
        sys.stdout.write(composed_help('controller', HELP_SUMMARY, PARAMS) if composed_run
                         else format_help('controller', HELP_SUMMARY, PARAMS,
                                          f'[{WITH_ESTIMATOR}] '))
        return 0
    if not composed_run:
        return run(ControllerNode, argv)

    return run(composed, argv, composed_params(PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
