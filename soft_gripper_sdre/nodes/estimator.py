"""The estimator node: the paper's constant-velocity Kalman filter on the measured tip positions.

Subscribes ``tip_positions`` (keeping only the newest: after a busy moment it goes on from the
present, predicting through what it skipped); publishes one ``state_estimate`` per accepted
measurement, stamped with the measurement's stamp, and ``/diagnostics``. ``task_dim`` says how
many coordinates of each tip are filtered: 2 (X, Y; the hand's planar tips, z ignored) or 3
(X, Y, Z); the estimate is [p; ṗ] of that many axes per finger. The rules are
:class:`~soft_gripper_sdre.control.tip_filter.TipFilter`'s, which the in-process loop
(:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`) shares: the first measurement
(after start or a reset) initialises the filter at the measured positions with zero velocity and
is published as is; every later one is one predict + update of
:class:`~soft_gripper_sdre.control.kf.ConstantVelocityKF`. The node decodes the messages, feeds
the filter, and publishes, logs and counts what it returns.

**Stamps and rates.** The filter's Δt is the difference of the measurement stamps, whatever the
source's rate and jitter: a mocap system at 120 Hz stamped with wall time is filtered as it comes.
``control_period`` is the source's *nominal* period. It decides only which stamp steps count as
gaps, and on the simulator's exact grid (a step of m whole periods) the filter steps period by
period with matrices built once, which is the arithmetic of the offline loop. Every received
message is either accepted (``estimates``) or rejected under one reason, so ``received`` =
``estimates`` + ``bad_message`` + ``duplicate`` + ``out_of_order``:

* a step of more than 1.5 nominal periods is a gap: messages were lost. Up to ``max_bridge``
  seconds the filter predicts through it quietly (counted: ``gaps``, and ``missed_periods``, the
  nominal periods without a message); a longer one, up to ``reset_on_jump``, is a dropout,
  reported (WARN, a throttled warning with the counts: ``dropouts``) and still predicted
  through;
* a jump of more than ``reset_on_jump`` seconds, forwards (an outage too long to predict through:
  a stalled driver, or this node starved of CPU on a busy machine) or backwards (the simulator
  restarting at t = 0), resets the filter (``resets``, WARN, a throttled warning with the count)
  and the measurement initialises it again. So what is predicted through is bounded by
  ``reset_on_jump``, not by ``max_bridge``;
* a stamp equal to the last accepted one is rejected (``duplicate``), an older one within
  ``reset_on_jump`` (a late message, overtaken by a newer one) too (``out_of_order``);
* malformed messages (wrong number of poses, NaN/Inf) are rejected (``bad_message``).

Rejected messages raise a throttled warning naming the problem; nothing is published for them
and the filter is untouched. A step of up to 1.5 nominal periods is neither counted nor
reported, so a clean source whose stamps jitter by ±20 % keeps the node OK. ``stamp_period_ms``
in /diagnostics is the mean stamp step accepted since the previous status.
"""
from __future__ import annotations

import copy
from typing import Callable

from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.kernels import warm_up
from soft_gripper_sdre.control.kf import PROCESS_NOISE_MODELS
from soft_gripper_sdre.control.tip_filter import (
    MAX_BRIDGE,
    RESET_ON_JUMP,
    Change,
    Notice,
    Outcome,
    TipFilter,
    make_kf,
)
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import Diagnostics, run
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    on_runtime_change,
)
from soft_gripper_sdre.nodes.topics import LOOP_QOS, NEWEST_QOS, STATE_ESTIMATE, TIP_POSITIONS

PARAMS = (
    finger_names_param('the fingers: pose i of tip_positions is finger i; the joint names of '
                       'state_estimate'),
    Param('task_dim', 2, "coordinates of each tip the filter estimates: 2 (X, Y: a planar tip, "
          "tip_positions' z ignored) or 3 (X, Y, Z: a 3-D tip); state_estimate then carries z",
          '', 2, 3, read_only=True),
    Param('control_period', 0.001, 'nominal period of the tip measurements: a stamp step over 1.5 '
          'periods is a gap (each KF step\'s Δt is the stamp difference)', 's', 1e-4, 0.05,
          read_only=True),
    Param('accel_psd', 1.0, 'white-acceleration intensity q of the process noise',
          '(m/s²)²/Hz', 0.0, 1e9, read_only=True),
    Param('meas_std', 5e-5, 'standard deviation of the tip measurement noise', 'm', 1e-9, 0.01,
          read_only=True),
    Param('process_noise', 'independent', "process-noise direction: one noise per axis, or the "
          "paper's D = [0 0 1 1]ᵀ", choices=PROCESS_NOISE_MODELS, read_only=True),
    Param('max_bridge', MAX_BRIDGE, 'a gap in the stamps up to this long is predicted through '
          'quietly (counted); a longer one, up to reset_on_jump, is predicted through and reported '
          'as a dropout (WARN)', 's', 1e-4, 1.0),
    Param('reset_on_jump', RESET_ON_JUMP, 'a tip stamp jump larger than this, either direction '
          '(forward: an outage, e.g. a stalled driver or a starved estimator; back: a restart), '
          'resets the filter (WARN); shorter gaps are predicted through', 's', 1e-3, 1.0),
    Param('tips_reliability', 'reliable', "reliability of the tip_positions subscription: "
          "'reliable' (the simulator: lockstep loses no period) or 'best_effort', which also "
          'matches a driver that publishes with the sensor-data QoS',
          choices=('reliable', 'best_effort'), read_only=True),
)

