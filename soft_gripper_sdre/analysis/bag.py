"""Read rosbag2 recordings of the graph (the recorder's or ``ros2 bag record``'s) into arrays.

Core module: rosbags only, no rclpy. Messages are deserialised with the types embedded in the bag,
falling back to rosbags' Jazzy typestore. Topic names may be given without the leading '/'; a
namespaced recording ('/sim/tip_positions') is found by its last name component if unambiguous.

:func:`extract_run` turns one run into SI arrays on each topic's own time axis (header stamps, sim
time, seconds); malformed messages (wrong sizes or names — the recorder keeps whatever was sent)
are skipped and counted. The finger's shape comes from the run: its m inputs from the command
names ``<finger>/ax<k>``, its task dimension d from the estimates (3 when any estimate carries a
z, which a planar estimator leaves 0).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import functools
from pathlib import Path
import re

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError
from rosbags.typesys import Stores, get_typestore

from soft_gripper_sdre import FINGER_NAMES

NS = 1_000_000_000
TIP_POSITIONS = 'tip_positions'
STATE_ESTIMATE = 'state_estimate'
GRASP_REFERENCE = 'grasp_reference'
TORQUE_COMMANDS = 'torque_commands'
CUBE_CONTACTS = 'cube_contacts'
CUBE_POSE = 'cube_pose'
JOINT_STATES = 'joint_states'
#: topics :func:`extract_run` needs; cube_contacts and cube_pose are optional (finger scene)
REQUIRED_TOPICS = (TIP_POSITIONS, STATE_ESTIMATE, GRASP_REFERENCE, TORQUE_COMMANDS)


class BagError(ValueError):
    """A bag is missing, unreadable or lacks what is asked of it; the message names the path."""


@dataclass(frozen=True)
class Series:
    """Samples of one topic: ``t`` (T,) sim time [s] from header stamps, ``values`` (T, …) SI."""

    t: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class Run:
    """One recorded run as arrays (see :func:`extract_run`)."""

    tips: Series                 # (T, n, d) tip X, Y (, Z) [m] in each finger's base frame
    estimate: Series             # (T, n, 2d) X, Y (, Z) [m], Ẋ, Ẏ (, Ż) [m/s]
    torques: Series              # (T, n, m) commanded u_ax0 … u_ax<m−1> [N·m or the input's unit]
    reference: Series            # on the tip times: (T, n, 2d) p_d [m], ṗ_d [m/s]
    contacts: Series | None      # (T, n) normal force of each finger on the cube [N]
    cube_pose: Series | None     # (T, 7) x, y, z [m], qx, qy, qz, qw
    joints: Series | None = None  # (T, n, 2, 10) each finger's joint angles [rad] and rates [rad/s]
    counts: dict[str, int] = field(default_factory=dict)    # messages per topic in the bag
    skipped: dict[str, int] = field(default_factory=dict)   # malformed messages per topic
    finger_names: tuple[str, ...] = ()   # the fingers, in the order of every array's finger axis

    @property
    def n_fingers(self) -> int:
        return self.tips.values.shape[1]

    @property
    def task_dim(self) -> int:
        """The tips' task dimension d."""
        return self.tips.values.shape[2]

    @property
    def n_inputs(self) -> int:
        """The inputs m of each finger."""
        return self.torques.values.shape[2]


class _Malformed(ValueError):
    """A message does not have the expected shape (skipped and counted)."""


def _open(path: str | Path) -> AnyReader:
    path = Path(path)
    if not (path / 'metadata.yaml').is_file() and not path.is_file():
        what = ('does not exist' if not path.exists()
                else 'is not a rosbag2 directory (no metadata.yaml)')
        raise BagError(f'bag {path} {what}')
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
    except (AnyReaderError, ReaderError, OSError) as exc:
        raise BagError(f'bag {path} cannot be read: {exc}') from None


