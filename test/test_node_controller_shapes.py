"""The controller node (and ``controller --with-estimator``) over real DDS for fingers unlike the
hand: a one-chamber planar finger (d = 2, m = 1, pressure 0..2e5 Pa) and a three-tendon 3-D
segment (d = 3, m = 3, pull-only tendons 0..2 N), each with a model really trained on a known
SDC system."""

from node_harness import MS, make_composed, make_controller, make_estimator
import numpy as np
import pytest
from rclpy.node import Node
from rosutil import drain, overrides, ros_context, spin_until
from shaped_models import KNOWN_SYSTEMS, trained_known_system
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, OK
from soft_gripper_sdre.nodes.controller import ControllerNode, composed
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, REFERENCE_QOS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.shape import InputBounds

pytestmark = pytest.mark.ros

NAMES = ['index', 'thumb']
WEIGHTS = dict(q_pos=8e5, q_vel=0.0, r=1e-6)


@pytest.fixture(scope='module', params=list(KNOWN_SYSTEMS), ids=lambda s: f'd{s[0]}m{s[1]}')
def checkpoint(request, tmp_path_factory):
    """(shape, bounds, the path of a model trained on the known system of that shape)."""
    return trained_known_system(*request.param, tmp_path_factory.mktemp('shape'))


def _bounds_params(bounds: InputBounds) -> dict:
    return dict(input_lower=[float(v) for v in bounds.lower],
                input_upper=[float(v) for v in bounds.upper])


def _plan(d: int, start_ns: int = 0, points: int = 21):
    """A constant reference 2 mm from rest along each axis (both fingers); (message, (2, d))."""
    target = np.full((2, d), 0.002)
    target[1] *= -1
    pos = np.repeat(target[None], points, 0)
    zeros = np.zeros_like(pos)
    offsets = 5 * MS * np.arange(points)
    return cv.reference_to_msg(start_ns, offsets, pos, zeros, zeros, NAMES), target


def test_commands_name_m_inputs_stay_within_the_bounds_and_are_the_offline_law(checkpoint):
    shape, bounds, path = checkpoint
    d, m = shape.d, shape.m
    model = SDCModel(path)
    assert model.shape == shape
    offline = make_law('sdre_ff', model, Weights(**WEIGHTS), 0.0625, n_fingers=2, bounds=bounds)
    rng = np.random.default_rng(3)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, model_path=str(path), finger_names=NAMES, **WEIGHTS,
            **_bounds_params(bounds))
        values = node.diag.values
        assert values['shape'] == f'd={d}, m={m}' and values['input_bounds'] == str(bounds)
        msg, target = _plan(d)
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        states = []
        for k in range(6):
            x = np.hstack([rng.normal(scale=0.003, size=(2, d)), rng.normal(scale=0.02,
                                                                             size=(2, d))])
            if k == 5:
                x[1, 0] = np.nan                              # refused: no command for it
            states.append(x)
            before = node.diag.counters['estimates'] + node.diag.counters['bad_estimate']
            est_pub.publish(cv.estimate_to_msg(k * MS, x[:, :d], x[:, d:], NAMES))
            assert spin_until(executor, lambda: node.diag.counters['estimates']
                              + node.diag.counters['bad_estimate'] > before, 5.0)
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == 5)
        assert node.diag.counters['bad_estimate'] == 1
        node.diag.publish()
        got = probe.received[TORQUE_COMMANDS]
        assert list(got[0].name) == cv.torque_names(NAMES, m)
        zeros = np.zeros((2, d))
        for k, cmd in enumerate(got):
            stamp, u = cv.msg_to_torques(cmd, NAMES, m)
            assert stamp == k * MS and u.shape == (2, m)
            assert np.isfinite(u).all() and bounds.contains(u)
            x = states[k]
            want = offline.compute(x[:, :d], x[:, d:], target, zeros, ref_acc=zeros)
            np.testing.assert_allclose(u, want.u, rtol=1e-9, atol=1e-12 * bounds.upper.max())
        if m < d:      # one input for a planar tip: what it cannot reach is shown
            assert float(values['unreachable_max']) > 0.0
        else:
            assert 'unreachable_max' not in values


