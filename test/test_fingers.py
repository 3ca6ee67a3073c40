"""Any number of named fingers through the graph, other publishers' message shapes on the fast
CDR path, and the controller's Float64MultiArray output in ros2_control's layout (real rclpy,
real DDS, real processes)."""
import importlib

from node_harness import MS, commands, make_controller, send_estimate
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_system_default
from rclpy.serialization import serialize_message
from rosutil import Probe, overrides, ros_context, spin_until
from std_msgs.msg import Float64MultiArray

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import ParameterError

NAMES = ('left', 'right', 'thumb')
#: a forward_command_controller's topic, and its joints (as the torques that drive them)
EFFORT_TOPIC = '/gripper_effort_controller/commands'
EFFORT_JOINTS = ['right/ax1', 'left/ax0', 'right/ax0', 'left/ax1']


# -- the raw CDR path with other publishers' shapes ----------------------------------------

def test_another_finger_order_decodes_fast_after_its_first_message_in_our_order():
    codec = cdr.estimate_codec(NAMES)
    theirs = ['thumb', 'left', 'right']          # another publisher's joint order
    rng = np.random.default_rng(1)
    for k in range(6):
        x = rng.standard_normal((3, 4))            # in our order
        perm = [NAMES.index(n) for n in theirs]
        msg = cv.estimate_to_msg(k * MS, x[perm, :2], x[perm, 2:], theirs)
        stamp, got = codec.decode(serialize_message(msg))
        assert stamp == k * MS and np.array_equal(got, x)
        assert codec.fallbacks == 1                 # only the first message went the slow way
    assert len(codec.adopted) == 1


def test_torques_in_another_name_order_decode_fast_after_the_first():
    codec = cdr.torques_codec(NAMES)
    rng = np.random.default_rng(2)
    for k in range(4):
        u = rng.standard_normal((3, 2))
        msg = cv.torques_to_msg(k * MS, u, NAMES)
        msg.name, msg.effort = msg.name[::-1], list(msg.effort)[::-1]
        stamp, got = codec.decode(serialize_message(msg))
        assert stamp == k * MS and np.array_equal(got, u)
    assert codec.fallbacks == 1


def test_tips_of_a_mocap_frame_id_decode_fast_after_the_first():
    codec = cdr.tips_codec(len(NAMES))
    rng = np.random.default_rng(3)
    for k in range(4):
        tips = rng.standard_normal((3, 3))
        msg = cv.tips_to_msg(k * MS, tips, frame_id='mocap_world')
        msg.poses[1].orientation.z, msg.poses[1].orientation.w = 0.6, 0.8   # a fixed mount
        stamp, got = codec.decode(serialize_message(msg))
        assert stamp == k * MS and np.array_equal(got, tips)
    assert codec.fallbacks == 1
    ours = codec.encode(5 * MS, np.zeros((3, 3)))
    assert codec.decode(ours)[0] == 5 * MS and codec.fallbacks == 1


def test_shapes_beyond_the_adoption_limit_stay_slow_and_correct():
    codec = cdr.tips_codec(2)
    tips = np.array([[0.01, 0.02, 0.0], [0.03, 0.04, 0.0]])
    frames = [f'frame_{i}' for i in range(cdr.MAX_ADOPTED + 2)]
    for frame in frames * 2:
        assert np.array_equal(codec.decode(serialize_message(cv.tips_to_msg(MS, tips, frame)))[1],
                              tips)
    assert len(codec.adopted) == cdr.MAX_ADOPTED
    assert codec.fallbacks == len(frames) + 2       # the last two shapes, both times


def test_a_bad_message_of_an_adopted_shape_is_refused_as_on_the_slow_path():
    codec = cdr.estimate_codec(NAMES)
    theirs = list(reversed(NAMES))
    x = np.zeros((3, 4))
    codec.decode(serialize_message(cv.estimate_to_msg(0, x[:, :2], x[:, 2:], theirs)))
    x[1, 3] = np.nan
    with pytest.raises(cv.MessageError, match='state_estimate contains NaN'):
        codec.decode(serialize_message(cv.estimate_to_msg(MS, x[:, :2], x[:, 2:], theirs)))
    assert codec.fallbacks == 1


# -- names and the effort order ------------------------------------------------------------

@pytest.mark.parametrize('names, needle', [
    ([], '1 to 4 names'), ([f'f{i}' for i in range(5)], '1 to 4 names'), (['a', 'a'], 'distinct'),
    (['left', 'x/y'], "'x/y' is not a valid finger name"), (['9'], 'not a valid finger name')])
def test_bad_finger_names_are_named(names, needle):
    assert needle in cv.finger_names_problem(names)


def test_effort_order_maps_each_joint_to_its_torque():
    order = cv.effort_array_order(EFFORT_JOINTS, ('left', 'right'))
    u = np.array([[1.0, 2.0], [3.0, 4.0]])           # left ax0, ax1; right ax0, ax1
    assert u.ravel()[order].tolist() == [4.0, 1.0, 3.0, 2.0]
    for joints, needle in [(EFFORT_JOINTS[:3], 'no joint carries left/ax1'),
                           (EFFORT_JOINTS + ['left/ax0'], "'left/ax0' appears more than once"),
                           (['finger_0/ax0'] + EFFORT_JOINTS[1:],
                            "'finger_0/ax0' is not a torque")]:
        with pytest.raises(ValueError, match=needle):
            cv.effort_array_order(joints, ('left', 'right'))


