"""What every node shares: process lifetime, throttled warnings, counters in /diagnostics."""
from __future__ import annotations

from collections import Counter
import signal
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node

from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


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
    """Counters and a status level published as one DiagnosticStatus on /diagnostics (~1 Hz, wall)."""

    def __init__(self, node: Node, hardware_id: str = 'soft_gripper', period: float = 1.0) -> None:
        self.node = node
        self.counters: Counter = Counter()
        self.values: dict[str, str] = {}
        self.level = OK
        self.message = 'ok'
        self._hardware_id = hardware_id
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

    def set_status(self, level: int, message: str) -> None:
        self.level, self.message = level, message

    def flush(self, timeout: float = 2.0) -> bool:
        """Wait up to ``timeout`` s until every subscriber acknowledged what was published."""
        return self._pub.wait_for_all_acked(Duration(nanoseconds=int(timeout * 1e9)))

    def publish(self) -> None:
        status = DiagnosticStatus(level=self.level, name=self.node.get_fully_qualified_name(),
                                  message=self.message, hardware_id=self._hardware_id)
        status.values = ([KeyValue(key=k, value=str(v)) for k, v in sorted(self.counters.items())]
                         + [KeyValue(key=k, value=v) for k, v in sorted(self.values.items())])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)


def run(node_factory: Callable[..., Node], args: list[str] | None = None) -> int:
    """``main()`` of every node: init → construct → spin until shutdown or ``node.done`` → clean up.

    SIGTERM is handled like SIGINT. A :class:`ParameterError` at construction is logged and the
    process exits with status 2; other construction errors exit 1.
    """
    # Our own SIGINT handling (KeyboardInterrupt) keeps the context alive while the node closes,
    # so it can still publish its final diagnostics and, for the recorder, finish the bag.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, lambda *_: signal.raise_signal(signal.SIGINT))
    node = None
    code = 0
    try:
        try:
            node = node_factory()
        except ParameterError as exc:
            rclpy.logging.get_logger('soft_gripper_sdre').fatal(f'bad parameter: {exc}')
            return 2
        except (OSError, ValueError) as exc:
            rclpy.logging.get_logger('soft_gripper_sdre').fatal(f'cannot start: {exc}')
            return 1
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not getattr(node, 'done', False):
            executor.spin_once(timeout_sec=0.1)
        code = int(getattr(node, 'exit_code', 0))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            diag = getattr(node, 'diag', None)
            if isinstance(diag, Diagnostics) and rclpy.ok():
                diag.publish()                  # final counters, for recorders still listening:
                diag.flush()                    # delivered before the process goes
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code
