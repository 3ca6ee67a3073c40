"""When the simulator steps, and with which torque: its stepping rules without ROS.

:class:`Stepping` is the simulator node's loop logic. Sim time is the period index k (t_k = k·Δt,
integer nanoseconds). The node reports each received command (stamp and torques), the wall clock
on a timer, and in realtime mode each period of its wall timer; each call says whether to step the
physics now and with what, or why a command is refused. The node steps the physics, publishes the
new period's tips and calls :meth:`Stepping.await_command` with the wall time (pipelined: it
publishes the new period's tips first and steps the physics after them).

* *lockstep*: the physics steps when the command stamped with the current period arrives; after
  ``timeout`` seconds of wall time without it, with the held command (``on_timeout='hold'``) or
  zero, counted (``timeouts``). A period is given up at the second look of the node's watchdog
  past its deadline, never at the first: a simulator starved of CPU wakes with its watchdog
  timer and the command both due, and may run the watchdog first. If the loop had answered
  before, commands are then *lost*: each following period waits only ``lost_command_wait`` and
  steps with zero torque (``safe_periods``), until any command is accepted again. A command for
  a period already stepped past is counted (``late_command``) and not applied.
* *pipelined*: lockstep's rules, all of them; the node steps the physics one period later. It
  publishes the tips of t_k when the command for t_(k−1) has arrived (or the watchdog gave up on
  it) and then steps the physics from t_k to t_(k+1) with that command, while the estimator and
  controller answer t_k: one period of sensing-to-actuation delay. The first step, t_0 → t_1,
  goes at the start with zero torque (:meth:`Stepping.start` returns it).
* *realtime*: each period of a wall timer steps with the newest command. The command for the
  current period's tips, or for the previous period's (one period of transport delay), is on
  time; an older one makes the period late (``late_periods``) and is held while it is at most
  ``hold_periods`` periods old; after that zero torque is applied (``safe_periods``).
* Refused in every mode: a stamp not newer than the last applied command (``stale_command``), a
  stamp ahead of the current period (``future_command``), a wrong-size or non-finite torque
  (``bad_command``). With ``on_bad_command='zero'`` a refused command also drops the held one.

The rules and their reasons: docs/design/loop_rules.md.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

MODES = ('lockstep', 'pipelined', 'realtime')
POLICIES = ('hold', 'zero')
#: periods back a command may answer and still count in the loop latency (realtime: late answers)
LATENCY_PERIODS = 64


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """What a received command leads to.

    ``step``: step the physics now with this torque (n, 2). ``refused``: the counter key of a
    refused command, with ``reason``. ``first_answer``: the period index whose tips this command
    is the first answer to, for the loop latency (None: not counted). ``resumed``: the command
    ended a spell of lost commands (zero torque), and the node reports that commands are back.
    """

    step: np.ndarray | None = None
    refused: str | None = None
    reason: str = ''
    first_answer: int | None = None
    resumed: bool = False


class Stepping:
    """The simulator's stepping rules (module doc).

    Args:
        n_fingers: the torque command is (n_fingers, 2).
        period_ns: the control period [ns].
        mode: 'lockstep', 'pipelined' (lockstep's rules; the node steps the physics one period
            later) or 'realtime'.
        total_steps: stop after this many periods (None: run on).
        timeout: lockstep and pipelined: wall time [s] to wait for the current period's command.
        on_timeout: lockstep, pipelined: 'hold' the last good command or apply 'zero' after a
            timeout.
        on_bad_command: 'hold' keeps, 'zero' drops the held command when a command is refused.
        lost_command_wait: lockstep, pipelined: wall time [s] each period waits for its command once
            commands are lost (after a timeout), before it steps with zero torque.
        hold_periods: realtime: how many periods old the held command may be; an older one is
            replaced by zero torque.
        counters: where to count (the node's diagnostics); a new Counter by default. Keys:
            ``steps``, ``commands`` (accepted), ``late_command``, ``timeouts``, ``late_periods``,
            ``safe_periods``. Refused commands are not counted here: the caller counts them with
            its other rejections (:attr:`CommandOutcome.refused`).

    ``timeout``, ``on_timeout``, ``on_bad_command``, ``lost_command_wait`` and ``hold_periods``
    may be changed between calls.
    """

    def __init__(self, n_fingers: int, period_ns: int, mode: str = 'lockstep',
                 total_steps: int | None = None, timeout: float = 0.5, on_timeout: str = 'hold',
                 on_bad_command: str = 'hold', lost_command_wait: float = 0.01,
                 hold_periods: int = 5, counters: Counter | None = None) -> None:
        if mode not in MODES or on_timeout not in POLICIES or on_bad_command not in POLICIES:
            raise ValueError(f'mode {mode!r} must be one of {MODES}, on_timeout {on_timeout!r} and '
                             f'on_bad_command {on_bad_command!r} one of {POLICIES}')
        self.n_fingers = n_fingers
        self.period_ns = int(period_ns)
        self.mode = mode
        self.total_steps = total_steps
        self.timeout = timeout
        self.on_timeout = on_timeout
        self.on_bad_command = on_bad_command
        self.lost_command_wait = lost_command_wait
        self.hold_periods = hold_periods
        self.counters = Counter() if counters is None else counters
        self.k = 0                             # current period; t_k = k · period_ns
        self.started = False
        self.done = False
        self.held = np.zeros((n_fingers, 2))   # the last good command
        self.last_command_ns = -1              # stamp of the last applied command
        self.answered_ns = -1                  # newest period whose latency was counted
        self.sent_at: float | None = None      # wall time the current tips went out (not realtime)
        self.lost = False                      # commands lost: stepping with zero torque
        self.lost_since_ns = -1                # the first period stepped without its command
        self._looked_overdue = None            # (period, deadline) a look already found past

    @property
    def now_ns(self) -> int:
        """Sim time of the current period [ns]."""
        return self.k * self.period_ns

    @property
    def deadline(self) -> float | None:
        """Lockstep, pipelined: the wall time until which the current period's command is
        awaited."""
        if self.sent_at is None:
            return None
        return self.sent_at + (self.lost_command_wait if self.lost else self.timeout)

    @property
    def pipelined(self) -> bool:
        """The node publishes the tips of t_k and then steps the physics from t_k to t_(k+1) with
        the command that answered t_(k−1): the physics runs one period behind the commands."""
        return self.mode == 'pipelined'

    def start(self) -> np.ndarray | None:
        """The graph is wired: commands are accepted and timeouts run from now on.

        Returns the torque of the physics step the node takes right after publishing the first
        tips, before any command: zero in pipelined mode (the step t_0 → t_1, whose command would
        answer t_(−1)), None (no such step) otherwise."""
        self.started = True
        return np.zeros((self.n_fingers, 2)) if self.pipelined else None

    def await_command(self, wall: float) -> None:
        """The current period's tips went out at wall time ``wall``: its command is awaited until
        :attr:`deadline`."""
        self.sent_at = wall

    # -- inputs ------------------------------------------------------------------------------
    def on_command(self, stamp: int, u: np.ndarray) -> CommandOutcome:
        """A command stamped ``stamp`` with torques ``u`` (an array, (n, 2) unless refused)
        arrived."""
        if u.shape != (self.n_fingers, 2) or not np.isfinite(u).all():
            return self._refuse('bad_command', f'torque_commands: {u.shape} torques or not '
                                f'finite; expected ({self.n_fingers}, 2) finite values')
        now_ns = self.now_ns
        first = None
        if self.answered_ns < stamp <= now_ns and self.started and stamp % self.period_ns == 0:
            j = stamp // self.period_ns  # answers the tips of period j (realtime: maybe late)
            if self.k - j < LATENCY_PERIODS:
                first = j
                self.answered_ns = stamp
        if stamp <= self.last_command_ns:
            return self._refuse('stale_command', f'torque_commands: stamp {stamp} ns is not newer '
                                f'than the last applied {self.last_command_ns} ns', first)
        if stamp > now_ns:
            return self._refuse('future_command', f'torque_commands: stamp {stamp} ns is ahead of '
                                f'sim time {now_ns} ns', first)
        self.counters['commands'] += 1
        resumed, self.lost = self.lost, False      # any accepted command: the loop answers again
        if self.mode == 'realtime':
            self.last_command_ns = stamp
            self.held = u
            return CommandOutcome(first_answer=first, resumed=resumed)
        if stamp == now_ns and self.started and not self.done:
            self.last_command_ns = stamp
            self.held = u
            return CommandOutcome(step=self._advance(u), first_answer=first, resumed=resumed)
        self.counters['late_command'] += 1        # for an earlier period we already stepped past
        return CommandOutcome(first_answer=first, resumed=resumed)

    def command_refused(self) -> None:
        """A command was refused (here or by the caller's decoder): ``on_bad_command='zero'``
        drops the held command."""
        if self.on_bad_command == 'zero':
            self.held = np.zeros((self.n_fingers, 2))

    def on_wall_time(self, wall: float) -> np.ndarray | None:
        """Lockstep and pipelined: the torque to step with now if the current period's command
        is overdue at wall time ``wall``, else None. The first overdue period is a timeout (the held
        command or zero, by ``on_timeout``); if a command was ever accepted, commands are lost from
        then on and every later overdue period gets zero after ``lost_command_wait``.

        Each call is one look: a period is overdue at the second look past its deadline, so a
        command that was already waiting at the first look is taken in between."""
        deadline = self.deadline
        if self.mode == 'realtime' or self.done or deadline is None or wall < deadline:
            return None
        if self._looked_overdue != (self.k, deadline):  # (a moved deadline gets its own two looks)
            self._looked_overdue = (self.k, deadline)
            return None
        if self.lost:
            self.counters['safe_periods'] += 1
            return self._advance(np.zeros((self.n_fingers, 2)))
        self.counters['timeouts'] += 1
        if self.last_command_ns >= 0:          # (before the loop has ever answered, keep waiting)
            self.lost, self.lost_since_ns = True, self.now_ns
        return self._advance(self.held if self.on_timeout == 'hold'
                             else np.zeros((self.n_fingers, 2)))

    def on_period(self) -> np.ndarray | None:
        """Realtime: a period of the wall timer ended; the torque to step with (the newest
        command, or zero once it is more than ``hold_periods`` old), or None once done."""
        if self.mode != 'realtime' or self.done:
            return None
        now_ns = self.now_ns
        # this period's or the previous one's
        if self.last_command_ns >= max(0, now_ns - self.period_ns):
            return self._advance(self.held)
        self.counters['late_periods'] += 1
        if (self.last_command_ns < 0
                or now_ns - self.last_command_ns <= self.hold_periods * self.period_ns):
            return self._advance(self.held)     # nothing yet (zero) or recent enough to hold
        if not self.lost:
            self.lost, self.lost_since_ns = True, self.last_command_ns + self.period_ns
        self.counters['safe_periods'] += 1
        return self._advance(np.zeros((self.n_fingers, 2)))

    # -- helpers -----------------------------------------------------------------------------
    def _advance(self, u: np.ndarray) -> np.ndarray:
        """Count the step with ``u`` and move to the next period; ``u`` is returned."""
        self.k += 1
        self.counters['steps'] += 1
        if self.total_steps is not None and self.k >= self.total_steps:
            self.done = True
        return u

    def _refuse(self, key: str, reason: str, first_answer: int | None = None) -> CommandOutcome:
        self.command_refused()
        return CommandOutcome(refused=key, reason=reason, first_answer=first_answer)
