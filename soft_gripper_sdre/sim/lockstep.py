"""When the simulator steps, and with which torque: its stepping rules without ROS.

:class:`Stepping` is the simulator node's loop logic. Sim time is the period index k (t_k = k·Δt,
integer nanoseconds). The node reports each received command (stamp and torques), the wall clock
on a timer, and in realtime mode each period of its wall timer; each call says whether to step the
physics now and with what, or why a command is refused. The node steps the physics, publishes the
new period's tips and then calls :meth:`Stepping.await_command` with the wall time.

* *lockstep*: the physics steps when the command stamped with the current period arrives; after
  ``timeout`` seconds of wall time without it, with the held command (``on_timeout='hold'``) or
  zero, counted (``timeouts``). A command for a period already stepped past is counted
  (``late_command``) and not applied.
* *realtime*: each period of a wall timer steps with the newest command; a period that received
  none is counted (``late_periods``).
* Refused in both modes: a stamp not newer than the last applied command (``stale_command``), a
  stamp ahead of the current period (``future_command``), a wrong-size or non-finite torque
  (``bad_command``). With ``on_bad_command='zero'`` a refused command also drops the held one.

The rules and their reasons: docs/design/loop_rules.md.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

MODES = ('lockstep', 'realtime')
POLICIES = ('hold', 'zero')
#: periods back a command may answer and still count in the loop latency (realtime: late answers)
LATENCY_PERIODS = 64


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """What a received command leads to.

    ``step``: step the physics now with this torque (n, 2). ``refused``: the counter key of a
    refused command, with ``reason``. ``first_answer``: the period index whose tips this command
    is the first answer to, for the loop latency (None: not counted).
    """

    step: np.ndarray | None = None
    refused: str | None = None
    reason: str = ''
    first_answer: int | None = None


class Stepping:
    """The simulator's stepping rules (module doc).

    Args:
        n_fingers: the torque command is (n_fingers, 2).
        period_ns: the control period [ns].
        mode: 'lockstep' or 'realtime'.
        total_steps: stop after this many steps (None: run on).
        timeout: lockstep: wall time [s] to wait for the current period's command.
        on_timeout: lockstep: 'hold' the last good command or apply 'zero' after a timeout.
        on_bad_command: 'hold' keeps, 'zero' drops the held command when a command is refused.
        counters: where to count (the node's diagnostics); a new Counter by default. Keys:
            ``steps``, ``commands`` (accepted), ``late_command``, ``timeouts``, ``late_periods``.
            Refused commands are not counted here: the caller counts them with its other
            rejections (:attr:`CommandOutcome.refused`).

    ``timeout``, ``on_timeout`` and ``on_bad_command`` may be changed between calls.
    """

    def __init__(self, n_fingers: int, period_ns: int, mode: str = 'lockstep',
                 total_steps: int | None = None, timeout: float = 0.5, on_timeout: str = 'hold',
                 on_bad_command: str = 'hold', counters: Counter | None = None) -> None:
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
        self.counters = Counter() if counters is None else counters
        self.k = 0                             # current period; t_k = k · period_ns
        self.started = False
        self.done = False
        self.held = np.zeros((n_fingers, 2))   # the last good command
        self.received: np.ndarray | None = None   # realtime: a command arrived this period
        self.last_command_ns = -1              # stamp of the last applied command
        self.answered_ns = -1                  # newest period whose latency was counted
        self.deadline: float | None = None     # lockstep: wall time the command is awaited until

    @property
    def now_ns(self) -> int:
        """Sim time of the current period [ns]."""
        return self.k * self.period_ns

    def start(self) -> None:
        """The graph is wired: commands are accepted and timeouts run from now on."""
        self.started = True

    def await_command(self, wall: float) -> None:
        """The current period's tips went out at wall time ``wall``: its command is awaited until
        ``wall + timeout``."""
        self.deadline = wall + self.timeout

    # -- inputs ------------------------------------------------------------------------------
    def on_command(self, stamp: int, u: np.ndarray) -> CommandOutcome:
        """A command stamped ``stamp`` with torques ``u`` (an array, (n, 2) unless refused) arrived."""
        if u.shape != (self.n_fingers, 2) or not np.isfinite(u).all():
            return self._refuse('bad_command', f'torque_commands: {u.shape} torques or not '
                                f'finite; expected ({self.n_fingers}, 2) finite values')
        now_ns = self.now_ns
        first = None
        if self.answered_ns < stamp <= now_ns and self.started and stamp % self.period_ns == 0:
            j = stamp // self.period_ns          # answers the tips of period j (realtime: maybe late)
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
        if self.mode == 'realtime':
            self.last_command_ns = stamp
            self.held = self.received = u
            return CommandOutcome(first_answer=first)
        if stamp == now_ns and self.started and not self.done:
            self.last_command_ns = stamp
            self.held = u
            return CommandOutcome(step=self._advance(u), first_answer=first)
        self.counters['late_command'] += 1        # for an earlier period we already stepped past
        return CommandOutcome(first_answer=first)

    def command_refused(self) -> None:
        """A command was refused (here or by the caller's decoder): ``on_bad_command='zero'``
        drops the held command."""
        if self.on_bad_command == 'zero':
            self.held = np.zeros((self.n_fingers, 2))

    def on_wall_time(self, wall: float) -> np.ndarray | None:
        """Lockstep: the torque to step with now if the current period's command is overdue at
        wall time ``wall`` (the held command or zero, by ``on_timeout``), else None."""
        if self.mode != 'lockstep' or self.done or self.deadline is None or wall < self.deadline:
            return None
        self.counters['timeouts'] += 1
        return self._advance(self.held if self.on_timeout == 'hold' else np.zeros((self.n_fingers, 2)))

    def on_period(self) -> np.ndarray | None:
        """Realtime: a period of the wall timer ended; the torque to step with (the newest
        command), or None once done."""
        if self.mode != 'realtime' or self.done:
            return None
        if self.received is None:
            self.counters['late_periods'] += 1
        self.received = None
        return self._advance(self.held)

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
