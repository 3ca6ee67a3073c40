"""One DDS hop between two processes, with the graph's own message, QoS and executor: the rclpy
floor of a loop period (``make bench``'s hop rows).

:func:`hop` pings from this process; the far end is this module run as a program,
``python -m soft_gripper_sdre.tools.benchmarks.hop COUNT [--raw]`` (:func:`echo`).
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager
import os
import time
from typing import Iterator

from soft_gripper_sdre.nodes import scheduling
from soft_gripper_sdre.nodes.graph import cpus_prefix, pinned_cpus, realtime_prefix
from soft_gripper_sdre.tools.graph.procs import ros_env

#: a ping-pong round unanswered this long [s] sends its ping again (see :func:`hop`)
RESEND_S = 1.0


def echo(count: int, raw: bool = False) -> int:
    """The far end of :func:`hop`: answer the tip messages stamped 0 … ``count - 1`` on
    ``bench_pong``, print the CPU seconds this process spent per message, and go when the pinging
    side says so with a ping stamped ``count``. ``raw``: receive the CDR bytes, decode and encode
    them as the loop nodes do (nodes/cdr.py); otherwise republish the message rclpy built."""
    from geometry_msgs.msg import PoseArray
    import rclpy
    from rclpy.node import Node

    from soft_gripper_sdre.nodes import cdr
    from soft_gripper_sdre.nodes import conversions as cv
    from soft_gripper_sdre.nodes.common import make_executor
    from soft_gripper_sdre.nodes.topics import LOOP_QOS
    codec = cdr.tips_codec(4) if raw else None     # learned before any DDS entity exists
    rclpy.init()
    node = Node('bench_echo')
    pub = node.create_publisher(PoseArray, 'bench_pong', LOOP_QOS)
    seen = {'n': 0, 'cpu': [0.0, 0.0], 'last': -1}

    def on_ping(msg) -> None:
        if raw:
            stamp, tips = codec.decode(msg)
        else:
            stamp = cv.from_time(msg.header.stamp)
        if stamp >= count:
            seen['last'] = stamp                     # goodbye: every pong has arrived
            return
        if seen['n'] == 0:
            seen['cpu'][0] = time.process_time()     # CPU from the first message on
        seen['n'] += 1
        pub.publish(codec.encode(stamp, tips) if raw else msg)
        if stamp == count - 1:
            seen['cpu'][1] = time.process_time()
    node.create_subscription(PoseArray, 'bench_ping', on_ping, LOOP_QOS, raw=raw)
    executor = make_executor()
    executor.add_node(node)
    # a last pong published just before this writer is destroyed can be lost, and the pinging
    # side would wait out its deadline: so this side waits for the goodbye
    deadline = time.monotonic() + 120.0
    while seen['last'] < count and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    end = seen['cpu'][1] or time.process_time()     # (the last round unanswered: up to now)
    cpu = (end - seen['cpu'][0]) / max(seen['n'] - 1, 1)
    print(f'cpu_per_message {cpu:.9f}', flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


class _Pinger:
    """The pinging side of :func:`hop` on ``node``: round k's ping is stamped k ns, and only the
    pong with that stamp ends it, its round trip in ``rtt[k]`` [s]."""

    def __init__(self, node, count: int) -> None:
        from geometry_msgs.msg import PoseArray
        import numpy as np

        from soft_gripper_sdre.nodes import conversions as cv
        from soft_gripper_sdre.nodes.topics import LOOP_QOS
        self._cv, self.count = cv, count
        self.msg = cv.tips_to_msg(0, np.zeros((4, 3)))
        self.rtt = np.zeros(count)
        self.k, self.t0, self.resent = 0, 0.0, 0
        self.pub = node.create_publisher(PoseArray, 'bench_ping', LOOP_QOS)
        self.sub = node.create_subscription(PoseArray, 'bench_pong', self.on_pong, LOOP_QOS)

    def ping(self) -> None:
        self._cv.set_time(self.msg.header.stamp, self.k)
        self.t0 = time.perf_counter()
        self.pub.publish(self.msg)

    def on_pong(self, pong) -> None:
        now = time.perf_counter()
        if self._cv.from_time(pong.header.stamp) != self.k:
            return                                   # the answer to a resent ping's first copy
        self.rtt[self.k] = now - self.t0
        self.k += 1
        if self.k < self.count:
            self.ping()

    def rounds(self, ex) -> int:
        """Once both sides have matched, ping every round in turn with ``ex`` spinning, a round
        unanswered for :data:`RESEND_S` pinged again; returns the rounds answered."""
        deadline = time.monotonic() + 30.0
        while (self.sub.get_publisher_count() == 0
               or self.pub.get_subscription_count() == 0) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        self.ping()
        deadline = time.monotonic() + 120.0
        while self.k < self.count and time.monotonic() < deadline:
            k = self.k
            ex.spin_once(timeout_sec=0.1)
            if self.k == k < self.count and time.perf_counter() - self.t0 > RESEND_S:
                self.resent += 1
                self.ping()
        return self.k

    def goodbye(self, far_end) -> str:
        """Ping stamped ``count`` (see :func:`echo`), again until the ``far_end`` process ends;
        returns what it printed ('' if it never did)."""
        import subprocess
        self.k = self.count
        for _ in range(30):
            self.ping()
            try:
                out, _ = far_end.communicate(timeout=RESEND_S)
                return out
            except subprocess.TimeoutExpired:
                continue
        return ''


@contextmanager
def _running_as(priority: int, cpu: int | None, cpu_latency: int | None) -> Iterator[None]:
    """The calling thread (and the threads and processes it starts meanwhile) under SCHED_FIFO at
    ``priority`` (0: as it is) and on ``cpu`` (None: as it is), the CPU wake-up latency held at
    ``cpu_latency`` µs (None: not), as a loop process runs so (nodes/scheduling.py); put back
    after."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    affinity = os.sched_getaffinity(0)
    hold = None
    if priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    if cpu_latency is not None:
        hold, _ = scheduling.hold_cpu_latency({scheduling.CPU_LATENCY_ENV: str(cpu_latency)})
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    try:
        yield
    finally:
        if hold is not None:
            hold.close()
        os.sched_setaffinity(0, affinity)
        os.sched_setscheduler(0, policy, param)