def topic_counts(path: str | Path) -> dict[str, int]:
    """Messages per topic, from the bag's metadata.

    Raises:
        BagError: the bag is missing or unreadable.
    """
    reader = _open(path)
    try:
        with reader:
            return {name: int(info.msgcount) for name, info in sorted(reader.topics.items())}
    except (AnyReaderError, ReaderError, OSError) as exc:
        raise BagError(f'bag {path} cannot be read: {exc}') from None


def read_bag(path: str | Path,
             topics: list[str] | None = None) -> dict[str, list[tuple[int, object]]]:
    """Deserialised messages per topic as ``(bag timestamp ns, message)`` in bag order.

    Args:
        path: rosbag2 directory.
        topics: only these topics (with or without the leading '/'); default all.

    Raises:
        BagError: the bag is missing or unreadable, or a requested topic is not in it.
    """
    reader = _open(path)
    try:
        with reader:
            names = list(reader.topics) if topics is None else [_resolve(path, reader.topics, t)
                                                                 for t in topics]
            out: dict[str, list[tuple[int, object]]] = {name: [] for name in names}
            conns = [c for c in reader.connections if c.topic in out]
            for conn, timestamp, raw in reader.messages(connections=conns):
                out[conn.topic].append((timestamp, reader.deserialize(raw, conn.msgtype)))
            return out
    except (AnyReaderError, ReaderError, OSError) as exc:
        raise BagError(f'bag {path} cannot be read: {exc}') from None


def _matches(available, name: str) -> list[str]:
    """The bag's topics ``name`` may mean: exact, with a leading '/', else by last component."""
    for candidate in (name, '/' + name.lstrip('/')):
        if candidate in available:
            return [candidate]
    base = name.rstrip('/').rsplit('/', 1)[-1]
    return [t for t in available if t.rsplit('/', 1)[-1] == base]


def _resolve(path, available, name: str) -> str:
    """The bag's topic meant by ``name``; BagError if none or several."""
    matches = _matches(available, name)
    if len(matches) == 1:
        return matches[0]
    what = f'several topics match {name!r}: {matches}' if matches else f'no topic {name!r}'
    raise BagError(f'bag {path}: {what} (topics: {", ".join(sorted(available)) or "none"})')


# -- message → array parsers (rosbags message objects) ---------------------------------------

def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * NS + int(msg.header.stamp.nanosec)


def _order(names, expected: list[str]) -> list[int]:
    names = list(names)
    if sorted(names) != sorted(expected):
        raise _Malformed(f'names {names[:4]} are not {expected[:4]}')
    return [names.index(n) for n in expected]


def _tips(msg, names: tuple[str, ...], d: int = 2) -> np.ndarray:
    n = len(names)
    if len(msg.poses) != n:
        raise _Malformed(f'{len(msg.poses)} poses, expected {n}')
    if d == 2:
        return np.array([(p.position.x, p.position.y) for p in msg.poses], dtype=float)
    return np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses], dtype=float)


def _torques(msg, names: tuple[str, ...], m: int = 2) -> np.ndarray:
    torques = [f'{name}/ax{a}' for name in names for a in range(m)]
    if len(msg.effort) != len(msg.name):
        raise _Malformed('names and efforts differ in length')
    return np.asarray(msg.effort, dtype=float)[_order(msg.name, torques)].reshape(len(names), m)


_INPUT_NAME = re.compile(r'(.+)/ax(\d+)')


def _inputs(messages, names: tuple[str, ...]) -> int:
    """The inputs m per finger of the first command whose names are ``<finger>/ax<k>`` of
    ``names`` with k = 0 … m−1 for every finger (2, the hand's, when none is)."""
    for _, msg in messages:
        found = [_INPUT_NAME.fullmatch(name) for name in msg.name]
        if not found or not all(found):
            continue
        per: dict[str, set[int]] = {}
        for match in found:
            per.setdefault(match.group(1), set()).add(int(match.group(2)))
        counts = {len(ks) for ks in per.values()}
        if set(per) == set(names) and len(counts) == 1:
            m = counts.pop()
            if all(ks == set(range(m)) for ks in per.values()):
                return m
    return 2


