"""Serialized CDR bytes of the per-period loop messages, read and written at fixed offsets.

rclpy builds a Python object for every nested message it deserializes, which makes the loop
topics costly to receive. The loop's messages never change shape from one period to the next:
only the stamp and a few float64 fields move. So each loop topic gets a :class:`Layout` learned at
start-up from a template message that rclpy itself serializes, and a period then costs a
comparison of the structural bytes and a gather (decode) or scatter (encode) at fixed offsets.

A message matches a layout when it has the template's length and the same structural bytes (the
encapsulation header, counts, strings, fields outside the slots); the stamp, the slots and the
alignment padding may hold anything. Anything else (another publisher's name order, a different
frame_id, more points, big-endian CDR, …) goes the slow way: ``deserialize_message`` and the
``msg_to_*`` conversion with all its checks (:class:`LoopCodec`). Both ways end in the same
finiteness check, with the same error message.

Another publisher sends every message in its own shape: a motion-capture system stamps its tips
with its own frame_id, a driver lists the fingers in its own order. So the first message of a shape
that decoded the slow way teaches the codec that shape too (at most :data:`MAX_ADOPTED` of them):
a layout is learned from a copy of that very message whose stamp and slots are refilled (values
written to the entry of the finger they belong to), and the following messages of that shape
decode fast, in our finger order.

The bytes we publish are the template with the padding zeroed and the slots filled: valid CDR of
the declared type, so ``ros2 topic echo``, rosbag2 and typed subscribers are unaffected.

The byte layouts of the four loop messages, and how :meth:`Layout.learn` finds them without an
offset derived by hand, are in docs/design/cdr.md.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
import math
import operator
import os
import struct
import sys
from typing import Callable

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.topics import CLOCK, STATE_ESTIMATE, TIP_POSITIONS, TORQUE_COMMANDS

#: CDR encapsulation header: 2 bytes representation id (00 01 = CDR little-endian), 2 bytes
#: options; CDR aligns every primitive to its size relative to the byte after it
HEADER = 4
#: builtin_interfaces/Time = int32 sec, uint32 nanosec, little-endian
_STAMP = struct.Struct('<iI')
#: the template's stamp (sec, nanosec), distinct from anything else in the bytes
_SENTINEL_STAMP = (0x5A5A_1234, 0x3B9A_C9FF)       # 1 515 852 340 s, 999 999 999 ns
#: layouts a codec learns from other publishers' messages, and attempts to learn one, at most
MAX_ADOPTED, MAX_ADOPT_ATTEMPTS = 4, 8


def _sentinels(count: int) -> np.ndarray:
    """``count`` distinct float64s whose bit patterns occur nowhere else in a template."""
    return -1234.5 - np.arange(count) * 0.0078125 * np.pi


@dataclass(frozen=True)
class Layout:
    """Where the stamp and the float64 slots of a fixed-shape message sit in its CDR bytes.

    Build with :meth:`learn`. ``template`` holds the padding zeroed; ``mask`` is 0xFF on the
    structural bytes and 0 on the stamp, the slots and the padding.

    A period's message is read and written with the standard library alone, since numpy's call
    overhead on a few dozen bytes is what a loop node pays most of its codec time for: the
    structural bytes are compared as the few runs they form, the slots are read by one
    :class:`struct.Struct` in byte order and put in slot order by an ``itemgetter``, and a
    message is written into one buffer kept for the layout, so one thread at a time encodes
    (docs/design/cdr.md).
    """

    msg_type: type
    template: bytes
    mask: np.ndarray              # (size,) uint8
    stamp_at: int                 # byte offset of the stamp's sec (its nanosec follows)
    slots: np.ndarray             # (m,) index of each slot among the float64 words after HEADER
    shape: tuple[int, ...]        # shape of the slot values
    slack_size: int               # length of rclpy's own serialization (with its slack)

    def __post_init__(self) -> None:
        structural = np.append(self.mask == 0xFF, False).astype(np.int8)
        edges = np.flatnonzero(np.diff(np.append(0, structural)))     # run starts and ends
        runs = tuple((int(a), int(b), self.template[a:b]) for a, b in edges.reshape(-1, 2))
        order = np.argsort(self.slots, kind='stable')       # the slots in byte order
        fmt, end = '<', HEADER
        for at in (HEADER + 8 * self.slots[order]).tolist():      # skip to each slot, read it
            fmt += f'{at - end}xd' if at > end else 'd'
            end = at + 8
        values = struct.Struct(fmt)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        # (one slot or none: struct's tuple is already in slot order)
        pick = operator.itemgetter(*rank.tolist()) if len(rank) > 1 else (lambda t: t)
        buf = bytearray(self.template)
        words = np.frombuffer(buf, '<f8', count=(len(buf) - HEADER) // 8, offset=HEADER)
        for name, value in (('_runs', runs), ('_values', values), ('_pick', pick),
                            ('_buf', buf), ('_words', words)):
            object.__setattr__(self, name, value)

    @classmethod
    def learn(cls, msg_type: type, build: Callable[[int, np.ndarray], object],
              shape: tuple[int, ...]) -> 'Layout':
        """The layout of ``build(ns, values)`` (values of ``shape``), as rclpy serializes it.

        Raises:
            ValueError: a sentinel is not found exactly once at an aligned place, or the learned
                layout does not round-trip (the message has no fixed layout).
        """
        values = _sentinels(int(np.prod(shape))).reshape(shape)
        sec, nanosec = _SENTINEL_STAMP
        msg = build(sec * cv.NS + nanosec, values)
        raw = serialize_message(msg)
        name = msg_type.__name__
        stamp_at = _find_once(raw, _STAMP.pack(sec, nanosec), 4, f'{name} stamp')
        slots = np.array([(_find_once(raw, struct.pack('<d', v), 8, f'{name} slot {i}') - HEADER)
                          // 8 for i, v in enumerate(values.ravel().tolist())], dtype=np.intp)
        moving = np.zeros(len(raw), dtype=bool)
        moving[stamp_at:stamp_at + _STAMP.size] = True
        for s in slots:
            moving[HEADER + 8 * s:HEADER + 8 * s + 8] = True
        with _quiet_stderr():       # the typesupport prints a line for each count it cannot read
            ignored = np.array([not moving[i] and _ignored(raw, i, msg, msg_type)
                                for i in range(len(raw))])
        # rclpy's buffer may end in slack the deserializer ignores; rmw sends typed messages
        # without it, so the layout ends at the last byte that is read (typed and raw then match)
        size = int(np.flatnonzero(~ignored)[-1]) + 1
        size += -(size - HEADER) % 4            # an RTPS payload is whole 4-byte words
        ignored = ignored[:size]
        moving = moving[:size]
        mask = np.where(moving | ignored, 0, 0xFF).astype(np.uint8)
        template = bytes(np.frombuffer(raw[:size], np.uint8)
                         & np.where(ignored, 0, 0xFF).astype(np.uint8))
        layout = cls(msg_type, template, mask, stamp_at, slots, tuple(shape), len(raw))
        if deserialize_message(layout.encode(sec * cv.NS + nanosec, values), msg_type) != msg:
            raise ValueError(f'{name}: the learned layout does not reproduce the template')
        return layout

    def read(self, data: bytes) -> tuple[int, tuple[float, ...]] | None:
        """(stamp ns, the slot values flat in slot order) of ``data``, or None when it does not
        match."""
        if len(data) != len(self.template) and len(data) != self.slack_size:   # rmw's or rclpy's
            return None
        for a, b, run in self._runs:
            if data[a:b] != run:
                return None
        sec, nanosec = _STAMP.unpack_from(data, self.stamp_at)
        return sec * cv.NS + nanosec, self._pick(self._values.unpack_from(data, HEADER))

    def decode(self, data: bytes) -> tuple[int, np.ndarray] | None:
        """(stamp ns, slot values of ``shape``) of ``data``, or None when it does not match."""
        got = self.read(data)
        if got is None:
            return None
        return got[0], np.array(got[1], dtype=float).reshape(self.shape)

    def encode(self, ns: int, values: np.ndarray) -> bytes:
        """The CDR bytes of the message stamped ``ns`` with slot ``values`` (of ``shape``)."""
        _STAMP.pack_into(self._buf, self.stamp_at, *divmod(int(ns), cv.NS))
        self._words[self.slots] = np.ravel(values)
        return bytes(self._buf)


def leading_stamp(data: bytes) -> int | None:
    """The leading stamp [ns] of the CDR bytes of any stamped message (its header's or Clock's
    time comes first), in either byte order; None if too short or negative (the recorder's
    index)."""
    if len(data) < HEADER + _STAMP.size:
        return None
    # byte 1: 1 = LE
    sec, nanosec = struct.unpack_from('<iI' if data[1] & 1 else '>iI', data, HEADER)
    ns = sec * cv.NS + nanosec
    return ns if ns >= 0 else None


def _find_once(raw: bytes, pattern: bytes, align: int, what: str) -> int:
    """The one offset of ``pattern`` in ``raw`` that is ``align``-aligned after the header."""
    at = raw.find(pattern)
    if at < 0 or raw.count(pattern) != 1 or (at - HEADER) % align:
        raise ValueError(f'{what}: the sentinel occurs {raw.count(pattern)} times '
                         f'(first at byte {at}); expected once, {align}-aligned after the header')
    return at


def _ignored(raw: bytes, i: int, msg, msg_type: type) -> bool:
    """Whether the deserializer ignores byte ``i`` of ``raw``: flipped, the message is the same."""
    flipped = bytearray(raw)
    flipped[i] ^= 0xFF
    try:
        return deserialize_message(bytes(flipped), msg_type) == msg
    except Exception:     # rclpy raises its RMWError (no public class) for bytes that do not parse
        return False


@contextlib.contextmanager
def _quiet_stderr():
    """File descriptor 2 on /dev/null for the duration (C++ writes there, not to sys.stderr)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, 'wb') as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class LoopCodec:
    """One loop topic's message ↔ (stamp, values), fast when the bytes match a layout.

    ``to_msg(ns, values)`` builds the message the slow way (and is the template of the layout);
    ``from_msg(msg)`` is the validating ``msg_to_*`` conversion used when the bytes do not match;
    ``finite_what`` names the values in the error for NaN/Inf, as ``from_msg`` does.
    ``refill(msg, ns, values)``, if given, writes a stamp and values (in our order) into a
    message of another publisher's shape, in place: the first such message that decodes the slow
    way then teaches the codec its layout (module doc). ``fallbacks`` counts the messages decoded
    the slow way.
    """

    def __init__(self, topic: str, msg_type: type, to_msg: Callable[[int, np.ndarray], object],
                 from_msg: Callable[[object], tuple[int, np.ndarray]], shape: tuple[int, ...],
                 finite_what: str | None,
                 refill: Callable[[object, int, np.ndarray], None] | None = None) -> None:
        self.topic = topic
        self.msg_type = msg_type
        self.layout = Layout.learn(msg_type, to_msg, shape)
        self.adopted: list[Layout] = []     # layouts learned from other publishers' messages
        self.from_msg = from_msg
        self._finite_what = finite_what
        self._refill = refill
        self._adopt_attempts = 0
        self.fallbacks = 0

    def encode(self, ns: int, values: np.ndarray) -> bytes:
        return self.layout.encode(ns, values)

    def decode(self, data: bytes) -> tuple[int, np.ndarray]:
        """(stamp ns, values) of serialized ``data``.

        Raises:
            conversions.MessageError: as ``from_msg`` would, or the bytes are not a message of
                the type at all.
        """
        fast = self.layout.read(data)
        for layout in self.adopted:
            if fast is not None:
                break
            fast = layout.read(data)
        if fast is None:
            self.fallbacks += 1
            try:
                msg = deserialize_message(data, self.msg_type)
            except Exception:      # rclpy's RMWError: not CDR of this type
                raise cv.MessageError(f'{self.topic}: {len(data)} bytes that do not deserialize as '
                                      f'{self.msg_type.__name__}') from None
            stamp, values = self.from_msg(msg)
            if (self._refill is not None and len(self.adopted) < MAX_ADOPTED
                    and self._adopt_attempts < MAX_ADOPT_ATTEMPTS):
                self._adopt(data, stamp, values)
            return stamp, values
        stamp, flat = fast
        values = np.array(flat, dtype=float).reshape(self.layout.shape)
        if self._finite_what is not None and not all(map(math.isfinite, flat)):
            cv.check_finite(values, self._finite_what)
        return stamp, values

    def _adopt(self, data: bytes, stamp: int, values: np.ndarray) -> None:
        """Learn the layout of ``data`` (a well-formed message of another shape), keeping it only
        if it reads ``data`` exactly as the slow way did."""
        self._adopt_attempts += 1

        def build(ns: int, slot_values: np.ndarray):
            msg = deserialize_message(data, self.msg_type)
            self._refill(msg, ns, slot_values)
            return msg

        try:
            layout = Layout.learn(self.msg_type, build, values.shape)
        except ValueError:          # no fixed layout (e.g. a value equal to a sentinel)
            return
        fast = layout.decode(data)
        if fast is not None and fast[0] == stamp and np.array_equal(fast[1], values):
            self.adopted.append(layout)


