"""The grasp plan's CDR codec (nodes/plan_cdr.py): our bytes are rclpy's message, rclpy's bytes are
read the fast way, and anything else goes the slow, validating way with the slow result."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.plan_cdr import PlanCodec

MS = 1_000_000
CODECS = {n: PlanCodec(n) for n in (1, 4)}


def plan(n, points, seed=0):
    rng = np.random.default_rng(seed)
    offsets = 5 * MS * np.arange(points, dtype=np.int64)
    return (offsets, *(rng.standard_normal((points, n, 2)) * 10.0 ** rng.integers(-6, 3)
                       for _ in range(3)))


def same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize('n', [1, 4])
@pytest.mark.parametrize('points', [1, 2, 3, 1101])
def test_our_bytes_are_the_message_built_the_slow_way_and_read_back_exactly(n, points):
    codec = CODECS[n]
    offsets, pos, vel, acc = plan(n, points)
    for ns in (0, 7 * cv.NS + 123):
        data = codec.encode(ns, offsets, pos, vel, acc)
        msg = cv.reference_to_msg(ns, offsets, pos, vel, acc)
        assert deserialize_message(data, MultiDOFJointTrajectory) == msg
        back = codec.decode(data)
        assert same(back, (ns, ns + offsets, pos, vel, acc))
        assert same(back, cv.msg_to_reference(msg, n))
        assert same(codec.decode(serialize_message(msg)), back)   # rclpy's bytes, whatever padding
    assert codec.fallbacks == 0


def _slow(n, msg):
    try:
        return cv.msg_to_reference(msg, n)
    except cv.MessageError as exc:
        return str(exc)


def _decoded(codec, data):
    try:
        return codec.decode(data)
    except cv.MessageError as exc:
        return str(exc)


def _variants(n):
    """Messages of another shape or content, as another publisher might send them."""
    offsets, pos, vel, acc = plan(n, 4)
    out = {}
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.joint_names = list(reversed(m.joint_names))
    out['names reversed'] = m
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.header.frame_id = 'hand'
    out['a frame_id'] = m
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.points[2].velocities = m.points[2].velocities[:-1]
    out['an entry missing'] = m
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.points[1].transforms[0].translation.y = float('nan')
    out['NaN'] = m
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.points[3].time_from_start = m.points[1].time_from_start
    out['times not increasing'] = m
    m = cv.reference_to_msg(0, offsets, pos, vel, acc)
    m.points = []
    out['no points'] = m
    return out


@pytest.mark.parametrize('n', [1, 4])
def test_other_messages_give_what_the_validating_conversion_gives(n):
    codec = CODECS[n]
    for name, msg in _variants(n).items():
        got, want = _decoded(codec, serialize_message(msg)), _slow(n, msg)
        assert (got == want) if isinstance(want, str) else same(got, want), name
    assert 'NaN or Inf' in _decoded(codec, serialize_message(_variants(n)['NaN']))


def test_bytes_that_are_not_a_plan_are_a_message_error_naming_the_topic():
    codec = CODECS[4]
    data = codec.encode(0, *plan(4, 5))
    for bad in (b'', b'\x00\x01\x00\x00', data[:len(data) // 2], bytes(range(256)) * 4):
        with pytest.raises(cv.MessageError, match='grasp_reference'):
            codec.decode(bad)
