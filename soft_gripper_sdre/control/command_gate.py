"""When the controller answers, and with what: the rules between its inputs and its torque commands.

:class:`CommandGate` is the controller node's loop logic without ROS. The node feeds it every
accepted grasp plan and state estimate, plus the wall time on a timer; each call returns an
:class:`Outcome` saying what to compute and publish (an :class:`Answer`: an estimate and the plan
to track there), which message to refuse, and which status changes to report. All times are
arguments: sim time as integer nanosecond stamps, wall time as float seconds, so the rules run the
same under a test, a node or a replay.

The rules (docs/design/loop_rules.md):

* an estimate is answered with the newest plan, once a plan covers its stamp; until then it
  waits, so the answer does not depend on which message arrived first;
* the controller answers estimates only: when they stop, it sends nothing (the simulator's own
  rules step the physics safely) and reports ERROR after ``watchdog`` seconds of wall time without
  one, OK again with the next; estimates that stop once they have passed the plan's end are the
  run ending (a simulator or driver that finished), reported as such and not as an error;
* estimates are taken in stamp order: an estimate not newer than the last is refused; a gap in
  the stamps is counted as skipped estimates (the node keeps only the newest message);
* a stamp ``reset_jump_ns`` behind the newest estimate (a restarted simulator) resets the gate:
  the waiting estimate and the plan are forgotten, unless the plan arrived at the end of the old
  run (within ``reset_jump_ns`` of its newest estimate): then it is the new run's plan, which beat
  the new run's first estimate.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
import enum
from typing import NamedTuple

import numpy as np


class Plan(NamedTuple):
    """A planned reference: points at absolute times ``times`` [ns] from ``start`` to ``end``; it
    covers every instant from ``start`` on (after ``end`` it holds its last point)."""

    start: int
    end: int
    times: np.ndarray            # (h,) strictly increasing [ns]
    pos: np.ndarray              # (h, n, d) [m]
    vel: np.ndarray              # (h, n, d) [m/s]
    acc: np.ndarray              # (h, n, d) [m/s²]


@dataclass(frozen=True, slots=True)
class Answer:
    """Compute and publish the law's torque for ``estimate`` (n, 2d) tracking ``plan``, stamped
    ``stamp``."""

    stamp: int
    estimate: np.ndarray
    plan: Plan


class Change(enum.Enum):
    """A change the node reports (status, log, and for RESET the law's own reset)."""

    RESET = 'time jumped back: the waiting estimate, the stamps and the law state are forgotten'
    ESTIMATES_LOST = 'no estimate for the watchdog time of wall time (ERROR)'
    RUN_ENDED = ('no estimate for the watchdog time, the last at or past the plan\'s end: the run '
                 'is over')
    ESTIMATES_BACK = 'an estimate arrived after estimates were lost: tracking again (OK)'


class Notice(NamedTuple):
    """``change`` happened; ``t_ns`` is the stamp it concerns: the stamp time jumped back to
    (RESET), the stamp of the last estimate (ESTIMATES_LOST, RUN_ENDED), the returning estimate's
    stamp (ESTIMATES_BACK)."""

    change: Change
    t_ns: int


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one input leads to: notices first (in order), then a refusal or an answer."""

    answer: Answer | None = None
    refused: str | None = None       # counter key of a refused message ('old_estimate')
    reason: str = ''                 # why it was refused
    notices: tuple[Notice, ...] = ()


NOTHING = Outcome()


class CommandGate:
    """The controller's covering-plan, estimate-order, reset and watchdog rules (module doc).

    Args:
        period_ns: the nominal control period [ns]: a step of m periods between two estimates
            (rounded to the nearest whole number) counts m − 1 skipped estimates.
        reset_jump_ns: how far a stamp may fall behind the newest estimate before it is taken
            for a restart of time rather than refused as old.
        watchdog: wall time [s] without an estimate before estimates are reported lost.
        counters: where to count (the node's diagnostics); a new Counter by default. Keys:
            ``references`` (plans), ``estimates``, ``skipped_estimates`` (stamps never received,
            within ``reset_jump_ns``), ``unanswered_estimates`` (superseded while waiting for a
            plan), ``resets``. Refused messages are not counted here: the caller counts them with
            its other rejections (:attr:`Outcome.refused`).

    ``watchdog`` may be changed between calls.
    """

    def __init__(self, period_ns: int, reset_jump_ns: int, watchdog: float,
                 counters: Counter | None = None) -> None:
        self.period_ns = int(period_ns)
        self.reset_jump_ns = int(reset_jump_ns)
        self.watchdog = float(watchdog)
        self.counters = Counter() if counters is None else counters
        self.plan: Plan | None = None
        self.plan_after_ns = -1                # the newest estimate stamp when the plan arrived
        self.pending: tuple[int, np.ndarray] | None = None   # estimate waiting for a plan
        self.last_estimate_ns = -1
        self.past_plan_end = False             # the last estimate at or past its plan's end
        self.last_heard: float | None = None   # wall time of the last estimate
        self.estimates_lost = False

    # -- inputs ------------------------------------------------------------------------------
    def on_plan(self, times: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                acc: np.ndarray) -> Outcome:
        """A validated plan (``times`` absolute, increasing): it replaces the stored one, and the
        waiting estimate is answered if the plan covers it."""
        self.plan = Plan(int(times[0]), int(times[-1]), times, pos, vel, acc)
        self.plan_after_ns = self.last_estimate_ns
        self.counters['references'] += 1
        if self.pending is not None and self.covers(self.pending[0]):
            stamp, x = self.pending
            self.pending = None
            return Outcome(Answer(stamp, x, self.plan))
        return NOTHING

    def on_estimate(self, stamp: int, x: np.ndarray, wall: float) -> Outcome:
        """A validated state estimate (n, 2d) stamped ``stamp``, received at wall time ``wall``."""
        notices = []
        last = self.last_estimate_ns
        if stamp < last - self.reset_jump_ns:
            notices.append(self._reset(stamp))
        elif stamp <= last:
            return Outcome(refused='old_estimate', reason=(
                f'state_estimate: stamp {stamp} ns is not newer than the last accepted {last} ns'))
        elif last >= 0 and stamp - last <= self.reset_jump_ns:
            # the nearest whole number of periods: a jittery source's steps are not exact multiples
            self.counters['skipped_estimates'] += max(
                0, (stamp - last + self.period_ns // 2) // self.period_ns - 1)
        self.last_estimate_ns = stamp
        self.past_plan_end = self.plan is not None and stamp >= self.plan.end
        self.last_heard = wall
        if self.estimates_lost:
            self.estimates_lost = False
            notices.append(Notice(Change.ESTIMATES_BACK, stamp))
        self.counters['estimates'] += 1
        answer = None
        if self.covers(stamp):
            self.pending = None
            answer = Answer(stamp, x, self.plan)
        else:
            if self.pending is not None:
                self.counters['unanswered_estimates'] += 1
            self.pending = (stamp, x)
        return Outcome(answer, notices=tuple(notices)) if answer or notices else NOTHING

    def on_wall_time(self, wall: float) -> Outcome:
        """The wall clock reads ``wall`` [s]: once no estimate came for ``watchdog``, estimates
        are reported lost, or the run ended if the last was at or past the end of the plan in
        force when it came (once; nothing is answered)."""
        if self.estimates_lost or self.last_heard is None or wall - self.last_heard < self.watchdog:
            return NOTHING
        self.estimates_lost = True
        change = Change.RUN_ENDED if self.past_plan_end else Change.ESTIMATES_LOST
        return Outcome(notices=(Notice(change, self.last_estimate_ns),))

    # -- state -------------------------------------------------------------------------------
    def covers(self, t_ns: int) -> bool:
        """Whether the stored plan covers ``t_ns`` (it starts at or before it)."""
        return self.plan is not None and self.plan.start <= t_ns

    def _reset(self, stamp: int) -> Notice:
        """Time went back (a new run): forget the waiting estimate, the estimate stamps and the
        old run's plan (the trajectory node sends one for the new run)."""
        self.counters['resets'] += 1
        self.pending = None
        if self.last_estimate_ns - self.plan_after_ns > self.reset_jump_ns:
            self.plan = None                   # made for the old run
        self.plan_after_ns = self.last_estimate_ns = -1
        return Notice(Change.RESET, stamp)
