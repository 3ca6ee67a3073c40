"""The plant driver serving fingers unlike the hand, over real DDS on loopback: pneumatic1 (one
chamber pressure per finger, 0..60 kPa, planar tips) and trunk3 (three tendon tensions, 0..4 N,
3-D tips): commands named <finger>/ax<k> for k < m, held, clipped to the one-sided bounds,
refused when named for another number of inputs; tips with z; bad bounds refused at start-up
naming the parameters (exit 2)."""
import os
import subprocess
import sys
import time

from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosutil import Probe, deep, drain, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.plant_driver import TRUE_TIP_POSITIONS, PlantDriverNode
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.plants.pneumatic import P_MAX
from soft_gripper_sdre.sim.plants.presets import plant_pair

pytestmark = pytest.mark.ros

NAMES = ['a', 'b']


def _driver(ctx, executor, **params):
    """The driver and a probe recording the true tips and publishing commands, matched."""
    node = PlantDriverNode(context=ctx, parameter_overrides=overrides(finger_names=NAMES,
                                                                      **params))
    probe = Probe(ctx)
    truth = []
    probe.create_subscription(PoseArray, TRUE_TIP_POSITIONS, truth.append, deep(LOOP_QOS))
    cmd_pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor, lambda: node.pub_truth.get_subscription_count() > 0
                      and cmd_pub.get_subscription_count() > 0, 20.0)
    return node, cmd_pub, truth


def _send(executor, node, pub, msg) -> None:
    before = node.diag.counters['commands']
    pub.publish(msg)
    assert spin_until(executor, lambda: node.diag.counters['commands'] > before, 5.0)


def _after_a_tick(executor, node) -> None:
    ticks = node.diag.counters['ticks']
    assert spin_until(executor, lambda: node.diag.counters['ticks'] > ticks + 1, 5.0)


def _hold(executor, node, pub, u, seconds: float, truth) -> np.ndarray:
    """Send ``u`` (n, m) every 50 ms for ``seconds``; the mean true tips (n, 3) over the last
    0.2 s."""
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), u, NAMES))
        drain(executor, 0.05)
    end = cv.from_time(truth[-1].header.stamp)
    settled = [m for m in truth if cv.from_time(m.header.stamp) > end - 0.2e9]
    return np.mean([[[p.position.x, p.position.y, p.position.z] for p in m.poses]
                    for m in settled], axis=0)


def test_pneumatic_fingers_take_one_pressure_each_clipped_to_0_to_p_max():
    """One input per finger (ax0 only): a held pressure moves each true tip where the plant,
    stepped offline, settles; a negative pressure is a vented chamber (clipped, counted), one
    above p_max is p_max; a two-input command is refused and the previous one stays in force;
    idle, the chamber is vented."""
    fingers = plant_pair('pneumatic1')
    u = np.array([[0.3 * P_MAX], [0.5 * P_MAX]])
    predicted = []
    for f, ui in zip(fingers, u):
        f.step(ui, 3.0)
        predicted.append(f.tip() - f.rest_tip)
    with ros_context('events') as (ctx, executor):
        node, pub, truth = _driver(ctx, executor, plant='pneumatic1', rate=100.0,
                                   command_timeout=2.0)
        c = node.diag.counters
        assert node.m == 1 and node.d == 2
        np.testing.assert_array_equal(node.applied, np.zeros((2, 1)))       # idle: vented
        tips = _hold(executor, node, pub, u, 3.0, truth)
        assert c['stale_ticks'] == 0 and c['bad_commands'] == 0
        np.testing.assert_array_equal(node.applied, u)
        for i, f in enumerate(fingers):
            moved = tips[i, :2] - f.rest_tip
            assert tips[i, 2] == 0.0, 'a planar tip: z = 0'
            assert np.linalg.norm(moved) > 5e-3
            assert np.linalg.norm(moved) == pytest.approx(np.linalg.norm(predicted[i]), rel=0.05)
            assert moved @ predicted[i] > 0.99 * np.linalg.norm(moved) * np.linalg.norm(
                predicted[i])

        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), [[-1e4], [2 * P_MAX]], NAMES))
        assert c['clipped_commands'] == 1
        _after_a_tick(executor, node)
        np.testing.assert_array_equal(node.applied, [[0.0], [P_MAX]])

        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), np.full((2, 2), 1e3), NAMES))
        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), np.zeros((2, 2)), NAMES))
        assert c['bad_commands'] == 2, 'ax1 is no input of a one-chamber finger'
        _after_a_tick(executor, node)
        np.testing.assert_array_equal(node.applied, [[0.0], [P_MAX]])       # still in force
        assert node.diag.values['shape'] == 'd=2, m=1'