# -- the loop topics -------------------------------------------------------------------------

def tips_codec(fingers: cv.Fingers) -> LoopCodec:
    """``tip_positions``: (n, 3) tip positions [m], pose i = finger i; orientations and frame_id
    are ours when we publish and anything fixed when another publisher does."""
    n = len(cv.finger_names(fingers))
    return LoopCodec(TIP_POSITIONS, cv.PoseArray, cv.tips_to_msg, lambda m: cv.msg_to_tips(m, n),
                     (n, 3), cv.TIPS_WHAT, refill=cv.fill_tips)


def estimate_codec(fingers: cv.Fingers, d: int = 2) -> LoopCodec:
    """``state_estimate``: (n, 2d) [p; ṗ] of tips of task dimension ``d`` ([X, Y, Ẋ, Ẏ] with
    z = 0 for d = 2; [X, Y, Z, Ẋ, Ẏ, Ż] for d = 3); joint names = the finger names (decoded in
    our order whatever the publisher's), one point."""
    names = cv.finger_names(fingers)

    def refill(msg, ns: int, x: np.ndarray) -> None:
        cv.set_time(msg.header.stamp, ns)
        point = msg.points[0]
        for name, row in zip(names, x.tolist()):
            j = msg.joint_names.index(name)
            t, v = point.transforms[j].translation, point.velocities[j].linear
            if d == 2:
                t.x, t.y, v.x, v.y = row
            else:
                t.x, t.y, t.z, v.x, v.y, v.z = row

    return LoopCodec(STATE_ESTIMATE, cv.MultiDOFJointTrajectory,
                     lambda ns, x: cv.estimate_to_msg(ns, x[:, :d], x[:, d:], names),
                     lambda m: cv.msg_to_estimate(m, names, d), (len(names), 2 * d),
                     cv.ESTIMATE_WHAT, refill=refill)


