"""The recorder node: a ``ros2 bag record`` for the pip environment (rosbags writer, MCAP storage).

Subscribes each topic in ``topics`` with ``raw=True`` (the serialized CDR bytes go into the bag as
received: no deserialisation cost), with its publishers' QoS but a queue of ``RECORD_DEPTH``
messages, and writes a rosbag2 directory (format version 9, metadata.yaml
plus one ``.mcap`` file) that ``ros2 bag info`` / ``ros2 bag play`` on Jazzy read. The writer is closed
in :meth:`RecorderNode.close`, which ``common.run`` calls on SIGINT, SIGTERM and normal exit, so
metadata.yaml is always written. Per-topic message counts go to /diagnostics.

Timestamp of each bag entry (the graph's time domain is sim time; README "Topics"):

* a message's own stamp (``header.stamp``, or ``clock`` for /clock), read from the CDR bytes — the
  sim time the data refers to, so a lockstep run gives the same bag on any machine;
* the latest /clock value instead when the stamp lies more than ``SKEW_NS`` from it: such a stamp is
  not the current sim time but an unset header (0) or a node whose clock is wall time (e.g. its
  /diagnostics), and would misplace the entry or stretch the bag over decades;
* messages that arrive before the first /clock are held back (at most ``MAX_PENDING``) and written
  once it comes, with the same rule, so a bag never mixes wall and sim time; if no /clock arrives
  (a graph without sim time) they are written with their stamp, else their wall receive time.
"""
from __future__ import annotations

import copy
from datetime import datetime
import functools
import os
from pathlib import Path
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes.common import ERROR, OK, Diagnostics, ThrottledLogger, run
from soft_gripper_sdre.nodes.params import Param, ParameterError, declare_all
from soft_gripper_sdre.nodes.topics import (CLOCK, CLOCK_QOS, GRASP_REFERENCE, LOOP_QOS, REFERENCE_QOS,
                                            STATE_ESTIMATE, STREAM_QOS, TIP_POSITIONS, TOPIC_TYPES,
                                            TORQUE_COMMANDS, type_name)

#: topics of the 1 kHz control loop (LOOP_QOS); /clock has CLOCK_QOS, the plan REFERENCE_QOS (a
#: recorder that starts after the plan went out still gets it), the rest STREAM_QOS
LOOP_TOPICS = (TIP_POSITIONS, STATE_ESTIMATE, TORQUE_COMMANDS)
#: a stamp further than this from the latest /clock is not the current sim time
SKEW_NS = 1_000_000_000
#: messages held back while waiting for the first /clock
MAX_PENDING = 10_000
#: queue of each recording subscription: 1 s of a 1 kHz topic, so a recorder that falls behind for
#: a moment (a busy machine) catches up instead of losing the oldest messages
RECORD_DEPTH = 1000
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}

PARAMS = (
    Param('output', '', 'bag directory to create; must not exist yet '
          "('' = rosbag2_<date>-<time> in the working directory)", read_only=True),
    Param('topics', list(TOPIC_TYPES), 'topics to record (names as in the topic table)',
          read_only=True),
    Param('storage', 'mcap', 'rosbag2 storage plugin', choices=tuple(STORAGES), read_only=True),
)


def find_topic(name: str) -> str | None:
    """The key of :data:`TOPIC_TYPES` that ``name`` means ('/tip_positions' or 'tip_positions')."""
    wanted = name.strip().lstrip('/')
    return next((t for t in TOPIC_TYPES if t.lstrip('/') == wanted), None)


def topic_qos(topic: str) -> QoSProfile:
    """QoS of ``topic``'s publishers (topics.py); the recorder subscribes with it, deeper."""
    if topic == CLOCK:
        return CLOCK_QOS
    if topic == GRASP_REFERENCE:
        return REFERENCE_QOS
    return LOOP_QOS if topic in LOOP_TOPICS else STREAM_QOS


