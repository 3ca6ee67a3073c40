"""The deployment benchmark's driver stand-in: the light process that takes a robot driver's place.

:func:`driver` publishes ``tip_positions`` on an absolute wall-clock schedule (:class:`Schedule`)
from CDR bytes built before the run, so a period costs no message object and no serialization,
and takes ``torque_commands`` as raw bytes, reading only each command's stamp
(:class:`CommandLog`). At every tick it notes whether the newest command answers tips older than
the tick before (late, the simulator's realtime rule); over the measured window it reports
lateness, the latency from tips out to the command with the same stamp back, and the CPU of every
process of the loop (:class:`Ticks`). It runs in its own process, started by
:func:`soft_gripper_sdre.tools.benchmarks.bench_deploy.run_deploy` as ``bench_deploy --driver``.
"""
from __future__ import annotations

from contextlib import contextmanager
import ctypes
from dataclasses import dataclass
import os
from pathlib import Path
import threading
import time
from typing import Iterator

import numpy as np

#: the driver's wait for the command of its last tick, after its last tick [s]
DRAIN_S = 0.2


def _schedstat_ns(pid: int) -> int:
    """Nanoseconds ``pid`` (all its threads) has run on a CPU (``/proc/<pid>/schedstat``)."""
    try:
        return int(Path(f'/proc/{pid}/schedstat').read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return -1


def _timer_slack(ns: int) -> None:
    """This thread's timer slack (Linux prctl PR_SET_TIMERSLACK), so sleeps end on time."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(29, ctypes.c_ulong(ns), 0, 0, 0)
    except (OSError, AttributeError):
        pass


@dataclass(frozen=True)
class Schedule:
    """The driver's ticks: one every ``period`` [s], ``total`` in all, measured from tick
    ``first`` on (the warm-up before it); tick k publishes the recorded tips of ``k · stride`` ms,
    stamped k · period from 0, as the simulator stamps them."""

    period: float
    total: int
    first: int
    stride: int

    @classmethod
    def of(cls, period: float, warmup: float, seconds: float) -> Schedule:
        return cls(period, total=int(round((warmup + seconds) / period)),
                   first=int(round(warmup / period)), stride=int(round(period / 1e-3)))

    @property
    def period_ns(self) -> int:
        return int(round(self.period * 1e9))


class CommandLog:
    """The torque commands heard, as raw bytes: when the command stamped k arrived
    (``received[k]``, perf_counter; 0 while it has not), and the newest period answered."""

    def __init__(self, schedule: Schedule) -> None:
        from soft_gripper_sdre.nodes.cdr import leading_stamp
        self._stamp = leading_stamp
        self._period_ns, self._total = schedule.period_ns, schedule.total
        self.received = np.zeros(schedule.total)
        self.newest = -1

    def on_command(self, data: bytes) -> None:
        now = time.perf_counter()
        stamp = self._stamp(data)
        if stamp is None:
            return
        k = stamp // self._period_ns
        if 0 <= k < self._total and not self.received[k]:
            self.received[k] = now
            if k > self.newest:
                self.newest = k


@dataclass
class Ticks:
    """What the ticking recorded: per tick the perf_counter at its publish (``sent``; 0: skipped),
    whether its newest command was late, how late it woke [s]; the ticks skipped; the first
    measured tick (past the warm-up, where a late wake-up may have skipped to); the CPU [ns] of
    every watched process at that tick and at the end; the period [s].

    Two shares of late periods come out of them (:meth:`figures`): ``late``, the realtime rule at
    the driver's tick (the newest command answers tips older than the tick before), which also
    counts what the stand-in did to itself (a tick it skipped, tips it sent late because it woke
    late, a command its own receive thread took late); and ``slow``, the loop's own share: ticks
    whose command came back more than a period after their tips went out, or never."""

    sent: np.ndarray
    late: np.ndarray
    wake: np.ndarray
    skipped: int
    first: int
    cpu0: dict[str, int]
    cpu1: dict[str, int]
    period: float

    def figures(self, received: np.ndarray, matched: tuple[int, int]) -> dict:
        """The driver's figures over the measured window (see :func:`driver`), given when each
        period's command arrived."""
        total = len(self.sent)
        window = np.arange(self.first, total)
        ticked = window[self.sent[window] > 0]
        answered = ticked[received[ticked] > 0]
        latency = 1e6 * (received[answered] - self.sent[answered])
        periods = total - self.first
        cpu = {name: (self.cpu1[name] - self.cpu0.get(name, self.cpu1[name])) / 1e3 / periods
               for name in self.cpu1}
        late = self.late[ticked]
        slow = slow_ticks(self.sent, received, ticked, self.period)
        return {
            'periods': periods, 'ticks': int(len(ticked)), 'skipped': self.skipped,
            'late': int(late.sum()), 'unanswered': int(len(ticked) - len(answered)),
            'late_pct': 100.0 * float(late.sum()) / max(len(ticked), 1),
            'slow': int(slow.sum()), 'slow_pct': 100.0 * float(slow.sum()) / max(len(ticked), 1),
            'latency_p50': float(np.percentile(latency, 50)) if len(latency) else float('nan'),
            'latency_p99': float(np.percentile(latency, 99)) if len(latency) else float('nan'),
            'latency_max': float(latency.max()) if len(latency) else float('nan'),
            'wake_p99': 1e6 * float(np.percentile(self.wake[ticked], 99)),
            'cpu_us': cpu, 'matched': matched,
        }


def slow_ticks(sent: np.ndarray, received: np.ndarray, ticked: np.ndarray,
               period: float) -> np.ndarray:
    """Of the ``ticked`` ticks, those whose command came back more than ``period`` after their
    tips were sent, or never."""
    back = received[ticked]
    return (back <= 0) | (back - sent[ticked] > period)


def _tick(pub, messages: list, schedule: Schedule, commands: CommandLog,
          watched: dict[str, int]) -> Ticks:
    """Publish ``messages[k]`` at tick k of ``schedule``, each on its absolute due time; a wake-up
    more than a period late skips the ticks it missed, as a timer does. The CPU of the
    ``watched`` processes (name → pid) is read at the first measured tick and at the end."""
    total, period, first = schedule.total, schedule.period, schedule.first
    sent, wake = np.zeros(total), np.zeros(total)
    late = np.zeros(total, dtype=bool)
    cpu0: dict[str, int] = {}
    skipped = 0
    perf = time.perf_counter
    t0 = perf() + 0.01
    k = 0
    while k < total:
        due = t0 + k * period
        now = perf()
        if now < due:
            time.sleep(due - now)
            now = perf()
        behind = int((now - t0) / period) - k
        if behind > 0:                  # woke more than a period late: skip, as a timer does
            skipped += behind
            k += behind
            if k >= total:
                break
            due = t0 + k * period
        if k >= first and not cpu0:
            cpu0 = {name: _schedstat_ns(pid) for name, pid in watched.items()}
            first = k
        wake[k] = now - due
        late[k] = commands.newest < k - 1
        sent[k] = perf()
        pub.publish(messages[k])
        k += 1
    cpu1 = {name: _schedstat_ns(pid) for name, pid in watched.items()}
    return Ticks(sent, late, wake, skipped, first, cpu0, cpu1, period)


def _wait_matched(pub, sub, readers: int, timeout: float = 60.0) -> tuple[int, int]:
    """Until ``readers`` subscribers have matched ``pub`` and a publisher ``sub`` (or
    ``timeout``); returns those counts."""
    deadline = time.monotonic() + timeout
    while (pub.get_subscription_count() < readers or sub.get_publisher_count() < 1) \
            and time.monotonic() < deadline:
        time.sleep(0.01)
    matched = pub.get_subscription_count(), sub.get_publisher_count()
    time.sleep(0.2)                     # both sides of every match settled
    return matched


@contextmanager
def _spinning(executor) -> Iterator[None]:
    """``executor`` spinning in a thread of its own while the block runs, so the commands are
    taken while the main thread ticks."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)
    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        yield
    finally:
        stop.set()
        spinner.join()


def driver(period: float, warmup: float, seconds: float, tips_path: Path, readers: int,
           pids: dict[str, int]) -> dict:
    """The driver stand-in (run in its own process): publish the tips of ``tips_path`` every
    ``period`` on an absolute schedule, time the commands, return the figures.

    Waits until ``readers`` subscribers have matched ``tip_positions`` and a publisher has matched
    ``torque_commands``, ticks for ``warmup`` + ``seconds``, and measures the last ``seconds``:
    lateness, latency, and the CPU of every process in ``pids`` (name → pid) and its own.
    """
    from geometry_msgs.msg import PoseArray
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from soft_gripper_sdre.nodes import cdr
    from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS, TORQUE_COMMANDS

    tips = np.load(tips_path)
    schedule = Schedule.of(period, warmup, seconds)
    if (schedule.total - 1) * schedule.stride >= len(tips):
        raise ValueError(f'{tips_path} holds {len(tips)} ms of tips, '
                         f'{schedule.total * schedule.stride} needed')
    codec = cdr.tips_codec(tips.shape[1])
    messages = [codec.encode(k * schedule.period_ns, tips[k * schedule.stride])
                for k in range(schedule.total)]
    commands = CommandLog(schedule)
    _timer_slack(1000)

    rclpy.init()
    node = Node('deploy_driver')
    pub = node.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    sub = node.create_subscription(JointState, TORQUE_COMMANDS, commands.on_command, LOOP_QOS,
                                   raw=True)
    executor = EventsExecutor()
    executor.add_node(node)
    with _spinning(executor):
        matched = _wait_matched(pub, sub, readers)
        ticks = _tick(pub, messages, schedule, commands, {**pids, 'driver': os.getpid()})
        time.sleep(DRAIN_S)
    probe = os.environ.get('SGS_PROBE')
    if probe:                           # loop_probe.late_causes joins these with the nodes' records
        np.savez(Path(probe) / 'ticks.npz', sent=ticks.sent, late=ticks.late, wake=ticks.wake,
                 received=commands.received, first=ticks.first, period=period)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return ticks.figures(commands.received, matched)