# -- the controller's Float64MultiArray output -----------------------------------------------

@pytest.mark.ros
def test_float64_multi_array_holds_the_joint_state_efforts_in_the_controllers_joint_order():
    names = ('left', 'right')
    rest = np.repeat(SDCModel().rest_tip[None, :2], 2, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, finger_names=list(names), effort_topic=EFFORT_TOPIC,
            effort_joints=EFFORT_JOINTS)
        # every message, for the comparison below (reliable, volatile, as ros2_control subscribes)
        probe.listen(Float64MultiArray, EFFORT_TOPIC,
                     QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.VOLATILE))
        # and a subscriber with the QoS of ros2_control's forward_command_controller (system
        # default: its history keeps about the newest message only)
        controller_like = Probe(ctx, 'forward_command_controller')
        controller_like.listen(Float64MultiArray, EFFORT_TOPIC, qos_profile_system_default)
        executor.add_node(controller_like)
        assert spin_until(executor, lambda: node.pub_effort.get_subscription_count() == 2, 10.0)
        times = 5 * MS * np.arange(21)
        pos = np.repeat(rest[None], 21, 0)
        pos[..., 1] += 0.005
        zeros = np.zeros_like(pos)
        ref_pub.publish(cv.reference_to_msg(0, times, pos, zeros, zeros, names))
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        nan = rest.copy()
        nan[0, 0] = np.nan
        for k in range(6):
            state = nan if k == 3 else rest         # a NaN estimate is answered on neither output
            send_estimate(executor, node, est_pub,
                          cv.estimate_to_msg(k * MS, state, np.zeros_like(state), names))
        arrays = probe.received[EFFORT_TOPIC]
        assert spin_until(executor, lambda: len(commands(probe)) == 5 and len(arrays) == 5)
        assert node.diag.counters['bad_estimate'] == 1
        for state, array in zip(commands(probe), arrays):
            efforts = dict(zip(state.name, state.effort))
            assert list(array.data) == [efforts[j] for j in EFFORT_JOINTS]
            assert list(array.layout.dim) == [] and array.layout.data_offset == 0
        assert np.all(np.isfinite(np.asarray([a.data for a in arrays])))
        assert all(any(v != 0.0 for v in a.data) for a in arrays)
        assert spin_until(executor, lambda: controller_like.received[EFFORT_TOPIC])
        assert (list(controller_like.received[EFFORT_TOPIC][-1].data)
                in [list(a.data) for a in arrays])


@pytest.mark.ros
@pytest.mark.parametrize('node, params, needle', [
    ('controller', dict(finger_names=['left', 'right'], effort_topic=EFFORT_TOPIC),
     "'finger_0/ax0' is not a torque of these fingers (the torques are left/ax0"),
    ('controller', dict(finger_names=['left', 'left']), 'names must be distinct'),
    ('trajectory', dict(finger_names=['left', 'right']),
     "grasp_fingers': [0, 2] are not all indices"),
    ('estimator', dict(finger_names=['a', 'b', 'c', 'd', 'e']), 'needs 1 to 4 names'),
    ('simulator', dict(finger_names=['left', 'right']),
     "hand_fingers': [0, 1, 2, 3] has 4 entries"),
])
def test_bad_finger_parameters_stop_the_node_naming_the_problem(node, params, needle):
    """A ParameterError, with which the node's process exits with status 2 naming it (that path:
    test_node_cli.py)."""
    module = importlib.import_module(f'soft_gripper_sdre.nodes.{node}')
    node_class = getattr(module, f'{node.capitalize()}Node')
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            node_class(context=ctx, parameter_overrides=overrides(**params))
    assert needle in str(info.value)


# -- a two-finger graph, end to end over DDS -----------------------------------------------------

@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(150)
def test_two_named_fingers_run_the_whole_graph_as_processes(tmp_path):
    from soft_gripper_sdre.analysis.bag import extract_run, read_bag
    from soft_gripper_sdre.tools.graph.demo import DemoGraph, run_demo

    result = run_demo(tmp_path, 1.5, DemoGraph(fingers={'left': 0, 'right': 2}), timeout=120,
                      progress=False, render=False)
    assert all(code == 0 for code in result['run']['exit_codes'].values()), result['run']
    assert list(result['fingers']) == ['left', 'right']
    run = extract_run(tmp_path / 'bag')
    assert run.finger_names == ('left', 'right') and run.skipped == {}
    assert run.tips.values.shape[1:] == (2, 2) and len(run.torques.t) >= 1500
    assert np.all(np.isfinite(run.torques.values))
    # the grasping fingers close toward the cube from t_start = 0.5 s on, on the plan
    assert run.reference.values[-1, :, 1].min() > run.reference.values[0, :, 1].max() + 5e-3
    for name in ('left', 'right'):
        assert result['fingers'][name]['rmse_mm'] < 0.5, result['fingers']
    last = read_bag(tmp_path / 'bag', ['torque_commands'])['/torque_commands'][-1][1]
    assert list(last.name) == ['left/ax0', 'left/ax1', 'right/ax0', 'right/ax1']
    assert result['controller']['slow_decodes'] == 0
