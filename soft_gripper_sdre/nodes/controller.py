"""The controller node: tracking of every finger with the learned SDC model.

The control law is the ``law`` parameter (:mod:`soft_gripper_sdre.control.laws`): ``sdre_ff``
(default: SDRE feedback plus model-inversion feedforward, with integral action unless
``integral_gain`` is 0), ``sdre`` (the paper's law), ``lqr``, ``pd``, ``computed_torque``, or the
Koopman baselines ``koopman_mpc`` and ``koopman_lqr``.

Subscribes ``state_estimate`` (one message per control period, keeping only the newest) and
``grasp_reference`` (the planned grasp, once per plan); publishes ``torque_commands`` (one per
estimate; with ``effort_topic`` also the same efforts as a ``std_msgs/Float64MultiArray`` in the
joint order of a ros2_control ``forward_command_controller``, ``effort_joints``) and
``/diagnostics`` (solves, Riccati check failures, fallbacks, saturation, compute
time, skipped estimates).

Which estimate is answered, and when, is decided by
:class:`~soft_gripper_sdre.control.command_gate.CommandGate`: each estimate is answered with the
plan once one covers its stamp; when estimates stop the controller sends nothing (the simulator
steps safely on its own) and a wall-time watchdog reports ERROR after ``estimate_watchdog``
(docs/design/loop_rules.md). This module is the ROS side: parameters, topics, conversions, status
and logs.

**Tuning at runtime.** ``q_pos``, ``q_vel``, ``r``, ``integral_gain``, ``integral_band``, ``pd_kp``
and ``pd_kd`` may be changed while the node runs (``ros2 param set /controller q_pos 2e6``). A
change is checked by building the law with the new values: a refused one returns its reason and
the old values stay in force. An accepted one takes effect at the next estimate: parameter
changes are executor callbacks like the estimates, so they never run inside a control step. The
law is built again with the new values and handed the state that keeps the command continuous
(the roll-off's last output, the integral's torque:
:func:`~soft_gripper_sdre.control.laws.hand_over`); the SDRE solves afresh, as after a
reset. The change is logged, and /diagnostics shows the values
in force (``weights``, ``integral``, ``pd_gains``). A value the law does not use (``pd_kp`` for
``sdre_ff``) is taken and has no effect.

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
from soft_gripper_sdre.control.compiled import plan_sample, warm_up
from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.control.laws import (
    DEFAULT_CT,
    DEFAULT_INTEGRAL,
    DEFAULT_LAW,
    DEFAULT_PD,
    GRAPH_LAWS,
    LAW_REGISTRY,
    hand_over,
    make_law,
    pd_gains,
)
from soft_gripper_sdre.control.riccati import Check
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    DEFAULT_WEIGHTS,
    Weights,
    roll_off_corner_hz,
)
from soft_gripper_sdre.learning.model import ModelFileError, SDCModel, set_torch_threads
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, OK, Diagnostics, ThrottledLogger, run
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    on_runtime_change,
)
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    NEWEST_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TORQUE_COMMANDS,
)

PARAMS = (
    Param('model_path', '', 'SDC model checkpoint (.pt); empty = the model shipped with the '
          'package', read_only=True),
    finger_names_param('the fingers controlled together: the joint names of state_estimate and '
                       'grasp_reference; torque_commands names <finger>/ax0, <finger>/ax1'),
    Param('q_pos', DEFAULT_WEIGHTS['q_pos'], 'SDRE state weight on tip position, Q = diag(q_pos, '
          'q_pos, q_vel, q_vel) (paper: 2 in sim units = 800 SI); every law but pd and '
          'computed_torque', '1/m²', 0.0, 1e12),
    Param('q_vel', DEFAULT_WEIGHTS['q_vel'], 'SDRE state weight on tip velocity', 's²/m²', 0.0,
          1e12),
    Param('r', DEFAULT_WEIGHTS['r'], 'SDRE input weight, R = diag(r, r) (paper: 0.1 in sim units = '
          '16000 SI)', '1/(N·m)²', 1e-12, 1e12),
    Param('torque_limit', 0.0625, 'saturation of each torque (0.0625 N·m = 25 sim units, the '
          'stable range of the physics step)', 'N·m', 1e-6, 1.0, read_only=True),
    Param('torque_lowpass_hz', DEFAULT_LOWPASS_HZ, 'first-order roll-off of the torque command '
          '(keeps the loop out of the finger\'s ~59 Hz bending mode; 0 = off); its corner is '
          'capped at a tenth of the control rate, 0.1 / control_period (10 Hz at 10 ms)', 'Hz',
          0.0, 500.0, read_only=True),
    Param('control_period', 0.001, 'period of the estimates (the roll-off filter\'s step)', 's',
          1e-4, 0.05, read_only=True),
    Param('solver', 'fast', 'Riccati solver: warm-started Newton–Kleinman or scipy reference',
          choices=('fast', 'reference'), read_only=True),
    Param('law', DEFAULT_LAW, 'control law (soft_gripper_sdre.control.laws): learned SDRE, LQR '
          'frozen at the origin, task-space PD, computed torque on the learned model; the oracle '
          'needs the plant\'s joint state and runs in-process only '
          '(tools/judging/evaluate.py); sdre_ff: SDRE + model-inversion feedforward '
          '(docs/results.md "Beyond the paper"); koopman_mpc, koopman_lqr: the Koopman baselines '
          'on the shipped Koopman model (models/koopman.npz; docs/results.md "Koopman baseline")',
          choices=GRAPH_LAWS, read_only=True),
    Param('state_weights', False, 'sdre only: state-dependent Q(x) that rises with the tracking '
          'error', read_only=True),
    Param('feedforward_at', 'x', "sdre_ff only: where the feedforward evaluates the learned model: "
          "'x' the estimated state (its error dynamics exactly linear), 'ref' the reference (no "
          'measurement noise reaches the model; what settings derived by training use)',
          choices=('x', 'ref'), read_only=True),
    Param('integral_gain', DEFAULT_INTEGRAL['gain'], 'sdre_ff only: integral action on the tip '
          'position error against the steady offset of joint friction, as a tip acceleration k_i '
          '∫(p_d − p)dt through the learned input map at rest; frozen while saturated, decaying '
          'while the error is outside integral_band (pressing on the cube); 0 = off', '1/s³', 0.0,
          1e8),
    Param('integral_band', DEFAULT_INTEGRAL['band'], 'sdre_ff only: tip error beyond which the '
          'integral stops integrating and decays (the reference is not reachable, e.g. inside the '
          'cube)', 'm', 1e-6, 0.1),
    Param('pd_kp', 0.0, 'pd and computed_torque only: the task-space gain on the tip position '
          "error, the error dynamics' natural frequency squared; 0 = the law's own tuned gain "
          f"({DEFAULT_PD['kp']:g} for pd, {DEFAULT_CT['kp']:g} for computed_torque)", '1/s²',
          0.0, 1e9),
    Param('pd_kd', 0.0, 'pd and computed_torque only: the gain on the tip velocity error, 2ζω; '
          f"0 = the law's own ({DEFAULT_PD['kd']:g} for pd, {DEFAULT_CT['kd']:g} for "
          'computed_torque)', '1/s', 0.0, 1e6),
    Param('estimate_watchdog', 0.5, 'wall time without a state_estimate after which the controller '
          'reports ERROR (it sends nothing without an estimate: the simulator steps safely on its '
          'own)', 's', 1e-2, 600.0),
    Param('reset_on_jump', 0.1, 'a stamp this far behind the last one (a simulator restart) resets '
          'the controller instead of being rejected (as in the estimator and trajectory node)', 's',
          1e-3, 1e6, read_only=True),
    Param('effort_topic', '', 'also publish each command as std_msgs/Float64MultiArray here, as a '
          'ros2_control forward_command_controller with the effort interface reads it '
          "(/<controller_name>/commands); '' = off", read_only=True),
    Param('effort_joints', cv.torque_names(FINGER_NAMES), 'effort_topic: for each joint of the '
          "forward_command_controller, in the order of its 'joints' list, the torque that drives "
          'it (<finger>/ax0 or <finger>/ax1); every torque once', read_only=True),
)


#: the parameters that may be changed while the node runs and retune the law
TUNABLE = ('q_pos', 'q_vel', 'r', 'integral_gain', 'integral_band', 'pd_kp', 'pd_kd')
#: the laws whose gains are not from the SDRE weights
FIXED_GAIN_LAWS = ('pd', 'computed_torque')


def rest_shift(model, names: tuple[str, ...]) -> np.ndarray | None:
    """(n, 2) p₀ − p₀ᶠ per finger: added to a finger's tip and reference, it puts the finger's own
    rest p₀ᶠ where the model's coordinates have theirs, p₀ (a model learned from several fingers
    that rest apart, each translated by its own rest in training); None when the model does not
    know every finger's rest, or they all rest where it does."""
    rests = model.finger_rests
    if not all(name in rests for name in names):
        return None
    shift = np.array([model.rest_tip[:2] - rests[name][:2] for name in names])
    return shift if np.any(shift != 0.0) else None