def test_trunk_segments_take_three_tensions_and_move_their_tips_in_3d():
    """Three inputs per finger; tendon 1 of finger a and tendon 2 of finger b pulled: the true
    tips (with z) settle where the plants, stepped offline, settle (off the Y axis: z ≠ 0);
    a pushed tendon is slack (clipped), tensions over 4 N are 4 N."""
    fingers = plant_pair('trunk3')
    u = np.array([[0.0, 1.5, 0.0], [0.0, 0.0, 2.0]])
    predicted = []
    for f, ui in zip(fingers, u):
        f.step(ui, 2.0)
        predicted.append(f.tip() - f.rest_tip)
    with ros_context('events') as (ctx, executor):
        node, pub, truth = _driver(ctx, executor, plant='trunk3', rate=250.0, command_timeout=2.0,
                                   noise_std=0.0)
        c = node.diag.counters
        assert node.m == 3 and node.d == 3
        tips = _hold(executor, node, pub, u, 2.0, truth)
        for i, f in enumerate(fingers):
            moved = tips[i] - f.rest_tip
            assert abs(moved[2]) > 3e-3, 'the tip leaves the plane'
            np.testing.assert_allclose(moved, predicted[i], atol=0.05 * np.linalg.norm(moved))
        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), [[-1.0, 9.0, 0.5],
                                                                  [1.0, 1.0, 1.0]], NAMES))
        assert c['clipped_commands'] == 1
        _after_a_tick(executor, node)
        np.testing.assert_array_equal(node.applied, [[0.0, 4.0, 0.5], [1.0, 1.0, 1.0]])
        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), [[np.nan, 1.0, 1.0],
                                                                  [1.0, 1.0, 1.0]], NAMES))
        assert c['nonfinite_commands'] == 1
        _after_a_tick(executor, node)
        np.testing.assert_array_equal(node.applied, np.zeros((2, 3)), 'slack, never NaN')


def test_input_bounds_narrow_the_presets_and_must_fit_them():
    with ros_context('events') as (ctx, executor):
        node, pub, _ = _driver(ctx, executor, plant='trunk3', rate=250.0,
                               input_lower=[0.5, 0.0, 0.0], input_upper=[2.0, 3.0, 1.0])
        np.testing.assert_array_equal(node.lower, [[0.5, 0.0, 0.0]] * 2)
        np.testing.assert_array_equal(node.applied, [[0.5, 0.0, 0.0]] * 2, 'the rest input')
        _send(executor, node, pub, cv.torques_to_msg(time.time_ns(), np.full((2, 3), 2.5), NAMES))
        _after_a_tick(executor, node)
        np.testing.assert_array_equal(node.applied, [[2.0, 2.5, 1.0]] * 2)
    bad = [
        (dict(plant='trunk3', input_lower=[0.0, 0.0], input_upper=[1.0, 1.0]),
         "'input_lower', 'input_upper' (plant 'trunk3'): the finger has 3 input(s); got 2 lower"),
        (dict(plant='trunk3', input_lower=[0.0, 0.0], input_upper=[1.0, 1.0, 1.0]),
         "'input_lower', 'input_upper' (plant 'trunk3'): the finger has 3 input(s); got 2 lower "
         'and 3 upper'),
        (dict(plant='trunk3', input_lower=[-1.0, 0.0, 0.0], input_upper=[1.0, 1.0, 1.0]),
         "reaches beyond the plant's bounds"),
        (dict(plant='pneumatic1', input_lower=[0.0], input_upper=[1e6]),
         "reaches beyond the plant's bounds"),
        (dict(plant='pneumatic1', input_lower=[2e4], input_upper=[1e4]),
         'input ax0: the lower bound must be below the upper one'),
        (dict(plant='pneumatic1', torque_limit=0.01), "parameter 'torque_limit': plant "
         "'pneumatic1' has inputs that are not ±a limit"),
        (dict(plant='trunk3', input_lower=[0.0, 0.0, 0.0]),
         "'input_lower', 'input_upper': give both (one value per input) or neither"),
        (dict(plant='trunk3', input_lower='0, 0, x', input_upper=[1.0, 1.0, 1.0]),
         "parameter 'input_lower': '0, 0, x' is not a list of numbers"),
    ]
    for params, message in bad:
        with ros_context() as (ctx, _), pytest.raises(ParameterError) as info:
            PlantDriverNode(context=ctx, parameter_overrides=overrides(finger_names=NAMES,
                                                                       **params))
        assert message in str(info.value), (params, str(info.value))


def test_a_lab_writes_one_chambers_bounds_as_plain_numbers():
    """``-p input_lower:=0 -p input_upper:=30000`` (integers) and the string form both narrow
    the chamber to 0..30 kPa."""
    for lower, upper in ((0, 30000), ('0', '30000.0')):
        with ros_context() as (ctx, _):
            node = PlantDriverNode(context=ctx, parameter_overrides=overrides(
                finger_names=NAMES, plant='pneumatic1', input_lower=lower, input_upper=upper))
            np.testing.assert_array_equal(node.upper, [[30000.0], [30000.0]])
            np.testing.assert_array_equal(node.lower, [[0.0], [0.0]])
            node.destroy_node()


@pytest.mark.parametrize('args, name', [
    (['plant:=trunk9'], "'plant'"),
    (['plant:=pneumatic1', 'input_lower:=[0.0, 0.0]', 'input_upper:=[1.0, 1.0]'],
     "'input_lower', 'input_upper'"),
    (['plant:=pneumatic1', 'input_lower:=0', 'input_upper:=70000'],
     "reaches beyond the plant's bounds"),
])
def test_bad_plants_and_bounds_exit_2_naming_them(args, name):
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.plant_driver',
                           '--ros-args', *[a for arg in args for a in ('-p', arg)]],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ))
    assert proc.returncode == 2, proc.stderr
    assert name in proc.stderr and 'Traceback' not in proc.stderr