def test_each_finger_receives_the_laws_command_divided_by_its_input_gain(checkpoint):
    """The law runs in the model's units within what both fingers deliver (the bounds through
    the gains), and each finger's command is the law's divided by its gain, within its bounds."""
    shape, bounds, path = checkpoint
    d, m = shape.d, shape.m
    gains = np.array([1.25, 0.8])
    seen = bounds.through_gains(gains)
    np.testing.assert_allclose(seen.upper, 0.8 * bounds.upper)
    model = SDCModel(path)
    offline = make_law('sdre_ff', model, Weights(**WEIGHTS), 0.0625, n_fingers=2, bounds=seen)
    rng = np.random.default_rng(5)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, model_path=str(path), finger_names=NAMES, **WEIGHTS,
            input_gains=[float(g) for g in gains], **_bounds_params(bounds))
        assert node.diag.values['input_gains'] == 'index 1.25, thumb 0.8'
        msg, target = _plan(d)
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        states, high = [], 0
        zeros = np.zeros((2, d))
        for k in range(6):
            # far from the plan: the law presses its bounds
            x = np.hstack([rng.normal(scale=0.01, size=(2, d)), np.zeros((2, d))])
            states.append(x)
            est_pub.publish(cv.estimate_to_msg(k * MS, x[:, :d], x[:, d:], NAMES))
            assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == k + 1)
        for k, cmd in enumerate(probe.received[TORQUE_COMMANDS]):
            u = cv.msg_to_torques(cmd, NAMES, m)[1]
            want = offline.compute(states[k][:, :d], states[k][:, d:], target, zeros,
                                   ref_acc=zeros).u
            np.testing.assert_allclose(u, want / gains[:, None], rtol=1e-9,
                                       atol=1e-12 * bounds.upper.max())
            assert bounds.contains(u)
            high += int(np.any(np.isclose(want, seen.upper)))
        assert high > 0         # some command at the shared bound: the thumb then at its own
        # ... which it reaches only to rounding: clipped into the bounds, not counted as clipped
        assert node.diag.counters['clipped_command'] == 0
        assert node.diag.values['law_bounds'] == str(seen)
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(
                model_path=str(path), finger_names=NAMES, input_gains=[1.2], **_bounds_params(
                    bounds)))
    assert "'input_gains': one gain per finger of finger_names (2), got 1" in str(info.value)


def test_symmetric_bounds_through_input_gains_bound_the_law_by_the_smallest(checkpoint):
    """Bounds ±U about zero (the hand's kind): the law runs with the limit g_min U, its own
    saturation, and each finger receives its command divided by its gain."""
    shape, bounds, path = checkpoint
    d, m = shape.d, shape.m
    limit = float(bounds.upper.max())
    gains = np.array([0.9, 1.2])
    model = SDCModel(path)
    offline = make_law('sdre_ff', model, Weights(**WEIGHTS), 0.9 * limit, n_fingers=2)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, model_path=str(path), finger_names=NAMES, **WEIGHTS,
            input_gains=[float(g) for g in gains],
            **_bounds_params(InputBounds.symmetric(limit, m)))
        assert node.law_bounds is None and node.diag.values['law_bounds'] == f'±{0.9 * limit:g}'
        msg, target = _plan(d)
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        x = np.hstack([np.full((2, d), 0.02), np.zeros((2, d))])       # far: at the limit
        est_pub.publish(cv.estimate_to_msg(0, x[:, :d], x[:, d:], NAMES))
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == 1)
        u = cv.msg_to_torques(probe.received[TORQUE_COMMANDS][0], NAMES, m)[1]
        zeros = np.zeros((2, d))
        want = offline.compute(x[:, :d], x[:, d:], target, zeros, ref_acc=zeros).u
        assert np.isclose(np.abs(want).max(), 0.9 * limit)
        np.testing.assert_allclose(u, want / gains[:, None], rtol=1e-9, atol=1e-12 * limit)
        assert np.abs(u).max() <= limit
        assert node.diag.counters['clipped_command'] == 0


