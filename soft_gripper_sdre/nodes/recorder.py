"""The recorder node: a ``ros2 bag record`` for the pip environment (rosbags writer, MCAP storage).

Records each topic in ``topics`` with ``raw=True`` (the serialized CDR bytes go into the bag as
received: no deserialisation cost), with a queue of ``RECORD_DEPTH`` messages, and writes a
rosbag2 directory (format version 9, metadata.yaml plus one ``.mcap`` file) that
``ros2 bag info`` / ``ros2 bag play`` on Jazzy read. The writer is closed in
:meth:`RecorderNode.close`, which ``common.run`` calls on SIGINT, SIGTERM and normal exit, so
metadata.yaml is always written. Per-topic message counts and matched publishers go to
/diagnostics.

Which topics, with which QoS:

* a name of the topic table (README "Topics", ``tip_positions`` or ``/tip_positions``; remapping
  applies, ``-r tip_positions:=/mocap/tips``) is subscribed at once with its type and its
  publishers' QoS from the table; ``tip_positions`` with ``tips_reliability`` (``best_effort``
  hears a driver publishing with the sensor-data QoS);
* any other name (namespaced, remapped, a topic of your own) is subscribed once a publisher
  appears in the graph, with the type the graph reports, and with the QoS ``ros2 bag record``
  adapts to the publishers' offers: reliable only if every publisher offers reliable, transient
  local only if every one offers it. Messages sent before that are not recorded.

Timestamp of each bag entry (the graph's time domain is sim time, or the driver's own clock when
there is no /clock):

* a message's own stamp (``header.stamp``, or ``clock`` for /clock), read from the CDR bytes — the
  time the data refers to, so a lockstep run gives the same bag on any machine;
* the latest /clock value instead when the stamp lies more than ``SKEW_NS`` from it: such a stamp is
  not the current sim time but an unset header (0) or a node whose clock is wall time (e.g. its
  /diagnostics), and would misplace the entry or stretch the bag over decades;
* while /clock is recorded but has not ticked yet, messages are held back and written once it
  comes, with the same rule, so a bag never mixes wall and sim time. Held messages are written
  with their own stamps (unstamped ones at their receive time) as soon as the graph shows it runs
  without sim time: a message of a topic other than ``WALL_TIME_TOPICS`` stamped within
  ``SKEW_NS`` of the wall clock (a driver stamping with wall time). At most ``MAX_PENDING``
  messages or ``CLOCK_WAIT_S`` of wall time are held; without /clock among the topics nothing is.

A run that never started need leave no bag: with ``discard_without`` naming a recorded topic
(the identification recipe gives ``torque_commands``), a bag in which that topic got no message
is removed at exit, with a warning, so the same ``output`` can be given again (an excitation
node that refused its arguments leaves only the driver's tips). By default every bag is kept.

The first message of each topic is reported on /diagnostics at once (``messages <topic>``), not
at the next 1 Hz report: the excitation node starts its run only once the recorder has received
both its tips and its commands. Such a report carries ``report: first <topic>``, and a recorder
that records /diagnostics leaves its own of them out of the bag, which holds what it would
without them.

Messages missing from a stream are counted per topic from its publisher's stamps
(:class:`GapCounter`; ROS 2 headers carry no sequence counter): each stamped topic with one
publisher learns its period as the median step of its recent stamps, and a step over
``GAP_FACTOR`` periods counts the periods it skipped as lost. A loss is either a message the
recorder never got (DDS, or a queue that overflowed while it was starved of CPU) or one the
publisher never sent (a node that skipped a period); the publisher's own counts in its
/diagnostics tell which. The counts go to /diagnostics (``lost <topic>``, and the learned
``period <topic>``), which is at WARN, naming the topics, in every report while losses grow and
back at OK after a report without a new one; the log WARNs with the counts (throttled), and the
run's totals are logged when the bag is closed. A step over ``JUMP_SECONDS`` and
``JUMP_PERIODS`` periods that is also ``JUMP_RATIO`` times longer than the time between the two
messages' arrivals is a jump, not losses (a clock set forward, a bad stamp; a stalled publisher's
or recorder's stamps advance with the time that passed, and its gap is losses): counted as
``jumps <topic>``, at WARN the same way, and the stream is judged afresh from it. Topics
stamped with wall time by several nodes (``WALL_TIME_TOPICS``), unstamped ones and a topic while
it has several publishers are not judged; a stamp that goes back (a restarted publisher) starts
the stream afresh.
"""
from __future__ import annotations

