"""When the controller answers, and with what: the rules between its inputs and its torque commands.

:class:`CommandGate` is the controller node's loop logic without ROS. The node feeds it every
accepted reference horizon, state estimate and sim-time tick, plus the wall time on a timer; each
call returns an :class:`Outcome` saying what to publish (an :class:`Answer`: the law's torque for
an estimate and the horizon that covers it, or the zero safe command), which message to refuse, and
which status changes to report. All times are arguments: sim time as integer nanosecond stamps,
wall time as float seconds, so the rules run the same under a test, a node or a replay.

The rules (docs/design/loop_rules.md):

* an estimate is answered with the newest stored horizon that covers its stamp; if none covers it
  yet, it waits for one, so the answer does not depend on which message arrived first;
* lost estimates: a tick ``estimate_timeout`` of sim time after the last estimate arrived gets the
  safe command stamped with the tick, until estimates come back; estimates for instants already
  answered are skipped;
* time stopped: ``clock_timeout`` of wall time without a tick or an estimate gets one safe command
  for the newest known instant, if it is still unanswered;
* a stamp ``reset_jump_ns`` behind the newest one of its kind (a restarted simulator) resets the
  gate; an older stamp within that distance is refused.
"""
from __future__ import annotations

from collections import Counter
from collections import deque
from dataclasses import dataclass
import enum
from typing import NamedTuple

import numpy as np

#: horizons kept for matching estimates (the trajectory node sends one every few tens of periods)
STORED_HORIZONS = 4


class Horizon(NamedTuple):
    """A reference horizon: points at absolute times ``times`` [ns] from ``start`` to ``end``."""

    start: int
    end: int
    times: np.ndarray            # (h,) strictly increasing [ns]
    pos: np.ndarray              # (h, n, 2) [m]
    vel: np.ndarray              # (h, n, 2) [m/s]
    acc: np.ndarray              # (h, n, 2) [m/s²]


@dataclass(frozen=True, slots=True)
class Answer:
    """A torque command to publish, stamped ``stamp``: the law's torque for ``estimate`` (n, 4)
    tracking ``reference``, or, when ``estimate`` is None, the safe command (zero torque)."""

    stamp: int
    estimate: np.ndarray | None = None
    reference: Horizon | None = None

    @property
    def safe(self) -> bool:
        return self.estimate is None


class Change(enum.Enum):
    """A change the node reports (status, log, and for RESET the law's own reset)."""

    RESET = 'time jumped back: horizons, estimates and the law state are forgotten'
    ESTIMATES_LOST = 'no estimate for estimate_timeout of sim time: safe commands (ERROR)'
    ESTIMATES_BACK = 'an estimate arrived after estimates were lost: tracking again (OK)'
    TIME_STOPPED = 'no tick or estimate for clock_timeout of wall time (ERROR)'
    TIME_MOVES = 'a tick or an estimate after time had stopped (OK, unless estimates are lost)'


