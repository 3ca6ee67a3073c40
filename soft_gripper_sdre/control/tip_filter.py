"""Which tip measurements the estimator takes, and how: its rules between tips and estimates.

:class:`TipFilter` is the estimator node's loop logic without ROS, around the paper's
:class:`~soft_gripper_sdre.control.kf.ConstantVelocityKF`. The node decodes each tip message and
calls :meth:`TipFilter.on_tips` with its stamp and positions; the returned :class:`Outcome` says
which estimate to publish, which message to refuse, and which changes to report. The in-process
loop (:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`) calls it with the stamps
k·Δt. Stamps are integer nanoseconds; nothing reads a clock.

The rules (docs/design/loop_rules.md):

* the first measurement (after start or a reset) initialises the filter at the measured positions
  with zero velocity and is the estimate as it is (:attr:`Change.INITIALISED`);
* every later one is one predict + update over the stamp step Δt. A step of m whole nominal
  periods is taken period by period with the matrices built once (m − 1 predictions, then the
  update: the arithmetic of a fixed-rate loop); any other step with Δt built for it;
* a step of more than :data:`GAP_PERIODS` nominal periods is a gap: messages were lost. It is
  counted (``gaps``, and ``missed_periods``: the nominal periods without a message) and predicted
  through; one longer than ``max_bridge_ns`` is also a dropout (:attr:`Change.DROPOUT`);
* a jump of more than ``reset_jump_ns``, forwards (an outage too long to predict through) or
  backwards (the simulator restarting at t = 0), resets the filter (:attr:`Change.RESET`) and the
  measurement initialises it again;
* refused, leaving the filter untouched: a stamp equal to the last accepted one (``duplicate``),
  an older one within ``reset_jump_ns`` (``out_of_order``: a late message, overtaken by a newer
  one), positions of the wrong shape or not finite (``bad_message``).

A step of up to :data:`GAP_PERIODS` periods is neither counted nor reported, so a clean source
whose stamps jitter by ±20 % raises nothing.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
import enum
from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.kf import ConstantVelocityKF

NS = 1_000_000_000
#: a stamp step longer than this many nominal periods is a gap (±20 % jitter on each stamp gives
#: steps of at most 1.4 periods; one lost message gives about 2)
GAP_PERIODS = 1.5
#: default of ``reset_on_jump`` [s]: a stamp jump larger than this resets the filter
RESET_ON_JUMP = 0.1
#: default of ``max_bridge`` [s]: a gap longer than this is reported as a dropout
MAX_BRIDGE = 0.05


def make_kf(dt: float, accel_psd: float, meas_std: float, n: int,
            process_noise: str = 'independent', d: int = 2) -> ConstantVelocityKF:
    """The constant-velocity KF of ``n`` fingers whose tips have ``d`` coordinates (2 or 3): for
    d = 2 built exactly as the hand's loop builds it (its compiled step).

    Raises:
        ValueError: a value the filter refuses (d not 2 or 3 among them).
    """
    if d == 2:
        return ConstantVelocityKF(dt, accel_psd, meas_std, n=n, process_noise=process_noise)
    return ConstantVelocityKF(dt, accel_psd, meas_std, n=n, process_noise=process_noise, d=d)


class Change(enum.Enum):
    """A change the caller reports (log, and for RESET and DROPOUT a counted problem)."""

    RESET = 'the stamp jumped by more than reset_jump_ns: the filter starts over'
    DROPOUT = 'a gap longer than max_bridge_ns before this measurement, predicted through'
    INITIALISED = 'the filter was set at the measured positions with zero velocity'


class Notice(NamedTuple):
    """``change`` happened at the measurement stamped ``t_ns``; ``last_ns`` is the stamp of the
    measurement accepted before it (the jump's or the dropout's start; -1: none)."""

    change: Change
    t_ns: int
    last_ns: int = -1


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one measurement leads to: notices first (in order), then a refusal or an estimate."""

    estimate: np.ndarray | None = None   # (n, 2d) to publish with the measurement's stamp (a copy)
    refused: str | None = None           # counter key of a refused message
    reason: str = ''                     # why it was refused
    notices: tuple[Notice, ...] = ()