from collections import deque
import copy
from datetime import datetime
import functools
import importlib
import os
from pathlib import Path
import shutil
import statistics
import time

from diagnostic_msgs.msg import DiagnosticArray
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes.common import ERROR, OK, WARN, Diagnostics, ThrottledLogger, run
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    tips_reliability_param,
    with_reliability,
)
from soft_gripper_sdre.nodes.topics import (
    CLOCK,
    CLOCK_QOS,
    DIAGNOSTICS,
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    STREAM_QOS,
    TIP_POSITIONS,
    TOPIC_TYPES,
    TORQUE_COMMANDS,
    type_name,
)

#: topics of the 1 kHz control loop (LOOP_QOS); /clock has CLOCK_QOS, the plan REFERENCE_QOS (a
#: recorder that starts after the plan went out still gets it), the rest STREAM_QOS
LOOP_TOPICS = (TIP_POSITIONS, STATE_ESTIMATE, TORQUE_COMMANDS)
#: a stamp further than this from the latest /clock is not the current sim time
SKEW_NS = 1_000_000_000
#: messages held back while waiting for the first /clock, at most
MAX_PENDING = 10_000
#: wall time [s] messages are held back waiting for the first /clock, at most
CLOCK_WAIT_S = 120.0
#: topics stamped with wall time in a sim-time graph too: they do not show the graph's time
WALL_TIME_TOPICS = (DIAGNOSTICS, '/rosout')
#: how often the graph is looked at for publishers of the topics not yet subscribed [s]
GRAPH_POLL_S = 0.1
#: queue of each recording subscription: 1 s of a 1 kHz topic, so a recorder that falls behind for
#: a moment (a busy machine) catches up instead of losing the oldest messages
RECORD_DEPTH = 1000
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
#: a stamp step over this many periods is a gap: the periods it skipped are lost messages
GAP_FACTOR = 1.5
#: stamp steps the period is the median of, and how many a stream needs before it is judged
PERIOD_WINDOW = 64
PERIOD_LEARN = 8
#: a stamp step over both of these [s] and [periods], and over JUMP_RATIO times the time between
#: the two messages' arrivals, is a jump (a clock set forward, a bad stamp), not lost messages:
#: the stream starts afresh from it
JUMP_SECONDS = 1.0
JUMP_PERIODS = 100
JUMP_RATIO = 10.0