def torques_codec(fingers: cv.Fingers, m: int = 2) -> LoopCodec:
    """``torque_commands``: (n, m) efforts [N·m, or each input's SI unit] named
    ``<finger>/ax0`` … ``<finger>/ax<m−1>`` (decoded in our order whatever the publisher's)."""
    names = cv.finger_names(fingers)
    torques = cv.torque_names(names, m)

    def refill(msg, ns: int, u: np.ndarray) -> None:
        cv.set_time(msg.header.stamp, ns)
        effort = list(msg.effort)
        for name, value in zip(torques, u.ravel().tolist()):
            effort[list(msg.name).index(name)] = value
        msg.effort = effort

    return LoopCodec(TORQUE_COMMANDS, cv.JointState, lambda ns, u: cv.torques_to_msg(ns, u, names),
                     lambda msg: cv.msg_to_torques(msg, names, m), (len(names), m),
                     cv.TORQUES_WHAT, refill=refill)


def clock_codec() -> LoopCodec:
    """``/clock``: the stamp only (values are an empty array)."""
    return LoopCodec(CLOCK, cv.Clock, lambda ns, _v: cv.clock_msg(ns),
                     lambda m: (cv.from_time(m.clock), np.empty(0)), (0,), None)


def watch(diag, *codecs: LoopCodec) -> None:
    """Report in ``diag`` (a :class:`~soft_gripper_sdre.nodes.common.Diagnostics`) how many
    messages ``codecs`` decoded the slow way, as the value ``slow_decodes`` (0 while every
    message comes from our own nodes)."""
    def refresh() -> None:
        diag.values['slow_decodes'] = str(sum(c.fallbacks for c in codecs))
    diag.before_publish.append(refresh)