def _bag_qos(profile: QoSProfile) -> Qos:
    """rclpy QoS profile → rosbags Qos, for the offered_qos_profiles that ``ros2 bag play`` uses."""
    def duration(d) -> QosTime:
        return QosTime(sec=d.nanoseconds // 1_000_000_000, nsec=d.nanoseconds % 1_000_000_000)

    return Qos(history=QosHistory[profile.history.name], depth=profile.depth,
               reliability=QosReliability[profile.reliability.name],
               durability=QosDurability[profile.durability.name],
               deadline=duration(profile.deadline), lifespan=duration(profile.lifespan),
               liveliness=QosLiveliness[profile.liveliness.name],
               liveliness_lease_duration=duration(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions)


def _is_stamped(msg_class) -> bool:
    """Whether the message starts with a builtin_interfaces/Time (``header.stamp`` or ``clock``)."""
    first = next(iter(msg_class.get_fields_and_field_types().values()), '')
    return first in ('std_msgs/Header', 'builtin_interfaces/Time')


def _output_path(value: str) -> Path:
    """The bag directory named by the ``output`` parameter; refuses an existing or unwritable path."""
    path = Path(value or datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')).expanduser().absolute()
    if path.exists():
        raise ParameterError(f"parameter 'output': {path} already exists (a bag is never overwritten)")
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not (parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)):
        raise ParameterError(f"parameter 'output': cannot create {path}: {parent} is not a writable directory")
    return path


class RecorderNode(Node):
    """Record topics of the graph into a rosbag2 (MCAP) directory (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('recorder', **kwargs)
        p = declare_all(self, PARAMS)
        names = list(p['topics'])
        if not names:
            raise ParameterError("parameter 'topics': name at least one topic")
        topics = []
        for name in names:
            topic = find_topic(name)
            if topic is None:
                raise ParameterError(f"parameter 'topics': unknown topic {name!r} "
                                     f'(known: {", ".join(TOPIC_TYPES)})')
            if topic not in topics:
                topics.append(topic)
        self.path = _output_path(p['output'])
        self._writer: Writer | None = Writer(self.path, version=Writer.VERSION_LATEST,
                                             storage_plugin=STORAGES[p['storage']])
        try:
            self._writer.open()
        except (OSError, WriterError) as exc:
            raise ParameterError(f"parameter 'output': cannot create bag {self.path}: {exc}") from None

        typestore = get_typestore(Stores.ROS2_JAZZY)
        self.counts: dict[str, int] = {}
        self.clock_ns: int | None = None          # latest /clock value
        self._pending: list[tuple] | None = []    # held until the first /clock; None once flushed
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        self._subs: dict = {}
        for topic in topics:
            msg_class, qos = TOPIC_TYPES[topic], topic_qos(topic)
            name = self.resolve_topic_name(topic)   # fully qualified, as ros2 bag stores it
            conn = self._writer.add_connection(name, type_name(msg_class), typestore=typestore,
                                               offered_qos_profiles=[_bag_qos(qos)])
            self.counts[name] = 0
            callback = functools.partial(self._on_message, name, conn, _is_stamped(msg_class),
                                         topic == CLOCK)
            deep = copy.copy(qos)
            deep.depth = RECORD_DEPTH           # history depth is not part of QoS matching
            self._subs[name] = self.create_subscription(msg_class, topic, callback, deep, raw=True)
        self.diag.values['output'] = str(self.path)
        self._matched_timer = self.create_timer(0.2, self._report_publishers)
        self.diag.set_status(OK, f'recording {len(topics)} topics')
        self.get_logger().info(f'recording {", ".join(self.counts)} to {self.path} ({p["storage"]})')

    def _report_publishers(self) -> None:
        """Matched publishers per topic in /diagnostics ('publishers /topic'), so a supervisor
        can start the simulator only once everything it records is connected."""
        for name, sub in self._subs.items():
            self.diag.values[f'publishers {name}'] = str(sub.get_publisher_count())

    # -- receiving ---------------------------------------------------------------------------
    def _on_message(self, topic: str, conn, stamped: bool, is_clock: bool, data: bytes) -> None:
        """Write one serialized message; never raises (bad input is counted and logged)."""
        if self._writer is None:
            return
        try:
            stamp = cdr.leading_stamp(data) if stamped else None
            if is_clock and stamp is not None:
                self.clock_ns = stamp
            self.counts[topic] += 1
            self.diag.count(f'messages {topic}')
            if self._pending is None:
                self._write(conn, self._entry_time(stamp, time.time_ns()), data)
                return
            self._pending.append((conn, stamp, time.time_ns(), data))
            if self.clock_ns is not None or len(self._pending) >= MAX_PENDING:
                self._flush_pending()
        except Exception as exc:  # noqa: BLE001 — a recorder must survive anything it receives
            self.diag.count('errors')
            self.log.warn('receive', f'{topic}: message not recorded: {exc!r}')

    def _entry_time(self, stamp: int | None, wall_ns: int) -> int:
        """Bag timestamp [ns] of a message (the rule in the module doc)."""
        if self.clock_ns is None:
            return stamp if stamp is not None else wall_ns
        if stamp is not None and abs(stamp - self.clock_ns) <= SKEW_NS:
            return stamp
        return self.clock_ns

    def _flush_pending(self) -> None:
        pending, self._pending = self._pending or [], None
        for conn, stamp, wall_ns, data in pending:
            self._write(conn, self._entry_time(stamp, wall_ns), data)

    def _write(self, conn, timestamp: int, data: bytes) -> None:
        try:
            self._writer.write(conn, timestamp, data)
        except (OSError, WriterError) as exc:
            self.diag.count('write_errors')
            self.diag.set_status(ERROR, f'cannot write to {self.path}: {exc}')
            self.log.warn('write', f'cannot write to {self.path}: {exc}')

    # -- shutdown ----------------------------------------------------------------------------
    def close(self) -> None:
        """Write held-back messages, close the storage and write metadata.yaml (idempotent)."""
        if self._writer is None:
            return
        self._flush_pending()
        writer, self._writer = self._writer, None
        # after a SIGINT the context is shut down and the node logger can no longer reach /rosout
        logger = self.get_logger() if self.context.ok() else rclpy.logging.get_logger('soft_gripper_sdre')
        try:
            writer.close()
        except (OSError, WriterError) as exc:
            logger.error(f'closing {self.path} failed: {exc}')
            return
        logger.info(f'wrote {sum(self.counts.values())} messages to {self.path}')


def main(args=None) -> int:
    return run(RecorderNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