class GapCounter:
    """Messages missing from one stream, from the stamps [ns] of the messages that arrived.

    The nominal period is the median of the last ``PERIOD_WINDOW`` positive stamp steps, first
    taken after ``PERIOD_LEARN`` of them (a loss before that is not seen) and taken again every
    ``PERIOD_WINDOW // 2`` steps, so a stream that changes its rate is followed (one that slows
    down counts losses until the window holds the new rate, at most ``PERIOD_WINDOW`` steps). A
    step over
    ``GAP_FACTOR`` periods counts ``round(step / period) - 1`` lost messages (at least one). A
    repeated stamp is ignored; a stamp before the previous one (a restarted publisher) starts the
    stream afresh from it, keeping its period. A step over both ``JUMP_SECONDS`` and
    ``JUMP_PERIODS`` periods that is also over ``JUMP_RATIO`` times the time between the two
    messages' arrivals (when ``received`` is given) ran ahead of time itself (a clock set
    forward, a bad stamp): it is counted in :attr:`jumps` instead of as losses, and the stream
    starts afresh from it, its period learned again.
    """

    def __init__(self) -> None:
        self.last: int | None = None            # the newest stamp [ns]
        self.period: float | None = None        # the learned period [ns]
        self.lost = 0                           # messages lost in all
        self.gaps = 0                           # steps that lost messages
        self.jumps = 0                          # steps forward too long to be losses
        self.jumped = False                     # whether the last step was one
        self.received: int | None = None        # the newest message's arrival [ns]
        self._steps: deque = deque(maxlen=PERIOD_WINDOW)
        self._since = 0                         # steps since the period was taken

    def add(self, stamp: int, received: int | None = None) -> int:
        """Take the next message's stamp [ns] (and its arrival on any steady clock [ns], if
        known); the number of messages lost just before it."""
        last, self.last = self.last, stamp
        arrived, self.received = self.received, received
        self.jumped = False
        if last is None or stamp <= last:
            return 0
        step = stamp - last
        if (self.period is not None and step > JUMP_SECONDS * 1e9
                and step > JUMP_PERIODS * self.period
                and (received is None or arrived is None
                     or step > JUMP_RATIO * (received - arrived))):
            self.jumps += 1
            self.jumped = True
            self.period = None
            self._steps.clear()
            self._since = 0
            return 0
        lost = 0
        if self.period is not None and step > GAP_FACTOR * self.period:
            lost = max(1, round(step / self.period) - 1)
            self.lost += lost
            self.gaps += 1
        self._steps.append(step)
        self._since += 1
        if ((self.period is None and len(self._steps) >= PERIOD_LEARN)
                or self._since >= PERIOD_WINDOW // 2):
            self.period = float(statistics.median(self._steps))
            self._since = 0
        return lost

    def restart(self) -> None:
        """Forget the newest stamp (another publisher came or went): judge from the next one."""
        self.last = None

PARAMS = (
    Param('output', '', 'bag directory to create; must not exist yet '
          "('' = rosbag2_<date>-<time> in the working directory)", read_only=True),
    Param('topics', list(TOPIC_TYPES), 'topics to record: names of the topic table, or any other '
          '(namespaced, remapped, your own), subscribed with the type the graph reports once a '
          'publisher appears', read_only=True),
    Param('storage', 'mcap', 'rosbag2 storage plugin', choices=tuple(STORAGES), read_only=True),
    Param('discard_without', '', 'at exit, remove the bag if this recorded topic got no message '
          "(a run that never started; e.g. torque_commands); '' = keep every bag", read_only=True),
    tips_reliability_param(),
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


def adapted_qos(offers: list[QoSProfile]) -> QoSProfile:
    """The QoS ``ros2 bag record`` subscribes with to publishers offering ``offers``: reliable if
    every one offers reliable, else best effort; transient local if every one offers it, else
    volatile; a queue of ``RECORD_DEPTH``."""
    reliable = all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    latched = all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    reliability = ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT
    durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RECORD_DEPTH, reliability=reliability,
                      durability=durability)


def message_class(type_name: str):
    """The message class of 'pkg/msg/Type'.

    Raises:
        ValueError: not a message type name, or its package is not installed.
    """
    parts = type_name.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        raise ValueError(f'{type_name!r} is not a message type')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2])
    except (ImportError, AttributeError):
        raise ValueError(f'message type {type_name} is not installed') from None


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
    """The bag directory named by the ``output`` parameter; refuses an existing or unwritable
    path."""
    path = Path(value
                or datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')).expanduser().absolute()
    if path.exists():
        raise ParameterError(f"parameter 'output': {path} already exists "
                             "(a bag is never overwritten)")
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not (parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)):
        raise ParameterError(f"parameter 'output': cannot create {path}: "
                             f"{parent} is not a writable directory")
    return path