class ControllerNode(Node):
    """SDRE tracking controller on topics (see module doc)."""

    def __init__(self, *, subscribe_estimates: bool = True, **kwargs) -> None:
        """``subscribe_estimates=False``: no ``state_estimate`` subscription; the estimates come
        by :meth:`take_estimate` (an estimator node in the same process)."""
        super().__init__('controller', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        set_torch_threads(1)
        try:
            model = SDCModel(Path(p['model_path']).expanduser() if p['model_path'] else None)
        except ModelFileError as exc:
            raise ParameterError(f'model_path: {exc}') from None
        self.model = model
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        self.rest_shift = rest_shift(model, self.names)
        self.effort_order = None            # index into u.ravel() of each effort_topic entry
        if p['effort_topic']:
            try:
                self.effort_order = cv.effort_array_order(p['effort_joints'], self.names)
            except ValueError as exc:
                raise ParameterError(f'parameter \'effort_joints\': {exc}') from None
        self._retuned = None                # the law built by an accepted runtime change
        on_runtime_change(self, PARAMS, validate=self._validate, apply=self._apply)
        try:
            self.ctrl = self._build_law(p)
        except ValueError as exc:
            raise ParameterError(f'law/state_weights/integral_gain/pd_kp/pd_kd: {exc}') from None
        warm_up()       # compiled (or loaded from the cache) before any topic shows the node ready
        self.done = False
        self.exit_code = 0
        self._compute_s = []
        self._plan: Plan | None = None      # the plan the contiguous copies below are of
        self._plan_arrays: tuple = ()

        # the per-period messages travel as CDR bytes read / written at fixed offsets (nodes/cdr.py)
        self.cdr_estimate = cdr.estimate_codec(self.names)
        self.cdr_cmd = cdr.torques_codec(self.names)
        self.cdr_plan = PlanCodec(self.names)
        self.pub_cmd = self.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        self.pub_effort = self._effort_msg = None
        if self.effort_order is not None:
            self.pub_effort = self.create_publisher(Float64MultiArray, p['effort_topic'], LOOP_QOS)
            self._effort_msg = Float64MultiArray()      # layout: no dims, data_offset 0
        self.sub_est = None
        if subscribe_estimates:
            self.sub_est = self.create_subscription(MultiDOFJointTrajectory, STATE_ESTIMATE,
                                                    self.on_estimate, NEWEST_QOS, raw=True)
        self.sub_ref = self.create_subscription(MultiDOFJointTrajectory, GRASP_REFERENCE,
                                                self.on_reference, REFERENCE_QOS, raw=True)
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        self.gate = CommandGate(_ns(p['control_period']), _ns(p['reset_on_jump']),
                                p['estimate_watchdog'], counters=self.diag.counters)
        cdr.watch(self.diag, self.cdr_estimate, self.cdr_plan)
        self.diag.values['model'] = str(model.path)
        self.diag.values['law'] = p['law']
        self._show_gains()
        self.diag.values['roll_off_hz'] = (
            f'{roll_off_corner_hz(p["torque_lowpass_hz"], p["control_period"]):g}')
        self._watchdog = self.create_timer(
            0.05, lambda: self._act(self.gate.on_wall_time(time.monotonic())))
        self.diag.before_publish.append(self._compute_stats)
        integral_note = (f'; integral gain {p["integral_gain"]:g}' if self._uses('integral_gain')
                         else '')
        self.get_logger().info(
            f'model {model.path.name} (rest tip {1e3 * model.rest_tip[0]:.1f}, '
            f'{1e3 * model.rest_tip[1]:.1f} mm'
            f'{"; each finger at its own" if self.rest_shift is not None else ""}); '
            f'{self.diag.values["weights"]}; '
            f'limit {p["torque_limit"]:g} N·m, rolled off at {self.diag.values["roll_off_hz"]} Hz; '
            f'{p["solver"]} solver; law {p["law"]}'
            f'{" with Q(x)" if p["state_weights"] else ""}{integral_note}; '
            f'fingers {", ".join(self.names)}'
            + (f'; efforts also on {self.pub_effort.topic_name} for {", ".join(p["effort_joints"])}'
               if self.pub_effort is not None else ''))

    # -- inputs ------------------------------------------------------------------------------
    def on_reference(self, data: bytes) -> None:
        try:
            _, times, pos, vel, acc = self.cdr_plan.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_reference', str(exc))
            return
        self._act(self.gate.on_plan(times, pos, vel, acc), GRASP_REFERENCE)

    def on_estimate(self, data: bytes) -> None:
        try:
            stamp, x = self.cdr_estimate.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_estimate', str(exc))
            return
        self._act(self.gate.on_estimate(stamp, x, time.monotonic()), STATE_ESTIMATE)

    def take_estimate(self, stamp: int, x: np.ndarray) -> None:
        """The estimate (n, 4) stamped ``stamp`` [ns], handed over in-process by an estimator
        node of the same process and executor: answered as if it had come on the topic."""
        self._act(self.gate.on_estimate(stamp, x, time.monotonic()), STATE_ESTIMATE)

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
            self.ctrl.reset()
        elif change is Change.ESTIMATES_LOST:
            self._error(f'no state_estimate for {self.p["estimate_watchdog"]:g} s of wall time, '
                        f'the last stamped t = {t:.4f} s: commanding nothing')
        elif change is Change.ESTIMATES_BACK:
            self.diag.set_status(OK, 'estimates are back; tracking')
            self.get_logger().info(f'state estimates are back at t = {t:.4f} s; tracking resumes')

    def _error(self, why: str) -> None:
        """Enter ERROR with ``why`` (status and log)."""
        self.diag.set_status(ERROR, why)
        self.get_logger().error(why)

    # -- the law -----------------------------------------------------------------------------
    def _control(self, stamp: int, x: np.ndarray, plan: Plan) -> None:
        ref_pos, ref_vel, ref_acc = self._sample(plan, stamp)
        pos = x[:, :2]
        if self.rest_shift is not None:         # each finger into the model's frame
            pos, ref_pos = pos + self.rest_shift, ref_pos + self.rest_shift
        t0 = time.perf_counter()
        out = self.ctrl.compute(pos, x[:, 2:], ref_pos, ref_vel, ref_acc=ref_acc)
        self._compute_s.append(time.perf_counter() - t0)
        u = out.u
        if not np.isfinite(u).all():        # the core guarantees this; keep the promise here too
            self.diag.count('nonfinite_torque')
            u = np.zeros_like(u)
        self.pub_cmd.publish(self.cdr_cmd.encode(stamp, u))
        if self.pub_effort is not None:  # the same efforts in the joint order of ros2_control
            self._effort_msg.data = u.ravel()[self.effort_order].tolist()
            self.pub_effort.publish(self._effort_msg)
        self.diag.good('commands', 'tracking')
        count_solve(self.diag, self.log, out, stamp)

    def _sample(self, plan: Plan, stamp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The plan's position, velocity and acceleration (n, 2) at ``stamp``: :func:`sample_plan`
        compiled (the same bits), on the plan's arrays made contiguous once per plan."""
        if plan is not self._plan:
            self._plan = plan
            self._plan_arrays = (np.ascontiguousarray(plan.times, dtype=np.int64),
                                 *(np.ascontiguousarray(a, dtype=np.float64)
                                   for a in (plan.pos, plan.vel, plan.acc)))
        out = np.empty((3, self.n, 2))
        if plan_sample(*self._plan_arrays, stamp, out[0], out[1], out[2]):
            return out[0], out[1], out[2]
        return sample_plan(plan.times, plan.pos, plan.vel, plan.acc, stamp, with_acc=True)

    # -- the law and its tuning --------------------------------------------------------------
    def _uses(self, name: str) -> bool:
        """Whether the law in use reads the tunable parameter ``name``."""
        options = LAW_REGISTRY[self.p['law']].options
        if name in ('q_pos', 'q_vel', 'r'):
            return self.p['law'] not in FIXED_GAIN_LAWS
        if name in ('integral_gain', 'integral_band'):
            return 'integral_gain' in options
        return name in ('pd_kp', 'pd_kd') and 'pd_gains' in options

    def _build_law(self, p: dict):
        """The control law of the parameters ``p``.

        Raises:
            ValueError: a value the law refuses (the message names it).
        """
        options = LAW_REGISTRY[p['law']].options
        extra = {}
        if 'integral_gain' in options:
            extra.update(integral_gain=p['integral_gain'], integral_band=p['integral_band'])
        if 'ff_at' in options:
            extra['ff_at'] = p['feedforward_at']
        if 'pd_gains' in options:
            extra['pd_gains'] = pd_gains(p['law'], p['pd_kp'], p['pd_kd'])
        return make_law(p['law'], self.model, Weights(p['q_pos'], p['q_vel'], p['r']),
                        p['torque_limit'], n_fingers=self.n, method=p['solver'],
                        lowpass_hz=p['torque_lowpass_hz'], dt=p['control_period'],
                        adaptive=p['state_weights'], **extra)

    def _show_gains(self) -> None:
        """The tunable values in force, in /diagnostics."""
        p, values = self.p, self.diag.values
        values['weights'] = f'q_pos={p["q_pos"]:g} q_vel={p["q_vel"]:g} r={p["r"]:g}'
        values['integral'] = f'gain={p["integral_gain"]:g} band={p["integral_band"]:g}'
        gains = pd_gains(p['law'], p['pd_kp'], p['pd_kd'])
        values['pd_gains'] = f'kp={gains["kp"]:g} kd={gains["kd"]:g}'

    def _validate(self, new: dict) -> str | None:
        """Why the runtime change ``new`` is refused, or None; an accepted change to a value the
        law uses builds the law it will run (:meth:`_apply` puts it in force)."""
        self._retuned = None
        if not any(self._uses(name) for name in TUNABLE if name in new):
            return None
        try:
            self._retuned = self._build_law({**self.p, **new})
        except ValueError as exc:
            return f'{", ".join(sorted(new))}: {exc}'
        return None

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.gate.watchdog = self.p['estimate_watchdog']
        tuned = {name: new[name] for name in TUNABLE if name in new}
        if not tuned:
            return
        changes = ', '.join(f'{name} = {value:g}' for name, value in tuned.items())
        if self._retuned is None:
            self.get_logger().info(f'{changes}: not used by the {self.p["law"]} law, no effect')
        else:
            hand_over(self.ctrl, self._retuned)
            self.ctrl, self._retuned = self._retuned, None
            self.get_logger().info(f'{changes}: the {self.p["law"]} law is retuned from the next '
                                   'estimate')
        self._show_gains()

    def _compute_stats(self) -> None:
        """Mean and max compute time [µs] since the last /diagnostics, into its values."""
        if self._compute_s:
            c = np.asarray(self._compute_s) * 1e6
            self.diag.values['compute_us_mean'] = f'{c.mean():.0f}'
            self.diag.values['compute_us_max'] = f'{c.max():.0f}'
            self._compute_s.clear()


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


#: the command-line flag that runs the estimator node in the controller's process
WITH_ESTIMATOR = '--with-estimator'


def with_estimator() -> tuple[Node, Node]:
    """The estimator and the controller as two nodes of one process: each estimate is handed to
    the controller in-process (no DDS hop, no second process to wake) and still published on
    ``state_estimate``; the controller has no ``state_estimate`` subscription."""
    from soft_gripper_sdre.nodes.estimator import EstimatorNode
    controller = ControllerNode(subscribe_estimates=False)
    try:
        estimator = EstimatorNode()
    except BaseException:
        controller.destroy_node()
        raise
    estimator.listeners.append(controller.take_estimate)
    return estimator, controller


def main(args=None) -> int:
    """``controller [--with-estimator] [--ros-args ...]``; with the flag the process also runs the
    estimator node (:func:`with_estimator`; ``-p`` takes the controller's parameter names, the
    estimator's own come from its parameters file)."""
    argv = list(sys.argv if args is None else args)
    if WITH_ESTIMATOR in argv:
        argv.remove(WITH_ESTIMATOR)
        return run(with_estimator, argv)
    return run(ControllerNode, argv)


if __name__ == '__main__':
    raise SystemExit(main())
