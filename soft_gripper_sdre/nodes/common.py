"""What every node shares: process lifetime (executor, signals, a flush before exit), throttled
warnings, counters in /diagnostics, a latency window and a stepping loop's timing for them."""
from __future__ import annotations

from collections import Counter
import os
import signal
import sys
import time
from typing import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from soft_gripper_sdre.nodes import scheduling
from soft_gripper_sdre.nodes.cli import USAGE_ERROR, settle_command_line
from soft_gripper_sdre.nodes.graph import wiring_key
from soft_gripper_sdre.nodes.params import Param, ParameterError
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR

#: environment variable choosing the executor of :func:`run` ('events', the default, or 'single')
EXECUTOR_ENV = 'SOFT_GRIPPER_EXECUTOR'
EXECUTORS = {'events': EventsExecutor, 'single': SingleThreadedExecutor}


class ThrottledLogger:
    """Warn at most once per ``period`` seconds per key, saying how many were suppressed."""

    def __init__(self, logger, period: float = 2.0) -> None:
        self._logger = logger
        self._period = period
        self._last: dict[str, float] = {}
        self._suppressed: Counter = Counter()

    def warn(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self._period:
            extra = f' ({self._suppressed[key]} more suppressed)' if self._suppressed[key] else ''
            self._logger.warning(message + extra)
            self._last[key] = now
            self._suppressed[key] = 0
        else:
            self._suppressed[key] += 1


class Diagnostics:
    """Counters and a status level published as one DiagnosticStatus on /diagnostics, on a wall
    timer (~1 Hz) and stamped with wall time; the loop topics are the ones stamped in sim time."""

    def __init__(self, node: Node, hardware_id: str = 'soft_gripper', period: float = 1.0) -> None:
        self.node = node
        self.counters: Counter = Counter()
        #: the process's scheduling (nodes/scheduling.py): whether the loop runs at real-time
        #: priority is the first thing to know about late periods
        self.values: dict[str, str] = {'scheduling': scheduling.describe()}
        latency = scheduling.process_cpu_latency()
        if latency is not None:                 # at real-time priority: the wake-up latency held
            self.values['cpu_latency'] = latency
        self.level = OK
        self.message = 'ok'
        self._hardware_id = hardware_id
        #: called before each publication, to refresh values that are costly to keep current
        self.before_publish: list[Callable[[], None]] = []
        self._clean = 0                         # good events since the last problem
        self._log = ThrottledLogger(node.get_logger())
        self._pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
        self._timer = node.create_timer(period, self.publish)

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] += n

    def problem(self, key: str, why: str) -> None:
        """Count ``key``, go to WARN with ``why`` (an ERROR stays) and warn (throttled per key)."""
        self.count(key)
        if self.level != ERROR:
            self.set_status(WARN, why)
        self._clean = 0
        self._log.warn(key, why)

    def good(self, key: str, message: str, clear_after: int = 1000) -> None:
        """Count ``key``; after ``clear_after`` good events in a row a WARN returns to OK (an
        ERROR is cleared only by the node that raised it)."""
        self.count(key)
        self._clean += 1
        if self._clean == clear_after and self.level == WARN:
            self.set_status(OK, message)

    def subscription_count(self) -> int:
        """Subscribers matched on /diagnostics."""
        return self._pub.get_subscription_count()

    def set_status(self, level: int, message: str) -> None:
        self.level, self.message = level, message

    def publish(self) -> None:
        for refresh in self.before_publish:
            refresh()
        status = DiagnosticStatus(level=self.level, name=self.node.get_fully_qualified_name(),
                                  message=self.message, hardware_id=self._hardware_id)
        status.values = ([KeyValue(key=k, value=str(v)) for k, v in sorted(self.counters.items())]
                         + [KeyValue(key=k, value=v) for k, v in sorted(self.values.items())]
                         + [KeyValue(key=k, value=v) for k, v in wiring(self.node).items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)


def wiring(node: Node) -> dict[str, str]:
    """The matched counts of ``node``'s topics, as /diagnostics carries them for the start rule
    (:func:`soft_gripper_sdre.nodes.graph.readiness_problem`): per publisher the readers it has
    matched, per subscription the writers (ROS's own /diagnostics and /parameter_events aside),
    plus the links the node has inside its process (``node.in_process_wiring``, the same keys: the
    estimator handing its estimates to a controller beside it)."""
    skip = {DIAGNOSTICS, '/parameter_events', '/rosout'}
    out = {wiring_key('readers', pub.topic_name): str(pub.get_subscription_count())
           for pub in node.publishers if pub.topic_name not in skip}
    out.update({wiring_key('writers', sub.topic_name): str(sub.get_publisher_count())
                for sub in node.subscriptions if sub.topic_name not in skip})
    for key, count in getattr(node, 'in_process_wiring', {}).items():
        out[key] = str(int(out.get(key, 0)) + count)
    return dict(sorted(out.items()))


class LatencyWindow:
    """The last ``size`` latencies in a ring buffer (no allocation per sample), summarised as
    p50 / p99 / max in µs for /diagnostics."""

    def __init__(self, size: int = 10_000) -> None:
        self._buf = np.empty(size)
        self._size = size
        self.count = 0                          # samples ever added

    def add(self, seconds: float) -> None:
        self._buf[self.count % self._size] = seconds
        self.count += 1

    def summary(self, prefix: str, last: int | None = None) -> dict[str, str]:
        """``{prefix}_p50``, ``_p99``, ``_max`` [µs] over the window, or over its newest ``last``
        samples ({} without a sample)."""
        held = min(self.count, self._size)
        if last is not None:
            held = min(held, last)
        if not held:
            return {}
        us = 1e6 * self._buf[(self.count - held + np.arange(held)) % self._size]
        p50, p99 = np.percentile(us, (50, 99))
        return {f'{prefix}_p50': f'{p50:.0f}', f'{prefix}_p99': f'{p99:.0f}',
                f'{prefix}_max': f'{us.max():.0f}'}


class SteppingTiming:
    """How fast a stepping loop runs, for /diagnostics: its real-time factor, this process's CPU
    time per step and the loop latency (tips for period k sent → the first command stamped k
    received), over the whole run (``loop_latency_us_*``) and since the previous report
    (``recent_latency_us_*``); when the first command was accepted
    (``first_command_monotonic_s`` on the wall clock, ``first_command_after_tips_ms`` from the
    first tips); and the mean wall time of a step from that command on (``step_period_us``: the
    loop's own pace, without the wait for the graph's first answer that the real-time factor
    counts). The clocks are arguments so the arithmetic can be checked."""

    def __init__(self, periods: int, wall=time.monotonic, cpu=time.process_time,
                 perf=time.perf_counter) -> None:
        self._wall, self._cpu, self._perf = wall, cpu, perf
        self.latency = LatencyWindow()
        self._reported = 0                      # latency samples in the previous report
        self._sent = np.zeros(periods)          # perf clock when the tips of period k went out, at
                                                # k % periods
        self.wall_start: float | None = None    # wall clock at the first step
        self._wall_end = self._cpu_start = self._cpu_end = None
        self._first_command: float | None = None    # wall clock at the first accepted command
        self._first_step = 0                        # the steps taken by then

    def start(self) -> None:
        self.wall_start, self._cpu_start = self._wall(), self._cpu()

    def finish(self) -> None:
        self._wall_end, self._cpu_end = self._wall(), self._cpu()

    def tips_sent(self, k: int) -> None:
        self._sent[k % len(self._sent)] = self._perf()

    def answered(self, k: int) -> None:
        """The first command for the tips of period ``k`` arrived."""
        self.latency.add(self._perf() - self._sent[k % len(self._sent)])

    def accepted(self, steps: int) -> None:
        """A command was accepted, ``steps`` steps into the run (its own included); the first
        one after the start is reported."""
        if self.wall_start is not None and self._first_command is None:
            self._first_command, self._first_step = self._wall(), steps

    def report(self, sim_time: float, steps: int) -> dict[str, str]:
        """The values for /diagnostics after ``steps`` steps, ``sim_time`` [s] of sim time."""
        out = {}
        if self.wall_start is not None:
            wall = (self._wall_end or self._wall()) - self.wall_start
            if wall > 0:
                out['real_time_factor'] = f'{sim_time / wall:.4f}'
            if steps:
                cpu = (self._cpu_end or self._cpu()) - self._cpu_start
                out['cpu_per_step_us'] = f'{1e6 * cpu / steps:.0f}'
        if self._first_command is not None:
            out['first_command_monotonic_s'] = f'{self._first_command:.6f}'
            out['first_command_after_tips_ms'] = (
                f'{1e3 * (self._first_command - self.wall_start):.1f}')
            if steps > self._first_step:
                since = (self._wall_end or self._wall()) - self._first_command
                out['step_period_us'] = f'{1e6 * since / (steps - self._first_step):.0f}'
        out.update(self.latency.summary('loop_latency_us'))
        out.update(self.latency.summary('recent_latency_us',
                                        last=self.latency.count - self._reported))
        self._reported = self.latency.count
        return out


def make_executor(kind: str | None = None, context=None) -> Executor:
    """The executor every node process spins: ``kind`` or $SOFT_GRIPPER_EXECUTOR, default 'events'.

    rclpy's EventsExecutor dispatches each message from C++ with no wait-set rebuild per callback,
    so it spends less CPU per received message than the SingleThreadedExecutor (BENCHMARKS.md,
    "one DDS hop"). Our nodes need nothing it lacks: one thread, subscriptions (also ``raw=True``),
    wall timers created and cancelled from callbacks, ``spin_once`` with a timeout.

    Raises:
        ValueError: an unknown executor name.
    """
    kind = kind or os.environ.get(EXECUTOR_ENV, 'events')
    if kind not in EXECUTORS:
        raise ValueError(f'{EXECUTOR_ENV}={kind!r}: expected one of {", ".join(EXECUTORS)}')
    return EXECUTORS[kind](context=context)


def flush(node: Node, timeout: float = 2.0) -> bool:
    """Wait (at most ``timeout`` s in all) until every reliable subscriber has acknowledged what
    ``node`` published, so a process that exits right after its last messages does not take them
    with it: a reader that fell behind would otherwise lose the tail and the final diagnostics.

    The diagnostics go first: they carry the counts a recorder or a test checks the others against,
    so a slow reader of a loop topic must not use up the time they get."""
    deadline = time.monotonic() + timeout
    acked = True
    for pub in sorted(node.publishers,
                      key=lambda pub: pub.topic_name != '/' + DIAGNOSTICS.lstrip('/')):
        left = max(0.0, deadline - time.monotonic())
        acked &= pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
    return acked


def run(node_factory: Callable[..., Node | tuple[Node, ...]], args: list[str] | None = None,
        params: Sequence[Param] | None = None) -> int:
    """``main()`` of every node: init → construct → spin until shutdown or ``node.done`` → clean up.

    ``node_factory`` builds one node, or several that share the process and its one executor (the
    first ``done`` ends them all; the exit status is the largest of theirs).
    ``args`` is the whole command line (program name first; default ``sys.argv``). ``--help`` and
    bad parameter files are settled first (:mod:`soft_gripper_sdre.nodes.cli`), from ``params``
    (default: the node module's ``PARAMS``). SIGTERM is handled like SIGINT. A
    :class:`ParameterError` at construction is logged and the process exits with status 2; other
    construction errors exit 1.
    """
    argv = list(sys.argv if args is None else args)
    executable, status = _settle_command_line(node_factory, argv, params)
    if status is not None:
        return status
    try:
        scheduling.cpu_latency_request()          # a bad value is refused at any priority
        latency = scheduling.process_cpu_latency()
    except ValueError as exc:
        sys.stderr.write(f'{executable}: cannot start: {exc}\n')
        return USAGE_ERROR
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as exc:               # rcl refused the ROS arguments (an RCLError)
        sys.stderr.write(f'{executable}: cannot start with these arguments: '
                         f'{str(exc).splitlines()[0]}\n')
        return USAGE_ERROR
    if latency is not None and latency.startswith('not held:'):
        rclpy.logging.get_logger('soft_gripper_sdre').warning(
            f'real-time priority, but the CPU wake-up latency is {latency}; each hop of the '
            'loop costs more (docs/performance.md, "Waking up")')
    stop = _stop_on_signals()
    nodes: tuple[Node, ...] = ()
    executor = None
    code = 0
    try:
        try:
            made = node_factory()
        except ParameterError as exc:
            rclpy.logging.get_logger('soft_gripper_sdre').fatal(f'bad parameter: {exc}')
            return 2
        except (OSError, ValueError) as exc:
            rclpy.logging.get_logger('soft_gripper_sdre').fatal(f'cannot start: {exc}')
            return 1
        nodes = made if isinstance(made, tuple) else (made,)
        executor = make_executor()
        for node in nodes:
            executor.add_node(node)
        while rclpy.ok() and not stop and not any(getattr(node, 'done', False) for node in nodes):
            executor.spin_once(timeout_sec=0.1)
        code = max(int(getattr(node, 'exit_code', 0)) for node in nodes)
    except ExternalShutdownException:       # the context was shut down from elsewhere
        pass
    finally:
        _shut_down(nodes, executor)
    return code


def _settle_command_line(node_factory: Callable, argv: list[str],
                         params: Sequence[Param] | None) -> tuple[str, int | None]:
    """The executable's name, and the exit status if the command line is settled already
    (``--help``, a bad parameter file: :func:`~soft_gripper_sdre.nodes.cli.settle_command_line`
    with the node module's first docstring line and ``params`` or its ``PARAMS``), else None."""
    module = sys.modules.get(node_factory.__module__)
    summary = ((getattr(module, '__doc__', None) or '').strip().splitlines() or [''])[0]
    spec = getattr(module, '__spec__', None)      # the module's own name also under python -m
    executable = (spec.name if spec is not None else node_factory.__module__).rsplit('.', 1)[-1]
    if params is None:
        params = getattr(module, 'PARAMS', ())
    return executable, settle_command_line(argv[1:], executable, summary, params)


def _stop_on_signals() -> list[int]:
    """Handle SIGINT and SIGTERM by appending the signal to the returned list.

    Our own SIGINT handling keeps the context alive while the node closes, so it can still
    publish its final diagnostics and, for the recorder, finish the bag. The handler only sets a
    flag: an exception raised inside a callback would be logged by the EventsExecutor as a
    failing callback; instead the loop sees the flag within one spin_once timeout. So no
    KeyboardInterrupt is raised once the handlers are installed (before anything can fail)."""
    stop: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stop.append(signum))
    return stop


def _shut_down(nodes: tuple[Node, ...], executor: Executor | None) -> None:
    """Close down in order: each node's final /diagnostics, what it published acknowledged
    (:func:`flush`), its ``close()`` and removal; then the executor and rclpy's context."""
    for node in nodes:
        diag = getattr(node, 'diag', None)
        if isinstance(diag, Diagnostics) and rclpy.ok():
            diag.publish()                  # final counters, for recorders still listening
        if rclpy.ok():
            flush(node)
        close = getattr(node, 'close', None)
        if close is not None:
            close()
        if executor is not None:
            executor.remove_node(node)
        node.destroy_node()
    if executor is not None:
        executor.shutdown()
    rclpy.try_shutdown()
