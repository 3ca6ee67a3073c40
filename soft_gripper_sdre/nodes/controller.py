"""The controller node: tracking of all four fingers with the learned SDC model.

The control law is the ``law`` parameter (:mod:`soft_gripper_sdre.control.laws`): ``sdre_ff`` (default:
SDRE feedback plus model-inversion feedforward), ``sdre`` (the paper's law), ``lqr`` or ``pd``.

Subscribes ``state_estimate`` (one message per control period), ``grasp_reference`` (a short
horizon a few tens of times per second) and ``/clock`` (sim time, for lost estimates, below);
publishes ``torque_commands`` stamped with the estimate's time (safe commands: with the tick's),
and ``/diagnostics`` (solves, Riccati check failures, fallbacks, saturation, compute time).

For each estimate stamped t_k the reference is sampled at t_k from the newest horizon that covers
it; if none does yet (the trajectory node's message for this instant is still in flight), the
estimate waits and is answered as soon as a covering reference arrives — the answer never depends
on which message won the race, so lockstep runs stay deterministic.

Nothing bad ever reaches the actuators: malformed, non-finite, wrong-size or old messages are
rejected (throttled warning, counted) and produce no torque; the SDRE core falls back to the last
valid gains when a Riccati check fails and saturates at ``torque_limit``; a torque that is still
not finite is replaced by zero and counted.

Lost estimates are judged in sim time. The node follows ``/clock``; on a tick t when no estimate
has arrived for ``estimate_timeout`` of sim time (two control periods by default; an estimate
"arrives at" the newer of its stamp and the tick then current), it publishes its safe command,
zero torque stamped t (the lockstep simulator accepts it: it answers the period the simulator
is waiting on), counts it (``safe_commands``) and reports ERROR until an estimate arrives again;
tracking then resumes. While estimates flow, the estimate of the previous period has always
arrived before the simulator publishes the next tick, so a fault-free lockstep run never takes
this path. An estimator that is alive but behind (just restarted, or starved of CPU) is not
silent: its estimates for instants already answered are skipped (``late_estimates``), no safe
command is sent, and the simulator waits for it (its ``lockstep_timeout``) until it has caught
up — the loop is never driven past a slow estimator. Only the instant the estimates come back is
ambiguous: if its tick wins the race against its estimate, that one period is still answered
with zero.

A wall-time watchdog is the last resort for when sim time itself stops (the simulator is dead or
hung): after ``clock_timeout`` seconds of wall time without a tick or an estimate (1 s by default,
twice the simulator's ``lockstep_timeout``, so that a live simulator waiting out a lost period is
not mistaken for a stopped one and the sim-time rule above stays in charge) the node
reports ERROR ("sim time stopped") and publishes zero torque for the newest instant it knows, if
that instant is still unanswered (a simulator still waiting on it takes it); no later instant can
be stamped honestly, so nothing more is sent until time moves again.
A missing or bad model file ends the node at start-up with a message and a non-zero status.
"""
from __future__ import annotations

from collections import deque
from pathlib import Path
import time

import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
import torch
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.control.horizon import sample_horizon
from soft_gripper_sdre.control.laws import DEFAULT_LAW, GRAPH_LAWS, make_law
from soft_gripper_sdre.learning.model import ModelFileError, SDCModel
from soft_gripper_sdre.nodes import cdr, conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, OK, Diagnostics, ThrottledLogger, run
from soft_gripper_sdre.nodes.params import Param, ParameterError, declare_all, on_runtime_change
from soft_gripper_sdre.nodes.topics import (CLOCK, CLOCK_QOS, GRASP_REFERENCE, LOOP_QOS, REFERENCE_QOS,
                                            STATE_ESTIMATE, TORQUE_COMMANDS)
from soft_gripper_sdre.control.riccati import Check

