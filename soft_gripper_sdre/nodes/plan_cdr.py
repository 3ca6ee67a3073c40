"""The grasp plan (``grasp_reference``) as CDR bytes written and read with numpy.

The plan is one ``trajectory_msgs/MultiDOFJointTrajectory`` holding the whole grasp: about a
thousand points of four fingers. rclpy builds and walks a Python object for every transform and
twist in it, a few hundred milliseconds for each of building, serializing and deserializing one;
a controller blocked that long misses hundreds of periods. Here the bytes are written and read
point by point with ``struct`` and numpy instead, following the CDR rules (little-endian,
primitives aligned to their size counted from the byte after the 4-byte encapsulation header).

:class:`PlanCodec` checks itself when it is made: the bytes it writes for a small plan must
deserialize (rclpy) to the message :func:`~soft_gripper_sdre.nodes.conversions.reference_to_msg`
builds, and its reading of rclpy's bytes must agree with
:func:`~soft_gripper_sdre.nodes.conversions.msg_to_reference`. Messages it does not read the fast
way (another joint order, another frame_id, big-endian CDR, a point with a different number of
entries, …) go the slow, validating way, as in :mod:`soft_gripper_sdre.nodes.cdr`.
"""
from __future__ import annotations

import struct

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE

HEADER = b'\x00\x01\x00\x00'          # CDR, little-endian, no options
_U32 = struct.Struct('<I')
_TIME = struct.Struct('<iI')
#: float64 words of one entry: Transform = translation (3) + rotation (4); Twist = linear + angular
TRANSFORM_WORDS, TWIST_WORDS = 7, 6
WHAT = 'grasp_reference'


def _pad(offset: int, align: int) -> int:
    """Bytes of padding before a primitive of size ``align`` at payload ``offset``."""
    return -offset % align