class Notice(NamedTuple):
    """``change`` happened; ``t_ns`` is the stamp it concerns: the stamp time jumped back to
    (RESET), the sim time the last estimate arrived at (ESTIMATES_LOST), the returning estimate's
    stamp (ESTIMATES_BACK), the newest known instant (TIME_STOPPED), the stamp heard (TIME_MOVES)."""

    change: Change
    t_ns: int


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one input leads to: notices first (in order), then a refusal or an answer."""

    answer: Answer | None = None
    refused: str | None = None       # counter key of a refused message ('old_estimate', …)
    reason: str = ''                 # why it was refused
    notices: tuple[Notice, ...] = ()


NOTHING = Outcome()


class CommandGate:
    """The controller's covering-reference, lost-estimate and stopped-time rules (module doc).

    Args:
        estimate_timeout_ns: sim time without an arriving estimate before a tick gets the safe
            command (more than one control period).
        reset_jump_ns: how far a stamp may fall behind the newest of its kind before it is taken
            for a restart of time rather than refused as old.
        clock_timeout: wall time [s] without a tick or an estimate before time is taken to have
            stopped.
        counters: where to count (the node's diagnostics); a new Counter by default. Keys:
            ``references``, ``estimates``, ``ticks``, ``late_estimates`` (skipped: their instant
            was already answered), ``unanswered_estimates`` (superseded while waiting for a
            horizon), ``safe_commands``, ``resets``. Refused messages are not counted here: the
            caller counts them with its other rejections (:attr:`Outcome.refused`).

    ``estimate_timeout_ns`` and ``clock_timeout`` may be changed between calls.
    """

    def __init__(self, estimate_timeout_ns: int, reset_jump_ns: int, clock_timeout: float,
                 counters: Counter | None = None) -> None:
        self.estimate_timeout_ns = int(estimate_timeout_ns)
        self.reset_jump_ns = int(reset_jump_ns)
        self.clock_timeout = float(clock_timeout)
        self.counters = Counter() if counters is None else counters
        self.horizons: deque[Horizon] = deque(maxlen=STORED_HORIZONS)   # newest last
        self.pending: tuple[int, np.ndarray] | None = None   # estimate waiting for a horizon
        self.last_estimate_ns = -1
        self.last_reference_ns = -1
        self.last_command_ns = -1           # newest instant answered (tracking or safe)
        self.clock_ns = -1                  # newest tick
        self.estimate_arrived_ns = -1       # sim time at which the last estimate arrived
        self.last_heard: float | None = None   # wall time of the last tick or estimate
        self.estimates_lost = False
        self.time_stopped = False

    # -- inputs ------------------------------------------------------------------------------
    def on_reference(self, stamp: int, times: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                     acc: np.ndarray) -> Outcome:
        """A validated horizon stamped ``stamp`` (``times`` absolute, increasing): stored, and the
        waiting estimate answered if it covers it."""
        notices = []
        if stamp < self.last_reference_ns - self.reset_jump_ns:
            notices.append(self._reset(stamp))
        if stamp < self.last_reference_ns:
            return Outcome(refused='old_reference', notices=tuple(notices), reason=(
                f'grasp_reference: stamp {stamp} ns is older than the last accepted '
                f'{self.last_reference_ns} ns'))
        self.last_reference_ns = stamp
        self.horizons.append(Horizon(int(times[0]), int(times[-1]), times, pos, vel, acc))
        self.counters['references'] += 1
        answer = None
        if self.pending is not None:
            horizon = self.covering(self.pending[0])
            if horizon is not None:
                stamp_est, x = self.pending
                answer = self._track(stamp_est, x, horizon)
        return Outcome(answer, notices=tuple(notices)) if answer or notices else NOTHING

    def on_estimate(self, stamp: int, x: np.ndarray, wall: float) -> Outcome:
        """A validated state estimate (n, 4) stamped ``stamp``, received at wall time ``wall``."""
        notices = []
        if stamp < self.last_estimate_ns - self.reset_jump_ns:
            notices.append(self._reset(stamp))
        if stamp <= self.last_estimate_ns:
            return Outcome(refused='old_estimate', notices=tuple(notices), reason=(
                f'state_estimate: stamp {stamp} ns is not newer than the last accepted '
                f'{self.last_estimate_ns} ns'))
        self.last_estimate_ns = stamp
        self.estimate_arrived_ns = max(stamp, self.clock_ns)
        self._heard(stamp, wall, notices)
        if self.estimates_lost:
            self.estimates_lost = False
            notices.append(Notice(Change.ESTIMATES_BACK, stamp))
        self.counters['estimates'] += 1
        answer = None
        if stamp <= self.last_command_ns:           # this instant already got the safe command
            self.counters['late_estimates'] += 1
            self.pending = None
        else:
            horizon = self.covering(stamp)
            if horizon is None:
                if self.pending is not None:
                    self.counters['unanswered_estimates'] += 1
                self.pending = (stamp, x)
            else:
                answer = self._track(stamp, x, horizon)
        return Outcome(answer, notices=tuple(notices)) if answer or notices else NOTHING

    def on_tick(self, t_ns: int, wall: float) -> Outcome:
        """Sim time reached ``t_ns`` (heard at wall time ``wall``): the safe command stamped
        ``t_ns`` if no estimate arrived for ``estimate_timeout_ns`` and ``t_ns`` is unanswered."""
        notices = []
        if self.clock_ns >= 0 and t_ns < self.clock_ns - self.reset_jump_ns:
            notices.append(self._reset(t_ns))
        self.clock_ns = max(self.clock_ns, t_ns)
        self.counters['ticks'] += 1
        self._heard(t_ns, wall, notices)
        if (self.estimate_arrived_ns < 0 or t_ns - self.estimate_arrived_ns < self.estimate_timeout_ns
                or t_ns <= self.last_command_ns):
            return Outcome(notices=tuple(notices)) if notices else NOTHING
        if not self.estimates_lost:
            self.estimates_lost = True
            notices.append(Notice(Change.ESTIMATES_LOST, self.estimate_arrived_ns))
        return Outcome(self._safe(t_ns), notices=tuple(notices))

    def on_wall_time(self, wall: float) -> Outcome:
        """The wall clock reads ``wall`` [s]: once nothing was heard for ``clock_timeout``, time
        has stopped, and the newest known instant gets the safe command if it is unanswered."""
        newest = self.newest_ns
        if newest < 0 or self.last_heard is None or wall - self.last_heard < self.clock_timeout:
            return NOTHING
        notices = ()
        if not self.time_stopped:
            self.time_stopped = True
            notices = (Notice(Change.TIME_STOPPED, newest),)
        answer = self._safe(newest) if newest > self.last_command_ns else None
        return Outcome(answer, notices=notices) if answer or notices else NOTHING

    # -- state -------------------------------------------------------------------------------
    @property
    def newest_ns(self) -> int:
        """The newest instant known from a tick or an estimate (-1: none yet)."""
        return max(self.clock_ns, self.last_estimate_ns)

    def covering(self, t_ns: int) -> Horizon | None:
        """The newest stored horizon whose span holds ``t_ns``, or None."""
        for horizon in reversed(self.horizons):
            if horizon.start <= t_ns <= horizon.end:
                return horizon
        return None

    def _track(self, stamp: int, x: np.ndarray, horizon: Horizon) -> Answer:
        self.pending = None
        self.last_command_ns = stamp
        return Answer(stamp, x, horizon)

    def _safe(self, stamp: int) -> Answer:
        """The safe command for ``stamp``; the waiting estimate, if any, is superseded."""
        self.pending = None
        self.last_command_ns = stamp
        self.counters['safe_commands'] += 1
        return Answer(stamp)

    def _heard(self, t_ns: int, wall: float, notices: list) -> None:
        self.last_heard = wall
        if self.time_stopped:
            self.time_stopped = False
            if not self.estimates_lost:
                notices.append(Notice(Change.TIME_MOVES, t_ns))

    def _reset(self, stamp: int) -> Notice:
        """Time went back: forget horizons, the waiting estimate and every stamp."""
        self.counters['resets'] += 1
        self.horizons.clear()
        self.pending = None
        self.last_estimate_ns = self.last_reference_ns = self.last_command_ns = -1
        self.clock_ns = self.estimate_arrived_ns = -1
        return Notice(Change.RESET, stamp)
