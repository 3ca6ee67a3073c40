"""Print the messages or the rate of one topic of the graph (``ros2 topic echo`` / ``hz`` for pip).

    python -m soft_gripper_sdre.tools.graph.echo TOPIC [--rate] [--once | --count N] [--timeout SEC]

The message type and QoS come from the topic table (nodes/topics.py), so only the graph's topics
are known. Messages print as YAML documents separated by ``---``; with ``--rate`` the average rate
over each second is printed instead (the subscription is raw, so fast topics are measured without
deserialising them). Exit status: 0, 1 if ``--timeout`` ran out before ``--count`` messages, 2
for an unknown topic.
"""
from __future__ import annotations

import argparse
import array
import os
import sys
import time

import numpy as np
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
import yaml

from soft_gripper_sdre.nodes.common import run
from soft_gripper_sdre.nodes.recorder import find_topic, topic_qos
from soft_gripper_sdre.nodes.topics import TOPIC_TYPES


def message_to_dict(value):
    """A message as nested dicts / lists of plain Python values (field order kept)."""
    if hasattr(value, 'get_fields_and_field_types'):
        return {name: message_to_dict(getattr(value, name))
                for name in value.get_fields_and_field_types()}
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple, array.array, np.ndarray)):
        return [message_to_dict(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class EchoNode(Node):
    """Subscribe one topic; print each message (or the rate) until ``count`` messages or
    ``timeout``."""

    def __init__(self, topic: str, rate: bool = False, count: int | None = None,
                 timeout: float | None = None, **kwargs) -> None:
        super().__init__(f'sgs_echo_{os.getpid()}', **kwargs)
        self.topic = topic
        self.count = count
        self.received = 0
        self.done = False
        self.exit_code = 0
        self._window_start = time.monotonic()
        self._window_count = 0
        self.create_subscription(TOPIC_TYPES[topic], topic,
                                 self._on_raw if rate else self._on_message,
                                 topic_qos(topic), raw=rate)
        if rate:
            self.create_timer(1.0, self._print_rate)
        if timeout is not None:
            self._deadline = self.create_timer(timeout, self._on_timeout)

    def _on_message(self, msg) -> None:
        if self.done:
            return
        print(yaml.safe_dump(message_to_dict(msg), sort_keys=False, allow_unicode=True, width=120)
              + '---', flush=True)
        self._received_one()

    def _on_raw(self, _data: bytes) -> None:
        if not self.done:
            self._window_count += 1
            self._received_one()

    def _received_one(self) -> None:
        self.received += 1
        if self.count is not None and self.received >= self.count:
            self.done = True

    def _print_rate(self) -> None:
        now = time.monotonic()
        elapsed, n = now - self._window_start, self._window_count
        self._window_start, self._window_count = now, 0
        if n:
            print(f'average rate: {n / elapsed:.2f} Hz ({n} messages in {elapsed:.2f} s)',
                  flush=True)
        else:
            print(f'no new messages on {self.resolve_topic_name(self.topic)}', flush=True)

    def _on_timeout(self) -> None:
        self._deadline.cancel()
        if self.count is not None and self.received < self.count:
            print(f'timeout: {self.received} of {self.count} messages on '
                  f'{self.resolve_topic_name(self.topic)}', file=sys.stderr, flush=True)
            self.exit_code = 1
        self.done = True


def main(argv: list[str] | None = None) -> int:
    full = sys.argv if argv is None else ['sgs_echo', *argv]
    parser = argparse.ArgumentParser(prog='sgs_echo', description=__doc__.split('\n\n')[0])
    parser.add_argument('topic', help=f'one of: {", ".join(TOPIC_TYPES)}')
    parser.add_argument('--rate', action='store_true', help='print the average rate every second')
    stop = parser.add_mutually_exclusive_group()
    stop.add_argument('--once', action='store_true', help='exit after the first message')
    stop.add_argument('--count', type=int, default=None, help='exit after N messages')
    parser.add_argument('--timeout', type=float, default=None,
                        help='give up after this many seconds (exit 1 if --once/--count unmet)')
    args = parser.parse_args(remove_ros_args(full)[1:])
    topic = find_topic(args.topic)
    if topic is None:
        print(f'{parser.prog}: error: unknown topic {args.topic!r}; known topics: '
              f'{", ".join(TOPIC_TYPES)}', file=sys.stderr)
        return 2
    if args.count is not None and args.count < 1:
        parser.error(f'--count must be >= 1, got {args.count}')
    if args.timeout is not None and not args.timeout > 0:
        parser.error(f'--timeout must be > 0 s, got {args.timeout}')
    count = 1 if args.once else args.count
    return run(lambda: EchoNode(topic, args.rate, count, args.timeout), full)


if __name__ == '__main__':
    sys.exit(main())