def hop(executor: str, count: int = 2000, raw: bool = False, realtime: int = 0,
        pin: bool = False, cpu_latency: int | None = None) -> dict[str, float]:
    """One DDS hop with the graph's own message and executor, between two processes.

    A ping-pong of ``tip_positions``-sized PoseArrays: half the round trip is the latency of one
    hop (publish → callback in the other process → publish back); the echo process reports its CPU
    per message (receive + publish; with ``raw`` as CDR bytes decoded and encoded by nodes/cdr.py,
    as the loop nodes do). Returns µs: ``p50``, ``p99`` of one hop, ``cpu``; and the counts
    ``rounds`` (answered, of ``count``) and ``resent``. ``realtime``: both processes under
    SCHED_FIFO at that priority (the caller checks the permission: ``scheduling.fifo_problem``);
    ``cpu_latency``: the CPU wake-up latency held at that many µs meanwhile;
    ``pin``: each on a CPU of its own (``pinned_cpus``: the echo where the simulator would run,
    this side where the estimator would).

    Round k's ping is stamped k ns and only the pong with that stamp ends it. Discovery is not
    symmetric: our reader can have matched the echo's writer before that writer has matched our
    reader, and a pong published then is dropped (volatile). So a round unanswered for
    ``RESEND_S`` sends its ping again (with a fresh start time); a late duplicate pong is ignored.
    A ping stamped ``count`` tells the echo that every pong has arrived.
    """
    import subprocess
    import sys

    import numpy as np
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    from soft_gripper_sdre.nodes.common import EXECUTOR_ENV, make_executor

    env = ros_env()
    env[EXECUTOR_ENV] = executor
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    cpus = pinned_cpus() if pin else {}
    echo_cpus = (cpus['simulator'],) if pin else ()
    with _running_as(realtime, cpus.get('estimator'), cpu_latency):
        echo = subprocess.Popen([*cpus_prefix(echo_cpus), *realtime_prefix(realtime),
                                 sys.executable, '-m',
                                 'soft_gripper_sdre.tools.benchmarks.hop', str(count)]
                                + ['--raw'] * raw, env=env, stdout=subprocess.PIPE, text=True)
        ctx = Context()
        rclpy.init(context=ctx)
        node = Node('bench_ping', context=ctx)
        ex = make_executor(executor, context=ctx)
        pinger = _Pinger(node, count)
        ex.add_node(node)
        try:
            rounds = pinger.rounds(ex)
            out = pinger.goodbye(echo)
        finally:
            if echo.poll() is None:
                echo.kill()
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
    cpu = next((float(line.split()[1]) for line in out.splitlines()
                if line.startswith('cpu_per_message')), float('nan'))
    one_way = 0.5e6 * pinger.rtt[:rounds]
    return {'p50': float(np.percentile(one_way, 50)), 'p99': float(np.percentile(one_way, 99)),
            'cpu': 1e6 * cpu, 'rounds': rounds, 'resent': pinger.resent}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.hop',
                                 description="the far end of hop(): answers COUNT pings")
    ap.add_argument('count', type=int, help='pings to answer (stamped 0 … COUNT − 1)')
    ap.add_argument('--raw', action='store_true', help='decode and encode the CDR bytes')
    a = ap.parse_args(argv)
    if a.count < 1:
        ap.error(f'COUNT must be >= 1, got {a.count}')
    return echo(a.count, a.raw)


if __name__ == '__main__':
    raise SystemExit(main())