PARAMS = (
    Param('model_path', '', 'SDC model checkpoint (.pt); empty = the model shipped with the package',
          read_only=True),
    Param('n_fingers', 4, 'fingers controlled together', '', 1, 4, read_only=True),
    Param('q_pos', DEFAULT_WEIGHTS['q_pos'], 'SDRE state weight on tip position, Q = diag(q_pos, q_pos, '
          'q_vel, q_vel) (paper: 2 in sim units = 800 SI)', '1/m²', 0.0, 1e12, read_only=True),
    Param('q_vel', DEFAULT_WEIGHTS['q_vel'], 'SDRE state weight on tip velocity', 's²/m²', 0.0, 1e12,
          read_only=True),
    Param('r', DEFAULT_WEIGHTS['r'], 'SDRE input weight, R = diag(r, r) (paper: 0.1 in sim units = '
          '16000 SI)', '1/(N·m)²', 1e-12, 1e12, read_only=True),
    Param('torque_limit', 0.0625, 'saturation of each torque (0.0625 N·m = 25 sim units, the '
          'stable range of the physics step)', 'N·m', 1e-6, 1.0, read_only=True),
    Param('torque_lowpass_hz', DEFAULT_LOWPASS_HZ, 'first-order roll-off of the torque command '
          '(keeps the loop out of the finger\'s ~59 Hz bending mode; 0 = off)', 'Hz', 0.0, 500.0,
          read_only=True),
    Param('control_period', 0.001, 'period of the estimates (the roll-off filter\'s step)', 's',
          1e-4, 0.05, read_only=True),
    Param('solver', 'fast', 'Riccati solver: warm-started Newton–Kleinman or scipy reference',
          choices=('fast', 'reference'), read_only=True),
    Param('law', DEFAULT_LAW, 'control law (soft_gripper_sdre.control.laws): learned SDRE, LQR frozen at the '
          'origin, task-space PD; the oracle needs the plant\'s joint state and runs in-process only '
          '(tools/evaluate.py); sdre_ff: SDRE + model-inversion feedforward (README "Beyond the paper")',
          choices=GRAPH_LAWS, read_only=True),
    Param('state_weights', False, 'sdre only: state-dependent Q(x) that rises with the tracking error',
          read_only=True),
    Param('estimate_timeout', 0.002, 'sim time without an arriving estimate before the safe '
          'command (zero torque) is sent; more than control_period (default: 2 periods)', 's',
          1e-4, 60.0),
    Param('reset_on_jump', 0.1, 'a stamp this far behind the last one (a simulator restart) resets '
          'the controller instead of being rejected (as in the estimator and trajectory node)', 's',
          1e-3, 1e6, read_only=True),
    Param('clock_timeout', 1.0, 'wall time without /clock or an estimate after which sim time is '
          'taken to have stopped (ERROR; zero torque for the newest unanswered instant); keep it '
          "longer than the simulator's lockstep_timeout, or a live simulator waiting out a lost "
          'period is taken for a stopped one', 's', 1e-2, 600.0),
)