def _planar(messages) -> bool:
    """No state_estimate carries a z (position or velocity): the estimator's tips are planar."""
    return not any(tf.translation.z != 0.0 or tw.linear.z != 0.0
                   for _, msg in messages for pt in msg.points[:1]
                   for tf, tw in zip(pt.transforms, pt.velocities))


def _contacts(msg, names: tuple[str, ...]) -> np.ndarray:
    if len(msg.effort) != len(msg.name):
        raise _Malformed('names and efforts differ in length')
    return np.asarray(msg.effort, dtype=float)[_order(msg.name, list(names))]


def _points(msg, names: tuple[str, ...], d: int = 2) -> np.ndarray:
    """(h, n, 2d) [p; ṗ] of every point of a MultiDOFJointTrajectory ([X, Y, Ẋ, Ẏ] for d = 2)."""
    n = len(names)
    idx = _order(msg.joint_names, list(names))
    if not msg.points:
        raise _Malformed('no points')
    out = []
    for pt in msg.points:
        if len(pt.transforms) != n or len(pt.velocities) != n:
            raise _Malformed('a point does not hold one entry per finger')
        if d == 2:
            out.append([(pt.transforms[j].translation.x, pt.transforms[j].translation.y,
                         pt.velocities[j].linear.x, pt.velocities[j].linear.y) for j in idx])
        else:
            out.append([(pt.transforms[j].translation.x, pt.transforms[j].translation.y,
                         pt.transforms[j].translation.z, pt.velocities[j].linear.x,
                         pt.velocities[j].linear.y, pt.velocities[j].linear.z) for j in idx])
    return np.asarray(out, dtype=float)


def _estimate(msg, names: tuple[str, ...], d: int = 2) -> np.ndarray:
    points = _points(msg, names, d)
    if len(points) != 1:
        raise _Malformed(f'{len(points)} points, expected 1')
    return points[0]


def _horizon(msg, names: tuple[str, ...], d: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Absolute point times [ns] (h,) and states (h, n, 2d) of a reference horizon."""
    stamp = _stamp(msg)
    times = np.array([stamp + int(pt.time_from_start.sec) * NS + int(pt.time_from_start.nanosec)
                      for pt in msg.points], dtype=np.int64)
    points = _points(msg, names, d)
    if np.any(np.diff(times) <= 0):
        raise _Malformed('point times are not increasing')
    return times, points


def _joints(msg, names: tuple[str, ...]) -> np.ndarray:
    """(n, 2, 10): angles and rates of ``<finger>/joint_j``, in that order whatever the
    message's."""
    per, n = 10, len(names)
    expected = [f'{name}/joint_{j}' for name in names for j in range(per)]
    idx = _order(msg.name, expected)
    q, qd = np.asarray(msg.position, dtype=float), np.asarray(msg.velocity, dtype=float)
    if len(q) != len(msg.name) or len(qd) != len(msg.name):
        raise _Malformed('joint_states: position/velocity lengths differ from the names')
    out = np.stack([q[idx], qd[idx]]).reshape(2, n, per).transpose(1, 0, 2)
    if not np.all(np.isfinite(out)):
        raise _Malformed('joint_states: non-finite values')
    return out


def _cube_pose(msg, names: tuple[str, ...]) -> np.ndarray:
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=float)


def _collect(messages, parse, names: tuple[str, ...], skipped: dict[str, int],
             topic: str) -> tuple[np.ndarray, list]:
    """Stamps [ns] and parsed values of the well-formed messages, sorted by stamp."""
    stamps, values = [], []
    for _, msg in messages:
        try:
            values.append(parse(msg, names))
        except _Malformed:
            skipped[topic] = skipped.get(topic, 0) + 1
            continue
        stamps.append(_stamp(msg))
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind='stable')
    return np.asarray(stamps, dtype=np.int64)[order], [values[i] for i in order]