class RecorderNode(Node):
    """Record topics of the graph into a rosbag2 (MCAP) directory (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('recorder', **kwargs)
        p = declare_all(self, PARAMS)
        names = list(p['topics'])
        if not names:
            raise ParameterError("parameter 'topics': name at least one topic")
        known: dict[str, str] = {}                # resolved name -> key of TOPIC_TYPES
        self._waiting: list[str] = []             # resolved names of the other topics
        for name in names:
            topic = find_topic(name)
            try:
                resolved = self.resolve_topic_name(topic or name.strip())
            except Exception as exc:            # noqa: BLE001 — rclpy raises its RCLError here
                raise ParameterError(f"parameter 'topics': {name!r} is not a topic name: "
                                     f'{str(exc).splitlines()[0]}') from None
            if resolved in known or resolved in self._waiting:
                continue
            if topic is None:
                self._waiting.append(resolved)
            else:
                known[resolved] = topic
        self.discard_without = None              # resolved name, if recorded
        if p['discard_without'].strip():
            try:
                wanted = self.resolve_topic_name(find_topic(p['discard_without'])
                                                 or p['discard_without'].strip())
            except Exception as exc:            # noqa: BLE001 — rclpy raises its RCLError here
                raise ParameterError(f"parameter 'discard_without': {p['discard_without']!r} is "
                                     f'not a topic name: {str(exc).splitlines()[0]}') from None
            if wanted in known or wanted in self._waiting:
                self.discard_without = wanted
        self.path = _output_path(p['output'])
        self._writer: Writer | None = Writer(self.path, version=Writer.VERSION_LATEST,
                                             storage_plugin=STORAGES[p['storage']])
        try:
            self._writer.open()
        except (OSError, WriterError) as exc:
            raise ParameterError(f"parameter 'output': cannot create bag {self.path}: "
                                 f"{exc}") from None

        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self.counts: dict[str, int] = {}
        self.clock_ns: int | None = None          # latest /clock value
        # held until the first /clock; None once flushed, or from the start without /clock
        self._pending: list[tuple] | None = [] if CLOCK in known.values() else None
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        self._subs: dict = {}
        #: per stamped topic, the messages missing from its stream; judged while it has one
        #: publisher (``_single``, refreshed with the matched counts)
        self.gaps: dict[str, GapCounter] = {}
        self._single: dict[str, bool] = {}
        self._lost_reported = 0                 # messages lost at the previous /diagnostics
        self._jumps_reported = 0                # stamp jumps at the previous /diagnostics
        self._loss_warn = False                 # the WARN in /diagnostics is the losses'
        self._own_reports = 0                   # marked reports of its own still to leave out
        self.diag.before_publish.append(self._report_losses)
        tips_qos = with_reliability(LOOP_QOS, p['tips_reliability'])
        for name, topic in known.items():
            qos = tips_qos if topic == TIP_POSITIONS else topic_qos(topic)
            self._record(name, TOPIC_TYPES[topic], qos, is_clock=topic == CLOCK)
        self.diag.values['output'] = str(self.path)
        self._matched_timer = self.create_timer(0.2, self._report_publishers)
        self._graph_timer = self.create_timer(GRAPH_POLL_S, self._look_at_graph)
        self.diag.set_status(OK, f'recording {len(known) + len(self._waiting)} topics')
        waiting = (f'; once a publisher appears: {", ".join(self._waiting)}' if self._waiting
                   else '')
        self.get_logger().info(f'recording {", ".join(self.counts) or "nothing yet"}{waiting} to '
                               f'{self.path} ({p["storage"]})')

    def _record(self, name: str, msg_class, qos: QoSProfile, is_clock: bool = False) -> None:
        """Add ``name`` (resolved) to the bag and subscribe it with ``qos``, deeper."""
        conn = self._writer.add_connection(name, type_name(msg_class), typestore=self._typestore,
                                           offered_qos_profiles=[_bag_qos(qos)])
        self.counts[name] = 0
        stamped = _is_stamped(msg_class)
        if stamped and name not in WALL_TIME_TOPICS:
            self.gaps[name] = GapCounter()
            self.diag.counters[f'lost {name}'] = 0
        callback = functools.partial(self._on_message, name, conn, stamped, is_clock)
        deep = copy.copy(qos)
        deep.depth = RECORD_DEPTH           # history depth is not part of QoS matching
        self._subs[name] = self.create_subscription(msg_class, name, callback, deep, raw=True)

    def _look_at_graph(self) -> None:
        """Subscribe each topic not in the table once a publisher of it is in the graph, with the
        type it reports and the QoS adapted to the offers; also give up holding messages back for
        a /clock that does not come within ``CLOCK_WAIT_S``."""
        if (self._pending and self.clock_ns is None
                and time.time_ns() - self._pending[0][2] > CLOCK_WAIT_S * 1e9):
            self.get_logger().info(f'no /clock within {CLOCK_WAIT_S:g} s: writing the messages '
                                   'with their own stamps')
            self._flush_pending()
        if self._writer is None or not self._waiting:
            return
        for name in list(self._waiting):
            offers = self.get_publishers_info_by_topic(name)
            if not offers:
                continue
            types = sorted({o.topic_type for o in offers})
            if len(types) > 1:
                self.log.warn(f'types {name}', f'{name}: publishers of several types '
                              f'({", ".join(types)}); not recording it until they agree')
                continue
            self._waiting.remove(name)
            try:
                msg_class = message_class(types[0])
                self._record(name, msg_class, adapted_qos([o.qos_profile for o in offers]))
            except (ValueError, KeyError, WriterError) as exc:
                self.diag.problem('unrecordable_topics', f'{name} ({types[0]}) cannot be '
                                  f'recorded: {exc}')
                continue
            qos = self._subs[name].qos_profile
            self.get_logger().info(f'recording {name} ({types[0]}, {qos.reliability.name.lower()}, '
                                   f'{qos.durability.name.lower()})')

    def _report_publishers(self) -> None:
        """Matched publishers per topic in /diagnostics ('publishers /topic'), so a supervisor
        can start the simulator only once everything it records is connected."""
        for name, sub in self._subs.items():
            count = sub.get_publisher_count()
            self.diag.values[f'publishers {name}'] = str(count)
            single = count <= 1
            if name in self.gaps and single != self._single.get(name, True):
                self.gaps[name].restart()
            self._single[name] = single
        for name in self._waiting:
            self.diag.values[f'publishers {name}'] = '0'

    # -- receiving ---------------------------------------------------------------------------
    def _on_message(self, topic: str, conn, stamped: bool, is_clock: bool, data: bytes) -> None:
        """Write one serialized message; never raises (bad input is counted and logged)."""
        if self._writer is None:
            return
        if self._own_reports and topic == DIAGNOSTICS and self._is_own_report(data):
            return
        try:
            stamp = cdr.leading_stamp(data) if stamped else None
            if is_clock and stamp is not None:
                self.clock_ns = stamp
            self.counts[topic] += 1
            self.diag.count(f'messages {topic}')
            if self.counts[topic] == 1:
                self._report_now(topic)
            gaps = self.gaps.get(topic)
            if gaps is not None and stamp is not None and self._single.get(topic, True):
                before = gaps.last
                lost = gaps.add(stamp, time.monotonic_ns())
                if lost:
                    self._lost(topic, gaps, lost, before, stamp)
                elif gaps.jumped:
                    self.diag.count(f'jumps {topic}')
                    self.log.warn(f'jump {topic}', f'{topic}: stamps jumped forward from '
                                  f'{before / 1e9:.6f} to {stamp / 1e9:.6f} s, far more than '
                                  'the time that passed (a clock set forward or a bad stamp): '
                                  f'not counted as lost; {gaps.jumps} such jump(s) of this topic')
            wall_ns = time.time_ns()
            if self._pending is None:
                self._write(conn, self._entry_time(stamp, wall_ns), data)
                return
            self._pending.append((conn, stamp, wall_ns, data))
            wall_time_graph = (stamp is not None and topic not in WALL_TIME_TOPICS
                               and abs(stamp - wall_ns) <= SKEW_NS)
            if self.clock_ns is not None or len(self._pending) >= MAX_PENDING or wall_time_graph:
                self._flush_pending()
        except Exception as exc:  # noqa: BLE001 — a recorder must survive anything it receives
            self.diag.count('errors')
            self.log.warn('receive', f'{topic}: message not recorded: {exc!r}')

    def _report_now(self, topic: str) -> None:
        """Publish /diagnostics at once, marked ``report: first <topic>`` (module doc)."""
        self.diag.values['report'] = f'first {topic}'
        self.diag.publish()
        del self.diag.values['report']
        if DIAGNOSTICS in self.counts:
            self._own_reports += 1

    def _is_own_report(self, data: bytes) -> bool:
        """Whether ``data`` is one of this node's marked reports (then it is not recorded)."""
        msg = deserialize_message(data, DiagnosticArray)
        own = any(status.name == self.get_fully_qualified_name()
                  and any(kv.key == 'report' for kv in status.values) for status in msg.status)
        self._own_reports -= own
        return own

    def _lost(self, topic: str, gaps: GapCounter, lost: int, before: int, stamp: int) -> None:
        """Count ``lost`` messages of ``topic`` missing between the stamps ``before`` and
        ``stamp`` [ns], and warn (throttled per topic)."""
        self.diag.count(f'lost {topic}', lost)
        self.log.warn(f'lost {topic}', f'{topic}: {lost} message(s) missing between stamps '
                      f'{before / 1e9:.6f} and {stamp / 1e9:.6f} s (period '
                      f'{gaps.period / 1e6:.3f} ms); {gaps.lost} lost of this topic in all')

    def _report_losses(self) -> None:
        """Before each /diagnostics: the learned periods, and WARN naming the topics while their
        losses or stamp jumps grow (OK again after a report without a new one; an ERROR
        stays)."""
        for name, gaps in self.gaps.items():
            if gaps.period is not None:
                self.diag.values[f'period {name}'] = f'{gaps.period / 1e6:.3f} ms'
        total = sum(g.lost for g in self.gaps.values())
        jumps = sum(g.jumps for g in self.gaps.values())
        new_lost, new_jumps = total - self._lost_reported, jumps - self._jumps_reported
        if (new_lost or new_jumps) and self.diag.level != ERROR:
            said = []
            if new_lost:
                topics = ', '.join(f'{name} {g.lost}' for name, g in self.gaps.items() if g.lost)
                said.append(f'{new_lost} message(s) lost since the last report; lost in all: '
                            f'{topics}')
            if new_jumps:
                topics = ', '.join(f'{name} {g.jumps}' for name, g in self.gaps.items()
                                   if g.jumps)
                said.append(f'{new_jumps} stamp jump(s) over {JUMP_SECONDS:g} s since the last '
                            'report, far ahead of the time that passed (a clock set forward or '
                            f'a bad stamp); in all: {topics}')
            self.diag.set_status(WARN, '; '.join(said))
            self._loss_warn = True
        elif self._loss_warn and self.diag.level == WARN:
            self.diag.set_status(OK, f'recording {len(self._subs) + len(self._waiting)} topics; '
                                 f'{total} message(s) lost earlier'
                                 + (f' and {jumps} stamp jump(s)' if jumps else '')
                                 + ', none since the last report')
            self._loss_warn = False
        self._lost_reported, self._jumps_reported = total, jumps

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
        logger = (self.get_logger() if self.context.ok()
                  else rclpy.logging.get_logger('soft_gripper_sdre'))
        try:
            writer.close()
        except (OSError, WriterError) as exc:
            logger.error(f'closing {self.path} failed: {exc}')
            return
        if self.discard_without is not None and not self.counts.get(self.discard_without):
            shutil.rmtree(self.path, ignore_errors=True)
            logger.warning(f'removed {self.path}: no message of {self.discard_without} (a run '
                           f'that never started; {sum(self.counts.values())} other message(s)); '
                           "set discard_without to '' to keep such a bag")
            return
        logger.info(f'wrote {sum(self.counts.values())} messages to {self.path}')
        lost = {name: g for name, g in self.gaps.items() if g.lost}
        if lost:
            logger.warning('messages missing from the streams (stamp gaps): ' + ', '.join(
                f'{name} {g.lost} in {g.gaps} gap(s)' for name, g in lost.items()))
        jumped = {name: g.jumps for name, g in self.gaps.items() if g.jumps}
        if jumped:
            logger.warning('stamps jumped forward (not counted as lost): ' + ', '.join(
                f'{name} {n} time(s)' for name, n in jumped.items()))


def main(args=None) -> int:
    return run(RecorderNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