class ControllerNode(Node):
    """SDRE tracking controller on topics (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('controller', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        torch.set_num_threads(1)
        try:
            model = SDCModel(Path(p['model_path']).expanduser() if p['model_path'] else None)
        except ModelFileError as exc:
            raise ParameterError(f'model_path: {exc}') from None
        try:
            weights = Weights(p['q_pos'], p['q_vel'], p['r'])
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        self.n = p['n_fingers']
        self.jump_ns = int(p['reset_on_jump'] * cv.NS)
        reason = _check_timeouts(p)
        if reason:
            raise ParameterError(reason)
        self.timeout_ns = int(round(p['estimate_timeout'] * cv.NS))
        on_runtime_change(self, PARAMS, validate=lambda new: _check_timeouts({**self.p, **new}),
                          apply=self._apply)
        try:
            self.ctrl = make_law(p['law'], model, weights, p['torque_limit'], n_fingers=self.n,
                                 method=p['solver'], lowpass_hz=p['torque_lowpass_hz'],
                                 dt=p['control_period'], adaptive=p['state_weights'])
        except ValueError as exc:
            raise ParameterError(f'law/state_weights: {exc}') from None
        self.done = False
        self.exit_code = 0

        self.refs: deque = deque(maxlen=4)     # (start ns, end ns, times, pos, vel, acc), newest last
        self.pending: tuple[int, np.ndarray] | None = None   # estimate waiting for a reference
        self.last_est_ns = -1
        self.last_ref_ns = -1
        self.last_cmd_ns = -1
        self.clock_ns = -1                      # newest /clock tick
        self.est_heard_ns = -1                  # sim time at which the last estimate arrived
        self.last_heard = time.monotonic()      # wall time of the last tick or estimate
        self.stale = False                      # no estimate for estimate_timeout of sim time
        self.clock_stopped = False              # nothing heard for clock_timeout of wall time
        self._compute_s = []

        # the per-period messages travel as CDR bytes read / written at fixed offsets (nodes/cdr.py)
        self.cdr_estimate = cdr.estimate_codec(self.n)
        self.cdr_clock = cdr.clock_codec()
        self.cdr_cmd = cdr.torques_codec(self.n)
        self.pub_cmd = self.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        self.sub_est = self.create_subscription(MultiDOFJointTrajectory, STATE_ESTIMATE,
                                                self.on_estimate, LOOP_QOS, raw=True)
        self.sub_ref = self.create_subscription(MultiDOFJointTrajectory, GRASP_REFERENCE,
                                                self.on_reference, REFERENCE_QOS)
        self.sub_clock = self.create_subscription(Clock, CLOCK, self.on_clock, CLOCK_QOS, raw=True)
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_estimate, self.cdr_clock)
        self.diag.values['model'] = str(model.path)
        self.diag.values['weights'] = f'q_pos={weights.q_pos:g} q_vel={weights.q_vel:g} r={weights.r:g}'
        self._watchdog = self.create_timer(0.05, self._check_clock)
        self.diag.before_publish.append(self._compute_stats)
        self.get_logger().info(
            f'model {model.path.name} (rest tip {1e3 * model.rest_tip[0]:.1f}, '
            f'{1e3 * model.rest_tip[1]:.1f} mm); {self.diag.values["weights"]}; '
            f'limit {p["torque_limit"]:g} N·m; {p["solver"]} solver; law {p["law"]}'
            f'{" with Q(x)" if p["state_weights"] else ""}')

    # -- inputs ------------------------------------------------------------------------------
    def on_reference(self, msg: MultiDOFJointTrajectory) -> None:
        try:
            stamp, times, pos, vel, acc = cv.msg_to_reference(msg, self.n)
        except cv.MessageError as exc:
            self._reject('bad_reference', str(exc))
            return
        if stamp < self.last_ref_ns - self.jump_ns:
            self._restart(stamp, 'grasp_reference')
        if stamp < self.last_ref_ns:
            self._reject('old_reference', f'grasp_reference: stamp {stamp} ns is older than the '
                         f'last accepted {self.last_ref_ns} ns')
            return
        self.last_ref_ns = stamp
        self.refs.append((int(times[0]), int(times[-1]), times, pos, vel, acc))
        self.diag.count('references')
        if self.pending is not None:
            ref = self._covering(self.pending[0])
            if ref is not None:
                stamp_est, x = self.pending
                self.pending = None
                self._control(stamp_est, x, ref)

    def on_estimate(self, data: bytes) -> None:
        try:
            stamp, x = self.cdr_estimate.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_estimate', str(exc))
            return
        if stamp < self.last_est_ns - self.jump_ns:
            self._restart(stamp, 'state_estimate')
        if stamp <= self.last_est_ns:
            self._reject('old_estimate', f'state_estimate: stamp {stamp} ns is not newer than the '
                         f'last accepted {self.last_est_ns} ns')
            return
        self.last_est_ns = stamp
        self.est_heard_ns = max(stamp, self.clock_ns)
        self._heard()
        if self.stale:
            self.stale = False
            self.diag.set_status(OK, 'estimates are back; tracking')
            self.get_logger().info(f'state estimates are back at t = {stamp / cv.NS:.4f} s; tracking resumes')
        self.diag.count('estimates')
        if stamp <= self.last_cmd_ns:           # this instant already got the safe command
            self.diag.count('late_estimates')
            self.pending = None
            return
        ref = self._covering(stamp)
        if ref is None:
            if self.pending is not None:
                self.diag.count('unanswered_estimates')   # superseded before any reference came
            self.pending = (stamp, x)
            return
        self.pending = None
        self._control(stamp, x, ref)

    def _restart(self, stamp: int, topic: str) -> None:
        """Time went back (the simulator restarted): forget references, estimates and warm starts."""
        self.get_logger().warning(f'{topic}: time jumped back to {stamp / cv.NS:.3f} s; resetting')
        self.diag.count('resets')
        self.refs.clear()
        self.pending = None
        self.last_est_ns = self.last_ref_ns = self.last_cmd_ns = self.clock_ns = self.est_heard_ns = -1
        self.ctrl.reset()

    def _covering(self, t_ns: int):
        """The newest stored horizon whose span holds ``t_ns``, or None."""
        for ref in reversed(self.refs):
            if ref[0] <= t_ns <= ref[1]:
                return ref
        return None

    def _reject(self, key: str, why: str) -> None:
        self.diag.problem(key, f'rejected: {why}')

    # -- the law -----------------------------------------------------------------------------
    def _control(self, stamp: int, x: np.ndarray, ref: tuple) -> None:
        _, _, times, pos, vel, acc = ref
        ref_pos, ref_vel, ref_acc = sample_horizon(times, pos, vel, acc, stamp, with_acc=True)
        t0 = time.perf_counter()
        out = self.ctrl.compute(x[:, :2], x[:, 2:], ref_pos, ref_vel, ref_acc=ref_acc)
        self._compute_s.append(time.perf_counter() - t0)
        u = out.u
        if not np.all(np.isfinite(u)):          # the core guarantees this; keep the promise here too
            self.diag.count('nonfinite_torque')
            u = np.zeros_like(u)
        self.pub_cmd.publish(self.cdr_cmd.encode(stamp, u))
        self.last_cmd_ns = stamp
        d = self.diag
        d.good('commands', 'tracking')
        if not out.ok.all():
            d.count('check_failures', int((~out.ok).sum()))
            for flag in Check:
                hits = int(np.count_nonzero(out.failed_checks & flag))
                if hits:
                    d.count(f'failed_{flag.name.lower()}', hits)
        if out.fallback.any():
            d.count('fallbacks', int(out.fallback.sum()))
            self.log.warn('fallback', f'Riccati checks failed for fingers '
                          f'{np.flatnonzero(out.fallback).tolist()} at t = {stamp / cv.NS:.3f} s; '
                          'using the last valid gains')
        if out.saturated.any():
            d.count('saturated', int(out.saturated.sum()))
        res = float(np.max(out.residual))
        if res > float(d.values.get('max_residual', '0')):
            d.values['max_residual'] = f'{res:.3g}'

    # -- liveness ----------------------------------------------------------------------------
    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.timeout_ns = int(round(self.p['estimate_timeout'] * cv.NS))

    def _heard(self) -> None:
        self.last_heard = time.monotonic()
        if self.clock_stopped:
            self.clock_stopped = False
            if not self.stale:
                self.diag.set_status(OK, 'sim time moves again')

    def on_clock(self, data: bytes) -> None:
        """Each sim-time tick: the safe command if the newest estimate is too old (module doc)."""
        try:
            t, _ = self.cdr_clock.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_clock', str(exc))
            return
        if self.clock_ns >= 0 and t < self.clock_ns - self.jump_ns:
            self._restart(t, '/clock')
        self.clock_ns = max(self.clock_ns, t)
        self.diag.count('ticks')
        self._heard()
        if self.est_heard_ns < 0 or t - self.est_heard_ns < self.timeout_ns or t <= self.last_cmd_ns:
            return
        if not self.stale:
            self.stale = True
            self._error(f'no state_estimate since t = {self.est_heard_ns / cv.NS:.4f} s (estimate_timeout '
                        f'{self.p["estimate_timeout"]:g} s of sim time): commanding zero torque')
        self._safe_command(t)

    def _error(self, why: str) -> None:
        """Enter ERROR with ``why`` (status and log)."""
        self.diag.set_status(ERROR, why)
        self.get_logger().error(why)

    def _safe_command(self, stamp: int) -> None:
        """Zero torque for the instant ``stamp``; the pending estimate, if any, is superseded."""
        self.pending = None
        self.pub_cmd.publish(self.cdr_cmd.encode(stamp, np.zeros((self.n, 2))))
        self.last_cmd_ns = stamp
        self.diag.count('safe_commands')

    def _check_clock(self) -> None:
        """Last resort (wall time): sim time has stopped, so the sim-time rule cannot fire."""
        newest = max(self.clock_ns, self.last_est_ns)
        if newest < 0 or time.monotonic() - self.last_heard < self.p['clock_timeout']:
            return
        if not self.clock_stopped:
            self.clock_stopped = True
            self._error(f'no /clock or state_estimate for {self.p["clock_timeout"]:g} s of wall time: '
                        f'sim time stopped at {newest / cv.NS:.4f} s')
        if newest > self.last_cmd_ns:
            self._safe_command(newest)

    def _compute_stats(self) -> None:
        """Mean and max compute time [µs] since the last /diagnostics, into its values."""
        if self._compute_s:
            c = np.asarray(self._compute_s) * 1e6
            self.diag.values['compute_us_mean'] = f'{c.mean():.0f}'
            self.diag.values['compute_us_max'] = f'{c.max():.0f}'
            self._compute_s.clear()


def _check_timeouts(p: dict) -> str | None:
    """Why the timeouts in ``p`` are refused, or None."""
    if not p['estimate_timeout'] > p['control_period']:
        return (f"parameter 'estimate_timeout': {p['estimate_timeout']} s must be more than one "
                f"control_period ({p['control_period']} s): every tick is a period ahead of the "
                'newest estimate')
    return None


def main(args=None) -> int:
    return run(ControllerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