def test_bounds_of_another_input_count_than_the_models_are_refused_naming_them(checkpoint):
    shape, bounds, path = checkpoint
    wrong = InputBounds.symmetric(1.0, 2 if shape.m == 1 else 1)
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(
                model_path=str(path), **_bounds_params(wrong)))
    assert "'input_lower', 'input_upper'" in str(info.value)
    assert f'the finger has {shape.m} input(s)' in str(info.value)


def test_effort_joints_name_the_models_inputs(checkpoint):
    shape, bounds, path = checkpoint
    joints = cv.torque_names(NAMES, shape.m)[::-1]
    with ros_context() as (ctx, _executor):
        node = ControllerNode(context=ctx, parameter_overrides=overrides(
            model_path=str(path), finger_names=NAMES, effort_topic='/efforts',
            effort_joints=joints, **_bounds_params(bounds)))
        assert node.effort_order.tolist() == list(range(2 * shape.m))[::-1]
        node.destroy_node()
        with pytest.raises(ParameterError, match='effort_joints'):
            ControllerNode(context=ctx, parameter_overrides=overrides(
                model_path=str(path), finger_names=NAMES, effort_topic='/efforts',
                effort_joints=cv.torque_names(NAMES, shape.m + 1), **_bounds_params(bounds)))


def test_the_composed_controller_filters_the_models_tips_and_refuses_another_task_dim(checkpoint):
    shape, bounds, path = checkpoint
    d = shape.d
    params = dict(model_path=str(path), finger_names=NAMES, **_bounds_params(bounds))
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError, match=f"'task_dim'.*give task_dim {d}"):
            composed(context=ctx, parameter_overrides=overrides(task_dim=5 - d, **params))
    with ros_context() as (ctx, executor):
        est, ctl, probe, tip_pub, ref_pub = make_composed(ctx, executor, task_dim=d, **params)
        ref_pub.publish(_plan(d)[0])
        assert spin_until(executor, lambda: ctl.diag.counters['references'] == 1)
        tips = np.array([[0.001, -0.002, 0.003], [0.0, 0.001, -0.001]])
        for k in range(5):
            tip_pub.publish(cv.tips_to_msg(k * MS, tips + 1e-4 * k))
            assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == k + 1)
        for cmd in probe.received[TORQUE_COMMANDS]:
            u = cv.msg_to_torques(cmd, NAMES, shape.m)[1]
            assert np.isfinite(u).all() and bounds.contains(u)
        assert est.filter.kf.x.shape == (2, 2 * d)


