"""Launch-free rclpy test helpers: own Context, one executor, deadline loops, discovery waits."""
from __future__ import annotations

import contextlib
import copy
import gc
import time

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from soft_gripper_sdre.nodes.common import make_executor


def overrides(**params) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in params.items()]


@contextlib.contextmanager
def ros_context(executor: str = 'single'):
    """A fresh rclpy Context and an executor on it ('single' or 'events', as the node processes
    spin), torn down afterwards.

    The garbage collector is off inside: a test process holds pytest's, torch's and every received
    message's objects (about 300 000), and one full collection of them stalls every node spun here
    for 0.1 s on a quiet machine, 0.5 s on a loaded one, long enough to trip a lockstep timeout.
    A node process has none of that heap (docs/performance.md measures its collections)."""
    ctx = Context()
    rclpy.init(context=ctx)
    executor = make_executor(executor, context=ctx)
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield ctx, executor
    finally:
        if collecting:
            gc.enable()
        for node in list(executor.get_nodes()):
            executor.remove_node(node)
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=ctx)


def spin_until(executor, predicate, timeout: float = 10.0) -> bool:
    """Spin until ``predicate()`` is true or ``timeout`` seconds pass; returns the predicate."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.01)
    return bool(predicate())


def linked(publisher, *readers: Node) -> bool:
    """Both ends of ``publisher``'s links matched: every node of ``readers`` has a subscription to
    its topic that has matched a writer, and the publisher has matched at least that many readers.
    Counts at least, never exactly: a participant that exits without saying so (a killed process
    of an earlier test on the domain) stays a match until its lease runs out."""
    topic = publisher.topic_name
    subs = [[s for s in node.subscriptions if s.topic_name == topic] for node in readers]
    return (publisher.get_subscription_count() >= len(readers)
            and all(any(s.get_publisher_count() > 0 for s in found) for found in subs))


def drain(executor, seconds: float = 0.1) -> None:
    """Run every callback that becomes ready within ``seconds`` (a poll for :meth:`Graph.wait`,
    which sleeps 0.1 s between polls; one ``spin_once`` would take one message a poll)."""
    spin_until(executor, lambda: False, seconds)


def deep(qos, depth: int = 10_000):
    """``qos`` with a reader history deep enough to hold what arrives between polls (the loop
    topics' depth 50 is 50 ms at 1 kHz)."""
    qos = copy.copy(qos)
    qos.depth = depth
    return qos


class Probe(Node):
    """A test node that publishes and records whatever the test asks."""

    def __init__(self, context, name: str = 'probe') -> None:
        super().__init__(name, context=context)
        self.received: dict[str, list] = {}

    def listen(self, msg_type, topic: str, qos):
        self.received.setdefault(topic, [])
        return self.create_subscription(msg_type, topic, self.received[topic].append, qos)
