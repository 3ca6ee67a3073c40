"""The raw CDR codec of the loop topics (nodes/cdr.py): valid bytes out, strict fast path in, the
slow path (deserialize_message + msg_to_*) for everything that does not match exactly."""
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from rosutil import Probe, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.topics import LOOP_QOS, STATE_ESTIMATE, TIP_POSITIONS, TORQUE_COMMANDS

NS = 7 * cv.NS + 123_456_789


def _codecs(n):
    """(codec, slow builder, slow reader, value shape) of each loop topic for n fingers."""
    return {
        'tips': (cdr.tips_codec(n), cv.tips_to_msg, lambda m: cv.msg_to_tips(m, n), (n, 3)),
        'estimate': (cdr.estimate_codec(n),
                     lambda ns, x: cv.estimate_to_msg(ns, x[:, :2], x[:, 2:]),
                     lambda m: cv.msg_to_estimate(m, n), (n, 4)),
        'torques': (cdr.torques_codec(n), cv.torques_to_msg, lambda m: cv.msg_to_torques(m, n),
                    (n, 2)),
        'clock': (cdr.clock_codec(), lambda ns, _v: cv.clock_msg(ns),
                  lambda m: (cv.from_time(m.clock), np.empty(0)), (0,)),
    }


CODECS = {n: _codecs(n) for n in (1, 4)}
CASES = [(n, topic) for n in (1, 4) for topic in CODECS[n]]


NOT_CDR = 'not CDR of the type'


def _slow(codec, data):
    """What the slow path alone makes of ``data``: the values, the MessageError text or NOT_CDR."""
    try:
        msg = deserialize_message(data, codec.msg_type)
    except Exception:                           # rclpy's RMWError
        return NOT_CDR
    try:
        return codec.from_msg(msg)
    except cv.MessageError as exc:
        return str(exc)


def _decoded(codec, data):
    """What the codec makes of ``data``, in the terms of :func:`_slow`."""
    try:
        return codec.decode(data)
    except cv.MessageError as exc:
        return NOT_CDR if 'do not deserialize' in str(exc) else str(exc)