class TipFilter:
    """The estimator's first-message, reset, order, gap and dropout rules (module doc).

    Args:
        kf: the filter to initialise and step (:func:`make_kf`); its ``n`` is the number of
            fingers, its ``d`` the tips' coordinates.
        period_ns: the source's nominal period [ns]: it decides which stamp steps are gaps and
            which lie on the nominal grid.
        reset_jump_ns: a stamp jump larger than this (either direction) resets the filter.
        max_bridge_ns: a gap longer than this is also a dropout.
        counters: where to count (the node's diagnostics); a new Counter by default. Keys:
            ``gaps``, ``missed_periods``. Refused messages and the problems of notices (``resets``,
            ``dropouts``) are not counted here: the caller counts them with its warnings.

    ``reset_jump_ns`` and ``max_bridge_ns`` may be changed between calls.
    """

    def __init__(self, kf: ConstantVelocityKF, period_ns: int, reset_jump_ns: int,
                 max_bridge_ns: int, counters: Counter | None = None) -> None:
        self.kf = kf
        self.d = kf.d
        self.period_ns = int(period_ns)
        self.gap_ns = int(GAP_PERIODS * self.period_ns)
        self.reset_jump_ns = int(reset_jump_ns)
        self.max_bridge_ns = int(max_bridge_ns)
        self.counters = Counter() if counters is None else counters
        self.last_ns: int | None = None        # stamp of the last accepted measurement
        self._predict_only = np.zeros(kf.n, dtype=bool)
        self._steps = [0, 0]                   # accepted steps since take_mean_step: count, sum

    def on_tips(self, stamp: int, z: np.ndarray) -> Outcome:
        """The measured tip positions ``z`` (n, d) [m] stamped ``stamp`` [ns]."""
        if z.shape != (self.kf.n, self.d) or not np.isfinite(z).all():
            return Outcome(refused='bad_message', reason=(
                f'tip positions {z.shape}, or not finite; expected ({self.kf.n}, {self.d}) '
                'finite values'))
        last = self.last_ns
        if last is None:
            return self._initialise(stamp, z)
        step = stamp - last
        if abs(step) > self.reset_jump_ns:
            return self._initialise(stamp, z, Notice(Change.RESET, stamp, last))
        if step <= 0:
            return Outcome(refused='duplicate' if step == 0 else 'out_of_order', reason=(
                f'tip_positions stamp {stamp} ns is not newer than the last accepted {last} ns'))
        notices = self._count_gap(stamp, step) if step > self.gap_ns else ()
        periods, rest = divmod(step, self.period_ns)
        if rest == 0:        # on the nominal grid: period by period, with the matrices built once
            for _ in range(periods - 1):
                self.kf.step(z, self._predict_only)
            x = self.kf.step(z)
        else:
            x = self.kf.step(z, dt=step / NS)
        self._steps[0] += 1
        self._steps[1] += step
        self.last_ns = stamp
        return Outcome(x, notices=notices)

    def take_mean_step(self) -> float | None:
        """The mean accepted stamp step [ns] since the previous call (None: no step accepted)."""
        count, total = self._steps
        if not count:
            return None
        self._steps = [0, 0]
        return total / count

    def _count_gap(self, stamp: int, step: int) -> tuple[Notice, ...]:
        """Messages were lost before ``stamp``: count the gap; a dropout is also a notice."""
        missing = max(1, (step + self.period_ns // 2) // self.period_ns - 1)
        self.counters['gaps'] += 1
        self.counters['missed_periods'] += missing
        if step > self.max_bridge_ns:
            return (Notice(Change.DROPOUT, stamp, stamp - step),)
        return ()

    def _initialise(self, stamp: int, z: np.ndarray, *notices: Notice) -> Outcome:
        """First measurement after start or a reset: positions z, zero velocity."""
        self.kf.reset(z)
        self.last_ns = stamp
        return Outcome(self.kf.x.copy(), notices=(*notices, Notice(Change.INITIALISED, stamp)))
