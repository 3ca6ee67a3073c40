"""When the simulator takes its first step: once the graph is wired and ready
(docs/design/loop_rules.md, "Start").

Tips published before their readers match would be lost, and with them the first period. So the
first step waits for ``min_tip_subscribers`` readers of the tips, a command writer and
``min_diagnostics_subscribers`` readers of /diagnostics (other than the gate's own reader) and,
given the graph's other nodes (``wait_for_nodes``), for the start rule
:func:`~soft_gripper_sdre.nodes.graph.readiness_problem` over their /diagnostics: each of them has
reported, and every writer and reader of the graph has matched its peers. Without
``wait_for_nodes`` the simulator starts after ``startup_timeout`` with what is there (a warning);
with it, it gives up instead, naming what is missing.
"""
from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription

from soft_gripper_sdre.nodes.common import ERROR, Diagnostics, wiring
from soft_gripper_sdre.nodes.graph import GRASP_NODES, readiness_problem
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

#: how often the gate looks [s of wall time]
LOOK_PERIOD = 0.01


def waited_nodes(text: str) -> tuple[str, ...]:
    """``wait_for_nodes`` as names: ``'recorder, estimator'`` → ``('recorder', 'estimator')``."""
    return tuple(name.strip() for name in text.split(',') if name.strip())


def waited_nodes_problem(text: str) -> str | None:
    """Why ``wait_for_nodes`` is refused: a name not of the grasp graph's other nodes, or one
    named twice (None: accepted)."""
    names = waited_nodes(text)
    known = [n for n in GRASP_NODES if n != 'simulator']
    unknown = [n for n in names if n not in known]
    if unknown:
        return f'{unknown[0]!r} is not a node of the grasp graph ({", ".join(known)})'
    if len(set(names)) != len(names):
        return f'{text!r} names a node twice'
    return None


@dataclass(frozen=True)
class StartRule:
    """What the first step waits for, and how long (the simulator's start-up parameters)."""

    tip_readers: int                # min_tip_subscribers
    diagnostics_readers: int        # min_diagnostics_subscribers
    nodes: tuple[str, ...]          # wait_for_nodes, as names ('': none)
    timeout: float                  # startup_timeout [s of wall time]

    @classmethod
    def from_params(cls, p: dict) -> StartRule:
        return cls(p['min_tip_subscribers'], p['min_diagnostics_subscribers'],
                   waited_nodes(p['wait_for_nodes']), p['startup_timeout'])


class StartGate:
    """Looks every :data:`LOOK_PERIOD` until the graph is ready, then calls ``start`` once; or,
    with nodes to wait for, gives up at the timeout (``gave_up``, ERROR in ``diag``).

    Args:
        node: the simulator node: its namespace, topics and logger.
        rule: what to wait for.
        tips: the publisher of the tips, whose readers are counted.
        commands: the subscription to the commands, whose writers are counted.
        diag: the node's diagnostics, whose readers are counted.
        start: called when the graph is ready, or at the timeout without nodes to wait for.
    """

    def __init__(self, node: Node, rule: StartRule, *, tips: Publisher, commands: Subscription,
                 diag: Diagnostics, start: Callable[[], None]) -> None:
        self._node, self.rule = node, rule
        self._tips, self._commands, self._diag, self._start = tips, commands, diag, start
        self.gave_up = False
        self._deadline = time.monotonic() + rule.timeout
        self._reports: dict[str, dict[str, str]] = {}      # /diagnostics values by full name
        self._sub_diag = (node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_report,
                                                   STREAM_QOS) if rule.nodes else None)
        self._timer = node.create_timer(LOOK_PERIOD, self._look)

    def _on_report(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self._reports[status.name] = {kv.key: kv.value for kv in status.values}

    def problem(self) -> str | None:
        """What the first step still waits for (module doc), or None."""
        problems = []
        rule = self.rule
        tips, commands = self._tips.get_subscription_count(), self._commands.get_publisher_count()
        if tips < rule.tip_readers:
            problems.append(f'{tips} of {rule.tip_readers} tip_positions readers')
        if commands < 1:
            problems.append('no torque_commands writer')
        readers = self._diag.subscription_count() - (self._sub_diag is not None)   # not its own
        if readers < rule.diagnostics_readers:
            problems.append(f'{readers} of {rule.diagnostics_readers} /diagnostics readers')
        if rule.nodes:
            prefix = self._node.get_namespace().rstrip('/')
            reports = {'simulator': wiring(self._node)} | {n: self._reports.get(f'{prefix}/{n}')
                                                           for n in rule.nodes}
            graph = readiness_problem(('simulator', *rule.nodes), reports,
                                      self._node.resolve_topic_name)
            if graph:
                problems.append(graph)
        return '; '.join(problems) or None

    def _look(self) -> None:
        problem = self.problem()
        if problem and time.monotonic() < self._deadline:
            return
        self._timer.cancel()
        log = self._node.get_logger()
        if problem and self.rule.nodes:
            log.error(f'the graph was not ready within startup_timeout ({self.rule.timeout:g} s): '
                      f'{problem}; giving up')
            self._diag.set_status(ERROR, f'the graph was not ready: {problem}')
            self.gave_up = True
            return
        if problem:
            log.warning(f'starting with an incomplete graph after startup_timeout: {problem}')
        elif self.rule.nodes:
            log.info(f'the graph is wired and ready ({", ".join(self.rule.nodes)}); stepping')
        if self._sub_diag is not None:
            self._node.destroy_subscription(self._sub_diag)
            self._sub_diag = None
        self._start()