def _same(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return a[0] == b[0] and np.array_equal(a[1], b[1])


@pytest.mark.parametrize('n, topic', CASES)
def test_our_bytes_are_the_message_built_the_slow_way_and_read_back_exactly(n, topic):
    codec, build, read, shape = CODECS[n][topic]
    rng = np.random.default_rng(n)
    for ns in (0, 1, NS, (2**31 - 1) * cv.NS + 999_999_999):
        values = rng.standard_normal(shape) * 10.0 ** rng.integers(-6, 6)
        data = codec.encode(ns, values)
        assert isinstance(data, bytes)
        assert deserialize_message(data, codec.msg_type) == build(ns, values)
        stamp, back = codec.decode(data)
        assert stamp == ns and np.array_equal(back, values)
        assert _same((stamp, back), read(build(ns, values)))
        # the layout writes into a buffer it keeps: bytes handed out earlier stay as they were
        assert codec.encode(ns ^ 1, values + 1.0) != data
        assert codec.decode(data)[0] == ns and np.array_equal(codec.decode(data)[1], values)
    assert codec.fallbacks == 0


@pytest.mark.parametrize('n, topic', CASES)
def test_rclpy_serialized_messages_take_the_fast_path_whatever_their_padding(n, topic):
    """rclpy leaves padding bytes uninitialised: they must not matter."""
    codec, build, read, shape = CODECS[n][topic]
    before = codec.fallbacks
    values = np.random.default_rng(3).standard_normal(shape)
    data = serialize_message(build(NS, values))
    assert _same(codec.decode(data), read(build(NS, values)))
    assert codec.fallbacks == before
    layout = codec.layout
    padding = [i for i in range(len(layout.template)) if layout.mask[i] == 0
               and not _in_slot(layout, i)]
    for i in padding:                         # any value in a padding byte: still fast and the same
        junk = bytearray(codec.encode(NS, values))
        junk[i] ^= 0xA5
        assert _same(codec.decode(bytes(junk)), (NS, values))
    assert codec.fallbacks == before


def _in_slot(layout, i) -> bool:
    if layout.stamp_at <= i < layout.stamp_at + 8:
        return True
    return (i - cdr.HEADER) // 8 in set(layout.slots.tolist()) and i >= cdr.HEADER


@pytest.mark.parametrize('n, topic', CASES)
def test_any_changed_structural_byte_goes_the_slow_way_with_the_slow_result(n, topic):
    codec, _, _, shape = CODECS[n][topic]
    data = codec.encode(NS, np.full(shape, 0.25))
    structural = np.flatnonzero(codec.layout.mask)
    assert structural.size > 0
    for i in structural:
        bad = bytearray(data)
        bad[i] ^= 0x01
        before = codec.fallbacks
        assert _same(_decoded(codec, bytes(bad)), _slow(codec, bytes(bad))), f'byte {i}'
        assert codec.fallbacks == before + 1, f'byte {i} was not checked'
    longer = data + bytes(12)                 # trailing bytes the deserializer ignores
    before = codec.fallbacks
    assert _same(_decoded(codec, longer), _slow(codec, longer)) and codec.fallbacks == before + 1
    with pytest.raises(cv.MessageError, match='do not deserialize'):
        codec.decode(data[:-1])


def test_messages_of_another_shape_are_read_by_the_validating_conversions():
    c = CODECS[4]
    tips, _, read_tips, _ = c['tips']
    est, _, read_est, _ = c['estimate']
    torques, _, read_torques, _ = c['torques']
    rng = np.random.default_rng(5)
    t = rng.standard_normal((4, 3))
    other_frame = cv.tips_to_msg(NS, t, frame_id='world')
    turned = cv.tips_to_msg(NS, t)
    turned.poses[2].orientation.z = 1.0
    five = cv.tips_to_msg(NS, np.vstack([t, t[:1]]))
    reordered = cv.torques_to_msg(NS, rng.standard_normal((4, 2)))
    reordered.name = reordered.name[2:] + reordered.name[:2]
    x = rng.standard_normal((4, 4))
    lifted = cv.estimate_to_msg(NS, x[:, :2], x[:, 2:])
    lifted.points[0].transforms[1].translation.z = 0.5
    renamed = cv.estimate_to_msg(NS, x[:, :2], x[:, 2:])
    renamed.joint_names = list(reversed(renamed.joint_names))
    two_points = cv.estimate_to_msg(NS, x[:, :2], x[:, 2:])
    two_points.points = two_points.points * 2
    cases = [(tips, read_tips, other_frame), (tips, read_tips, turned), (tips, read_tips, five),
             (torques, read_torques, reordered), (est, read_est, lifted), (est, read_est, renamed),
             (est, read_est, two_points)]
    for codec, read, msg in cases:
        before = codec.fallbacks
        try:
            expected = read(msg)
        except cv.MessageError as exc:
            expected = str(exc)
        assert _same(_decoded(codec, serialize_message(msg)), expected)
        assert codec.fallbacks == before + 1
    assert _decoded(tips, serialize_message(five)) == 'tip_positions: expected 4 poses, got 5'
    assert _decoded(est, serialize_message(two_points)) == 'state_estimate: expected 1 point, got 2'


@pytest.mark.parametrize('topic', ['tips', 'estimate', 'torques'])
def test_non_finite_values_are_refused_on_the_fast_path_with_the_slow_paths_words(topic):
    codec, build, read, shape = CODECS[4][topic]
    for bad in (np.nan, np.inf, -np.inf):
        values = np.zeros(shape)
        values[-1, 1] = bad
        data = codec.encode(NS, values)
        with pytest.raises(cv.MessageError) as fast:
            codec.decode(data)
        with pytest.raises(cv.MessageError) as slow:
            read(build(NS, values))
        assert str(fast.value) == str(slow.value) and 'NaN or Inf' in str(fast.value)


def test_bytes_that_are_not_the_type_are_a_message_error_naming_the_topic():
    codec = CODECS[4]['tips'][0]
    for junk in (b'', b'\x00\x01', b'\x00\x01\x00\x00' + b'\xff' * 40):
        with pytest.raises(cv.MessageError,
                           match=r'^tip_positions: \d+ bytes that do not deserialize'):
            codec.decode(junk)


def test_a_message_without_a_fixed_layout_is_refused_when_learned():
    # the same values twice: a sentinel lands at two places
    with pytest.raises(ValueError, match='slot 0: the sentinel occurs 2 times'):
        cdr.Layout.learn(PoseArray, lambda ns, v: cv.tips_to_msg(ns, np.vstack([v, v])), (2, 3))


@pytest.mark.ros
def test_raw_bytes_over_dds_reach_typed_subscribers_and_typed_messages_take_the_fast_path():
    c = CODECS[4]
    topics = {TIP_POSITIONS: ('tips', PoseArray),
              STATE_ESTIMATE: ('estimate', MultiDOFJointTrajectory),
              TORQUE_COMMANDS: ('torques', JointState), 'clock_test': ('clock', Clock)}
    values = {name: np.random.default_rng(9).standard_normal(c[name][3])
              for name, _ in topics.values()}
    with ros_context() as (ctx, executor):
        typed, raw = Probe(ctx, 'typed'), Probe(ctx, 'raw')
        pubs_raw, pubs_typed, got_raw, subs = {}, {}, {}, []
        for topic, (name, msg_type) in topics.items():
            subs.append(typed.listen(msg_type, topic, LOOP_QOS))
            got_raw[topic] = []
            subs.append(raw.create_subscription(msg_type, topic, got_raw[topic].append, LOOP_QOS,
                                                raw=True))
            pubs_raw[topic] = raw.create_publisher(msg_type, topic, LOOP_QOS)
            pubs_typed[topic] = typed.create_publisher(msg_type, topic, LOOP_QOS)
        executor.add_node(typed)
        executor.add_node(raw)
        # both ends of every pair matched (a reader that has not yet matched its writer drops
        # what the writer already sends it): eight writers' discovery on a loaded machine
        assert spin_until(executor,
                          lambda: all(p.get_subscription_count() == 2
                                      for p in (*pubs_raw.values(), *pubs_typed.values()))
                          and all(s.get_publisher_count() == 2 for s in subs), 30.0)
        for topic, (name, _) in topics.items():
            codec, build, _, _ = c[name]
            pubs_raw[topic].publish(codec.encode(NS, values[name]))       # our bytes
            pubs_typed[topic].publish(build(NS + 1, values[name]))        # rmw's serialization
        assert spin_until(executor, lambda: all(len(typed.received[t]) == 2 and len(got_raw[t]) == 2
                                                for t in topics), 10.0)
        for topic, (name, _) in topics.items():
            codec, build, _, _ = c[name]
            assert typed.received[topic][0] == build(NS, values[name])
            before = codec.fallbacks
            for data, ns in zip(got_raw[topic], (NS, NS + 1)):
                stamp, back = codec.decode(data)
                assert stamp == ns and np.array_equal(back, values[name])
            assert codec.fallbacks == before, f'{topic}: rmw bytes did not take the fast path'