@pytest.mark.parametrize('node, args, needle', [
    ('controller', ['-p', 'input_lower:=[0.0]', '-p', 'input_upper:=[0.05]'],
     "'input_lower', 'input_upper': the finger has 2 input(s); got 1 lower and 1 upper"),
    ('controller', ['-p', 'input_lower:=0'], 'got 1 lower and 0 upper'),
    ('controller', ['-p', 'input_lower:=[0.0, 0.01]', '-p', 'input_upper:=[0.01, 0.01]'],
     'input ax1: the lower bound must be below the upper one'),
    ('controller', ['-p', 'input_gains:=[1.1, 0.9, 1.0]'],
     "'input_gains': one gain per finger of finger_names (4), got 3"),
    ('controller', ['-p', 'input_gains:=[1.1, 0.9, 1.0, 3.0]'],
     "'input_gains': each gain must lie in [0.5, 2]"),
    ('controller', ['-p', 'input_gains:=1.1 0.9 x 1.0'], "'input_gains': '1.1 0.9 x 1.0' is not"),
    ('estimator', ['-p', 'task_dim:=4'], 'task_dim'),
    ('trajectory', ['-p', 'direction:=[0.0, 1.0, 0.0]'], "'direction': needs task_dim = 2 values"),
    ('trajectory', ['-p', 'close_path:=[0.001, .nan]'], "'close_path'"),
])
def test_bad_shape_parameters_exit_2_naming_them(node, args, needle, tmp_path):
    """Real processes: exit status 2, the message names the parameters, no traceback."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    out = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.nodes.{node}', '--ros-args',
                          *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2, out.stderr
    assert needle in out.stderr and 'Traceback' not in out.stderr
    assert not list(tmp_path.iterdir())


def test_an_estimator_of_another_task_dim_is_named_and_its_estimates_refused(checkpoint):
    """A planar estimator before a 3-D model (or a 3-D one before a planar model) sends
    estimates nothing in them tells apart: the controller asks the publisher for its task_dim,
    reports ERROR naming it with the fix, and commands nothing until that publisher is gone,
    keeping the plan of a planner of its own task_dim; a publisher without the parameter (the
    probe, a lab's estimator) is taken as it is."""
    shape, bounds, path = checkpoint
    d = shape.d
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, model_path=str(path), finger_names=NAMES, **WEIGHTS,
            **_bounds_params(bounds))
        wrong, _, _ = make_estimator(ctx, executor, finger_names=NAMES, task_dim=5 - d)

        def settled(expect_problem: bool) -> bool:
            node.peers.poll()
            return (node.peers.problem is not None) == expect_problem
        assert spin_until(executor, lambda: settled(True), 10.0)
        want = (f'/estimator publishes /state_estimate for task_dim {5 - d}, but the model is of '
                f'{d}-D tips: start it with -p task_dim:={d}')
        assert node.peers.problem == want
        assert node.diag.level == ERROR and node.diag.values['task_dim_mismatch'] == want
        msg, _ = _plan(d)
        ref_pub.publish(msg)                    # the probe's plan (no task_dim there) is kept
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        x = np.zeros((2, d))
        for k in range(8):                      # refused estimates over 0.8 s: past the
            est_pub.publish(cv.estimate_to_msg(k * MS, x, x, NAMES))    # watchdog, the same
            drain(executor, 0.1)                                        # ERROR
        assert node.diag.counters['wrong_task_dim'] >= 5
        assert probe.received[TORQUE_COMMANDS] == [] and node.diag.message.startswith(want)
        # the estimator gone, the next estimate is answered along the plan the controller kept
        executor.remove_node(wrong)
        wrong.destroy_node()
        assert spin_until(executor, lambda: settled(False), 10.0)
        assert node.diag.level == OK and 'task_dim_mismatch' not in node.diag.values
        est_pub.publish(cv.estimate_to_msg(10 * MS, x, x, NAMES))
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == 1)
        assert node.diag.counters['estimate_jumps'] == 0


def test_a_plan_publisher_of_another_task_dim_drops_the_plan_and_its_plans_are_refused(checkpoint):
    """A node of another task_dim on grasp_reference: the plan the controller held is dropped
    (it may be that node's), plans are refused and counted until it is gone, then taken again."""
    shape, bounds, path = checkpoint
    d = shape.d
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(
            ctx, executor, model_path=str(path), finger_names=NAMES, **WEIGHTS,
            **_bounds_params(bounds))
        msg, _ = _plan(d)
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.gate.plan is not None)
        planner = Node('trajectory', context=ctx, parameter_overrides=overrides(task_dim=5 - d),
                       automatically_declare_parameters_from_overrides=True)
        planner.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        executor.add_node(planner)
        assert spin_until(executor, lambda: node.peers.problem is not None, 15.0)
        assert node.peers.problem.startswith(f'/trajectory publishes /grasp_reference for '
                                             f'task_dim {5 - d}')
        assert node.gate.plan is None and node.diag.level == ERROR
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.diag.counters['wrong_task_dim'] == 1)
        assert node.gate.plan is None
        executor.remove_node(planner)
        planner.destroy_node()
        assert spin_until(executor, lambda: node.peers.problem is None, 15.0)
        ref_pub.publish(msg)
        assert spin_until(executor, lambda: node.gate.plan is not None)