def sample_reference(t_ns: np.ndarray, ref_stamps: np.ndarray,
                     horizons: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The reference in force at each time ``t_ns``: (T, n, 2d), NaN before the first message.

    For each time the latest message stamped at or before it is used; its points are interpolated
    linearly between the two whose absolute times bracket the time (held at the horizon's end).
    """
    n, k = horizons[0][1].shape[1:] if horizons else (0, 4)
    out = np.full((len(t_ns), n, k), np.nan)
    which = np.searchsorted(ref_stamps, t_ns, side='right') - 1
    for m in np.unique(which[which >= 0]):
        rows = np.flatnonzero(which == m)
        times, points = horizons[m]
        flat = points.reshape(len(times), -1)
        out[rows] = np.stack([np.interp(t_ns[rows], times, flat[:, c])
                              for c in range(flat.shape[1])], axis=1).reshape(len(rows), n, k)
    return out


def extract_run(path: str | Path) -> Run:
    """One run of the graph from a bag, as arrays (shapes in :class:`Run`).

    The number of fingers n comes from the first tip_positions message with poses, their names
    from the first state_estimate message with n joint names (finger_0.. if there is none), the
    inputs m from the first command named ``<finger>/ax0`` … ``<finger>/ax<m−1>`` (2 if none is),
    the task dimension d from the estimates (3 when any carries a z). The reference is sampled at
    the tip times by :func:`sample_reference`.

    Raises:
        BagError: the bag is missing or unreadable, lacks one of :data:`REQUIRED_TOPICS`, or holds
            no well-formed message on one of them.
    """
    counts = topic_counts(path)
    missing = [t for t in REQUIRED_TOPICS if len(_matches(counts, t)) != 1]
    if missing:
        raise BagError(f'bag {path} lacks topic(s) {", ".join(missing)} '
                       f'(has: {", ".join(counts) or "none"})')
    wanted = list(REQUIRED_TOPICS) + [t for t in (CUBE_CONTACTS, CUBE_POSE, JOINT_STATES)
                                      if len(_matches(counts, t)) == 1]
    messages = read_bag(path, wanted)
    by_name = {t: messages[_resolve(path, counts, t)] for t in wanted}
    n = next((len(m.poses) for _, m in by_name[TIP_POSITIONS] if len(m.poses) > 0), 0)
    if not 0 < n <= len(FINGER_NAMES):
        raise BagError(f'bag {path}: no usable tip_positions message')
    names = next((tuple(m.joint_names) for _, m in by_name[STATE_ESTIMATE]
                  if len(m.joint_names) == n), FINGER_NAMES[:n])
    skipped: dict[str, int] = {}

    def collect(topic: str, parse) -> tuple[np.ndarray, list]:
        stamps, values = _collect(by_name[topic], parse, names, skipped, topic)
        if not values:
            raise BagError(f'bag {path}: no well-formed {topic} message')
        return stamps, values

    def series(topic: str, parse) -> Series | None:
        if topic not in by_name:
            return None
        stamps, values = collect(topic, parse)
        return Series(stamps / NS, np.asarray(values))

    d = 2 if _planar(by_name[STATE_ESTIMATE]) else 3
    m = _inputs(by_name[TORQUE_COMMANDS], names)
    tip_ns, tips = collect(TIP_POSITIONS, functools.partial(_tips, d=d))
    ref_ns, horizons = collect(GRASP_REFERENCE, functools.partial(_horizon, d=d))
    return Run(tips=Series(tip_ns / NS, np.asarray(tips)),
               estimate=series(STATE_ESTIMATE, functools.partial(_estimate, d=d)),
               torques=series(TORQUE_COMMANDS, functools.partial(_torques, m=m)),
               reference=Series(tip_ns / NS, sample_reference(tip_ns, ref_ns, horizons)),
               contacts=series(CUBE_CONTACTS, _contacts), cube_pose=series(CUBE_POSE, _cube_pose),
               joints=series(JOINT_STATES, _joints), counts=counts, skipped=skipped,
               finger_names=names)
