"""The estimator node: the paper's constant-velocity Kalman filter on the measured tip positions.

Subscribes ``tip_positions`` (keeping only the newest: after a busy moment it goes on from the
present, predicting through what it skipped); publishes one ``state_estimate`` per accepted
measurement, stamped with the measurement's stamp, and ``/diagnostics``. The rules are those of
:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`: the first measurement (after start or a
reset) initialises the filter at the measured positions with zero velocity and is published as
is; every later one is one predict + update of :class:`~soft_gripper_sdre.control.kf.ConstantVelocityKF`
with Δt = ``control_period``.

Stamps are checked against that period. A step of m > 1 periods (lost measurements) predicts
through the m − 1 missing ones first (counted as ``gaps`` and ``missed_periods``); a step that
is not a whole number of periods is rounded to the nearest one (at least one) and counted
(``off_period``). A stamp that is not newer than the last is rejected (``stale``). A jump of more
than ``reset_on_jump`` seconds — backwards, as when the simulator restarts at t = 0, or forwards
over a long outage — resets the filter (``resets``, logged) and the measurement initialises it
again.

Malformed messages (wrong number of poses, NaN/Inf) are rejected with a throttled warning naming
the problem and counted (``bad_message``); nothing is published for them and the filter is
untouched.
"""
from __future__ import annotations

from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.node import Node
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.compiled import warm_up
from soft_gripper_sdre.control.kf import PROCESS_NOISE_MODELS, ConstantVelocityKF
from soft_gripper_sdre.nodes import cdr, conversions as cv
from soft_gripper_sdre.nodes.common import Diagnostics, run
from soft_gripper_sdre.nodes.params import (Param, ParameterError, declare_all, finger_names_param,
                                            on_runtime_change)
from soft_gripper_sdre.nodes.topics import LOOP_QOS, NEWEST_QOS, STATE_ESTIMATE, TIP_POSITIONS

PARAMS = (
    finger_names_param('the fingers: pose i of tip_positions is finger i; the joint names of '
                       'state_estimate'),
    Param('control_period', 0.001, 'period of the measurements: the KF step Δt and the expected '
          'stamp step', 's', 1e-4, 0.05, read_only=True),
    Param('accel_psd', 1.0, 'white-acceleration intensity q of the process noise',
          '(m/s²)²/Hz', 0.0, 1e9, read_only=True),
    Param('meas_std', 5e-5, 'standard deviation of the tip measurement noise', 'm', 1e-9, 0.01,
          read_only=True),
    Param('process_noise', 'independent', "process-noise direction: one noise per axis, or the "
          "paper's D = [0 0 1 1]ᵀ", choices=PROCESS_NOISE_MODELS, read_only=True),
    Param('reset_on_jump', 0.1, 'a stamp jump larger than this (either direction) resets the filter; '
          'shorter gaps are predicted through period by period, hence the bound', 's', 1e-3, 1.0),
)


class EstimatorNode(Node):
    """Constant-velocity KF from ``tip_positions`` to ``state_estimate`` (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('estimator', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        try:
            self.kf = ConstantVelocityKF(p['control_period'], p['accel_psd'], p['meas_std'], n=self.n,
                                         process_noise=p['process_noise'])
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        warm_up()       # compiled (or loaded from the cache) before any topic shows the node ready
        self.period_ns = int(round(p['control_period'] * cv.NS))
        self.jump_ns = int(round(p['reset_on_jump'] * cv.NS))
        on_runtime_change(self, PARAMS, apply=self._apply)

        self.last_ns: int | None = None          # stamp of the last accepted measurement
        self._predict_only = np.zeros(self.n, dtype=bool)
        # both messages travel as CDR bytes read / written at fixed offsets (nodes/cdr.py)
        self.cdr_tips = cdr.tips_codec(self.names)
        self.cdr_estimate = cdr.estimate_codec(self.names)

        self.pub = self.create_publisher(MultiDOFJointTrajectory, STATE_ESTIMATE, LOOP_QOS)
        self.sub = self.create_subscription(PoseArray, TIP_POSITIONS, self.on_tips, NEWEST_QOS, raw=True)
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_tips)
        self.diag.values['process_noise'] = p['process_noise']
        self.get_logger().info(
            f'{self.n} fingers ({", ".join(self.names)}), Δt = {1e3 * p["control_period"]:g} ms, q = {p["accel_psd"]:g} '
            f'(m/s²)²/Hz, σ = {1e3 * p["meas_std"]:g} mm, {p["process_noise"]} process noise')

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        self.jump_ns = int(round(self.p['reset_on_jump'] * cv.NS))

    # -- measurements ------------------------------------------------------------------------
    def on_tips(self, data: bytes) -> None:
        try:
            stamp, tips = self.cdr_tips.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_message', f'rejected: {exc}')
            return
        z = tips[:, :2]
        last = self.last_ns
        if last is None:
            self._initialise(stamp, z)
            return
        step = stamp - last
        if abs(step) > self.jump_ns:
            self.diag.problem('resets', f'tip_positions stamp jumped from {last / cv.NS:.4f} s to '
                              f'{stamp / cv.NS:.4f} s (more than reset_on_jump); filter reset')
            self._initialise(stamp, z)
            return
        if step <= 0:
            self.diag.problem('stale', f'rejected: tip_positions stamp {stamp} ns is not newer than '
                              f'the last {last} ns')
            return
        periods = max(1, (step + self.period_ns // 2) // self.period_ns)
        if step != periods * self.period_ns:
            self.diag.problem('off_period', f'tip_positions stamp step {step} ns is not a multiple of '
                              f'control_period ({self.period_ns} ns); treated as {periods} period(s)')
        if periods > 1:
            self.diag.count('missed_periods', periods - 1)
            self.diag.problem('gaps', f'{periods - 1} measurement(s) missing before t = '
                              f'{stamp / cv.NS:.4f} s; predicting through them')
            for _ in range(periods - 1):
                self.kf.step(z, self._predict_only)
        self.kf.step(z)
        self._accept(stamp)

    def _initialise(self, stamp: int, z: np.ndarray) -> None:
        """First measurement after start or reset: positions z, zero velocity (as closed_loop.py)."""
        self.kf.reset(z)
        self.get_logger().info(f'filter initialised at t = {stamp / cv.NS:.4f} s')
        self._accept(stamp)

    def _accept(self, stamp: int) -> None:
        self.last_ns = stamp
        self._publish(stamp, self.kf.x)
        self.diag.good('estimates', 'estimating')

    def _publish(self, stamp: int, x: np.ndarray) -> None:
        self.pub.publish(self.cdr_estimate.encode(stamp, x))


def main(args=None) -> int:
    return run(EstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