class PlanCodec:
    """A plan of the fingers ``fingers`` (names, or a count for finger_0..) with tips of task
    dimension ``d`` (2: X, Y with z = 0; 3: X, Y, Z) ↔ CDR bytes of its MultiDOFJointTrajectory
    (module doc).

    ``fallbacks`` counts the messages read the slow way.

    Raises:
        ValueError: at construction, if the self-check against rclpy's serialization fails.
    """

    def __init__(self, fingers: cv.Fingers, d: int = 2) -> None:
        self.names = list(cv.finger_names(fingers))
        self.n = len(self.names)
        if d not in (2, 3):
            raise ValueError(f'{GRASP_REFERENCE}: the task dimension must be 2 or 3, got {d!r}')
        self.d = d
        self.fallbacks = 0
        prefix, padding = bytearray(), []   # frame_id '' and the joint names, after the stamp
        fields = [_U32.pack(1) + b'\x00', _U32.pack(len(self.names))]
        fields += [_U32.pack(len(name) + 1) + name.encode() + b'\x00' for name in self.names]
        for field in fields:                  # each starts with a 4-byte length or count
            pad = _pad(_TIME.size + len(prefix), 4)
            padding += range(len(prefix), len(prefix) + pad)
            prefix += bytes(pad) + field
        mask = np.full(len(prefix), 0xFF, dtype=np.uint8)
        mask[padding] = 0                     # rclpy leaves padding uninitialised
        self._prefix = bytes(prefix)
        self._prefix_mask = mask
        self._self_check()

    # -- writing -----------------------------------------------------------------------------
    def encode(self, ns: int, offsets_ns: np.ndarray, pos: np.ndarray, vel: np.ndarray,
               acc: np.ndarray) -> bytes:
        """The bytes of :func:`~soft_gripper_sdre.nodes.conversions.reference_to_msg` for the
        same arguments: stamp ``ns``, points at ``offsets_ns`` after it, pos/vel/acc (h, n, 2|3)."""
        pos, vel, acc = (_xyz(a, self.n) for a in (pos, vel, acc))
        h = len(offsets_ns)
        transforms = np.zeros((h, self.n, TRANSFORM_WORDS))
        transforms[..., :3] = pos
        transforms[..., 6] = 1.0                      # identity rotation (w)
        twists = np.zeros((2, h, self.n, TWIST_WORDS))
        twists[0, ..., :3] = vel
        twists[1, ..., :3] = acc
        out = bytearray(HEADER)
        out += _TIME.pack(*divmod(int(ns), cv.NS)) + self._prefix
        offset = len(out) - len(HEADER)
        out += bytes(_pad(offset, 4)) + _U32.pack(h)
        for k in range(h):
            for block in (transforms[k], twists[0, k], twists[1, k]):
                offset = len(out) - len(HEADER)
                out += bytes(_pad(offset, 4)) + _U32.pack(self.n)
                offset = len(out) - len(HEADER)
                out += bytes(_pad(offset, 8)) + block.astype('<f8').tobytes()
            offset = len(out) - len(HEADER)
            out += bytes(_pad(offset, 4)) + _TIME.pack(*divmod(int(offsets_ns[k]), cv.NS))
        return bytes(out)

    # -- reading -----------------------------------------------------------------------------
    def decode(self, data: bytes) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(stamp ns, times ns (h,), pos, vel, acc (h, n, d)) of serialized ``data``.

        Raises:
            conversions.MessageError: as
                :func:`~soft_gripper_sdre.nodes.conversions.msg_to_reference` would, or the bytes
                are not a MultiDOFJointTrajectory at all.
        """
        fast = self._read(data)
        if fast is None:
            self.fallbacks += 1
            try:
                msg = deserialize_message(data, cv.MultiDOFJointTrajectory)
            except Exception:      # rclpy's RMWError: not CDR of this type
                raise cv.MessageError(f'{WHAT}: {len(data)} bytes that do not deserialize as '
                                      'MultiDOFJointTrajectory') from None
            return cv.msg_to_reference(msg, self.names, self.d)
        stamp, times, transforms, velocities, accelerations = fast
        if np.any(np.diff(times) <= 0):
            raise cv.MessageError(f'{WHAT}: point times are not increasing')
        d = self.d
        values = np.concatenate([transforms[..., :d], velocities[..., :d],
                                 accelerations[..., :d]], axis=2)
        cv.check_finite(values, WHAT)
        return stamp, times, values[..., 0:d], values[..., d:2 * d], values[..., 2 * d:3 * d]

    def _read(self, data: bytes):
        """The stamp, point times and (h, n, words) blocks of ``data``, or None when it is not a
        little-endian plan of our frame_id, joint names and n entries per point."""
        start = len(HEADER) + _TIME.size
        end_prefix = start + len(self._prefix)
        if len(data) < end_prefix + 4 or data[:2] != HEADER[:2]:
            return None
        got = np.frombuffer(data, np.uint8, count=len(self._prefix), offset=start)
        if not np.array_equal(got & self._prefix_mask, np.frombuffer(self._prefix, np.uint8)):
            return None
        sec, nanosec = _TIME.unpack_from(data, len(HEADER))
        stamp = sec * cv.NS + nanosec
        at = end_prefix + _pad(end_prefix - len(HEADER), 4)
        (h,) = _U32.unpack_from(data, at)
        at += 4
        if h == 0 or h > (len(data) - at) // 8:
            return None
        sizes = (TRANSFORM_WORDS, TWIST_WORDS, TWIST_WORDS)
        blocks = [np.empty((h, self.n, words)) for words in sizes]
        times = np.empty(h, dtype=np.int64)
        n = self.n
        for k in range(h):
            for block, words in zip(blocks, sizes):
                at += _pad(at - len(HEADER), 4)
                if at + 4 > len(data) or _U32.unpack_from(data, at)[0] != n:
                    return None
                at += 4
                at += _pad(at - len(HEADER), 8)
                count = n * words
                if at + 8 * count > len(data):
                    return None
                block[k] = np.frombuffer(data, '<f8', count=count, offset=at).reshape(n, words)
                at += 8 * count
            at += _pad(at - len(HEADER), 4)
            if at + _TIME.size > len(data):
                return None
            sec, nanosec = _TIME.unpack_from(data, at)
            times[k] = stamp + sec * cv.NS + nanosec
            at += _TIME.size
        if len(data) - at >= 8:              # more than the slack a serializer may leave
            return None
        return stamp, times, blocks[0], blocks[1], blocks[2]

    def _self_check(self) -> None:
        """Our bytes are rclpy's message and our reading of rclpy's bytes is the slow one."""
        rng = np.random.default_rng(0)
        offsets = np.array([0, 5_000_000, 1_000_000_123], dtype=np.int64)
        pos, vel, acc = (rng.standard_normal((3, self.n, self.d)) for _ in range(3))
        ns = 7 * cv.NS + 123
        msg = cv.reference_to_msg(ns, offsets, pos, vel, acc, self.names)
        ours = self.encode(ns, offsets, pos, vel, acc)
        theirs = serialize_message(msg)
        read = self._read(theirs)
        slow = cv.msg_to_reference(msg, self.names, self.d)
        if (deserialize_message(ours, cv.MultiDOFJointTrajectory) != msg or read is None
                or self._read(ours) is None
                or not all(np.array_equal(a, b) for a, b in zip(self.decode(theirs), slow))):
            raise ValueError(f'{GRASP_REFERENCE}: the plan codec does not reproduce rclpy\'s '
                             'serialization of MultiDOFJointTrajectory')


def _xyz(a: np.ndarray, n: int) -> np.ndarray:
    """(h, n, 3) of (h, n, 2|3) values (z = 0 when absent)."""
    a = np.asarray(a, dtype=float)
    if a.shape[-1] == 2:
        a = np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)
    return a