#: the counters every received message is counted under exactly one of
MESSAGE_OUTCOMES = ('estimates', 'bad_message', 'duplicate', 'out_of_order')


class EstimatorNode(Node):
    """Constant-velocity KF from ``tip_positions`` to ``state_estimate`` (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('estimator', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        self.d = int(p['task_dim'])
        try:
            self.kf = make_kf(p['control_period'], p['accel_psd'], p['meas_std'], self.n,
                              p['process_noise'], self.d)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        warm_up()       # compiled (or loaded from the cache) before any topic shows the node ready
        #: called with (stamp, estimate) for every estimate before it is published: a node of
        #: this process that takes the estimates without a DDS round trip (``controller
        #: --with-estimator``); the estimate is still published for everyone else
        self.listeners: list[Callable[[int, np.ndarray], None]] = []
        # both messages travel as CDR bytes read / written at fixed offsets (nodes/cdr.py)
        self.cdr_tips = cdr.tips_codec(self.names)
        self.cdr_estimate = cdr.estimate_codec(self.names, self.d)

        self.pub = self.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
        tips_qos = copy.copy(NEWEST_QOS)
        tips_qos.reliability = ReliabilityPolicy[p['tips_reliability'].upper()]
        self.sub = self.create_subscription(PoseArray, TIP_POSITIONS, self.on_tips, tips_qos,
                                            raw=True)
        self.diag = Diagnostics(self)
        self.filter = TipFilter(self.kf, _ns(p['control_period']), _ns(p['reset_on_jump']),
                                _ns(p['max_bridge']), counters=self.diag.counters)
        on_runtime_change(self, PARAMS, apply=self._apply)
        cdr.watch(self.diag, self.cdr_tips)
        self.diag.values['process_noise'] = p['process_noise']
        self.diag.values['task_dim'] = str(self.d)
        self.diag.before_publish.append(self._stamp_stats)
        self.get_logger().info(
            f'{self.n} fingers ({", ".join(self.names)}), {self.d}-D tips, '
            f'nominal period {1e3 * p["control_period"]:g} ms, q = {p["accel_psd"]:g} '
            f'(m/s²)²/Hz, σ = {1e3 * p["meas_std"]:g} mm, {p["process_noise"]} process noise')

    @property
    def jump_ns(self) -> int:
        """``reset_on_jump`` [ns]: a larger stamp jump resets the filter."""
        return self.filter.reset_jump_ns

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.filter.reset_jump_ns = _ns(self.p['reset_on_jump'])
        self.filter.max_bridge_ns = _ns(self.p['max_bridge'])

    def _stamp_stats(self) -> None:
        mean = self.filter.take_mean_step()
        if mean is not None:
            self.diag.values['stamp_period_ms'] = f'{mean / 1e6:.4g}'

    # -- measurements ------------------------------------------------------------------------
    def on_tips(self, data: bytes) -> None:
        self.diag.count('received')
        try:
            stamp, tips = self.cdr_tips.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_message', f'rejected: {exc}')
            return
        self._act(stamp, self.filter.on_tips(stamp, tips[:, :self.d]))

    def _act(self, stamp: int, outcome: Outcome) -> None:
        """Report the filter's notices, then publish its estimate or refuse the message."""
        for notice in outcome.notices:
            self._report(notice)
        if outcome.refused:
            self.diag.problem(outcome.refused, f'rejected ({outcome.refused}): {outcome.reason}')
        if outcome.estimate is not None:
            self._publish(stamp, outcome.estimate)
            self.diag.good('estimates', 'estimating')

    def _report(self, notice: Notice) -> None:
        change, t, last = notice.change, notice.t_ns / cv.NS, notice.last_ns
        c = self.diag.counters
        if change is Change.RESET:
            jump_ms = (notice.t_ns - last) / 1e6
            why = ('back: a restarted driver or simulator' if jump_ms < 0 else
                   'forward: an outage too long to predict through (a stalled driver, or this '
                   'node starved of CPU)')
            self.diag.problem('resets', f'tip_positions stamp jumped {why}, from '
                              f'{last / cv.NS:.4f} s to {t:.4f} s ({jump_ms:+.1f} ms, more '
                              f'than reset_on_jump {1e3 * self.p["reset_on_jump"]:g} ms); '
                              'filter reset '
                              f'({c["resets"] + 1} reset(s) in all)')
        elif change is Change.DROPOUT:
            gap_ms = (notice.t_ns - last) / 1e6
            self.diag.problem('dropouts', f'no tip_positions for {gap_ms:.1f} ms (more than '
                              f'max_bridge) before t = {t:.4f} s; predicting through it '
                              f'({c["dropouts"] + 1} dropout(s), {c["missed_periods"]} missed '
                              'period(s) in all)')
        elif change is Change.INITIALISED:
            self.get_logger().info(f'filter initialised at t = {t:.4f} s')

    def _publish(self, stamp: int, x: np.ndarray) -> None:
        for listener in self.listeners:
            listener(stamp, x.copy())
        self.pub.publish(self.cdr_estimate.encode(stamp, x))


def _ns(seconds: float) -> int:
    return int(round(seconds * cv.NS))


def main(args=None) -> int:
    return run(EstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
