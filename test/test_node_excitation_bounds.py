"""The excitation node over real DDS with per-input bounds: one-sided inputs for m = 1 (a
chamber) and m = 3 (tendons): the commands name <finger>/ax<k> for k < m, are the plan's inputs
for their stamps, never leave the bounds, hold the rest value while settling and at the end; bad
bounds are refused naming the parameters."""
import os
import subprocess
import sys

from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosutil import Probe, deep, drain, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.excitation import ExcitationPlan
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.sim.signal_specs import resolve_signals

pytestmark = pytest.mark.ros

MS = 1_000_000
NAMES = ['a', 'b']
REST = np.array([[0.1, 0.005, 0.0], [0.12, 0.0, 0.001]])


def _start(ctx, executor, **params):
    params.setdefault('min_command_subscribers', 1)
    node = ExcitationNode(context=ctx, parameter_overrides=overrides(finger_names=NAMES, **params))
    probe = Probe(ctx)
    pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor, lambda: (pub.get_subscription_count() > 0
                                         and node.pub_cmd.get_subscription_count() > 0), 20.0)
    return node, probe, pub


def _play(executor, node, probe, pub, period_ms: int, most: int):
    for k in range(most):
        n = len(probe.received[TORQUE_COMMANDS])
        pub.publish(cv.tips_to_msg(5 * MS + k * period_ms * MS, REST))
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) > n, 5.0), k
        if node.done:
            return
    raise AssertionError('the plan did not end')


@pytest.mark.parametrize('m, lower, upper, signals', [
    (1, [0.0], [60000.0], ['u1', 'x1']),
    (3, [0.0, 0.0, 0.0], [4.0, 4.0, 4.0], ['x2', 'b1']),
    (2, [0.0, 0.0], [4.0, 4.0], ['u4', 'u1']),
])
def test_one_sided_inputs_are_played_from_rest_into_their_bounds(m, lower, upper, signals):
    """(Two tendons: u4 staggered over the pair, u1 alike, sim/signals.py.)"""
    bounds = InputBounds(lower, upper)
    with ros_context() as (ctx, executor):
        node, probe, pub = _start(ctx, executor, signals=signals, duration=0.1, settle_time=0.02,
                                  settle_samples=5, input_lower=lower, input_upper=upper,
                                  amplitude=1.5)
        assert node.m == m
        _play(executor, node, probe, pub, 2, 200)
        msgs = probe.received[TORQUE_COMMANDS]
        assert all(list(msg.name) == [f'{f}/ax{k}' for f in NAMES for k in range(m)]
                   for msg in msgs)
        got = [cv.msg_to_torques(msg, NAMES, m) for msg in msgs]
    plan = ExcitationPlan(resolve_signals(signals, duration=0.1, m=m, one_sided=True), 0.02, 2,
                          amplitude=1.5, bounds=bounds)
    for k, (stamp, u) in enumerate(got[:-1]):
        assert stamp == 5 * MS + 2 * k * MS
        np.testing.assert_array_equal(u, plan.torques(2 * k * MS / cv.NS))
    u = np.array([u for _, u in got])
    assert bounds.contains(u)
    assert np.all(u[:10] == 0.0) and np.all(got[-1][1] == 0.0), 'at rest: settling and at the end'
    assert u.max() > 0.3 * max(upper)
    assert node.exit_code == 0 and node.diag.values['level'] == 'fixed'
    if m == 2:
        u4, u1 = u[10:60], u[70:120]                # each signal's 50 commands after settling
        assert np.abs(u4[..., 0] - u4[..., 1]).max() > 0.5
        np.testing.assert_array_equal(u1[..., 0], u1[..., 1])


def test_symmetric_bounds_on_two_inputs_are_the_hands_torque_limit():
    with ros_context() as (ctx, executor):
        node, probe, pub = _start(ctx, executor, signals=['u1'], duration=0.6, settle_time=0.0,
                                  input_lower=[-0.03, -0.03], input_upper=[0.03, 0.03])
        assert node.m == 2 and node.run.plan.map is None and node.run.plan.torque_limit == 0.03
        _play(executor, node, probe, pub, 10, 200)
        got = [cv.msg_to_torques(msg, NAMES) for msg in probe.received[TORQUE_COMMANDS]]
    u = np.array([u for _, u in got])
    assert np.abs(u).max() == 0.03 and np.all(u[:, :, 0] == u[:, :, 1])


def test_one_chambers_bounds_given_as_plain_numbers():
    with ros_context() as (ctx, _executor):
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, input_lower=0, input_upper=60000))
        assert node.m == 1 and node.run.plan.map.bounds == InputBounds([0.0], [60000.0])
        node.destroy_node()


@pytest.mark.parametrize('params, message', [
    (dict(input_lower=[0.0, 0.0], input_upper=[4.0, 4.0, 4.0]),
     "parameters 'input_lower', 'input_upper': 2 lower and 3 upper bound(s)"),
    (dict(input_upper=[4.0, 4.0]), 'give both (one value per input) or neither'),
    (dict(input_lower='0 nan', input_upper=[4.0, 4.0]), 'holds a value that is not finite'),
    (dict(input_lower=[0.0] * 5, input_upper=[1.0] * 5),
     'input bounds: 5 inputs; a finger has 1 to 4'),
    (dict(input_lower=[0.0, 2.0], input_upper=[1.0, 1.0]),
     'input ax1: the lower bound must be below the upper one, got [2.0, 1.0]'),
    (dict(input_lower=[0.0], input_upper=[1.0], signals=['mine'], spec_file='/no/such.yaml'),
     'signal file /no/such.yaml does not exist'),
    (dict(input_lower=[0.0], input_upper=[1.0], level='auto', level_per='plan',
          max_excursion=0.01, signals=['u1', 'mine'], spec_file='SPEC'),
     'all built-in or all from spec_file'),
])
def test_bad_bounds_stop_the_node_at_start_up_naming_them(params, message, tmp_path):
    if params.get('spec_file') == 'SPEC':
        path = tmp_path / 's.yaml'
        path.write_text('signals:\n  mine: {kind: chirp, duration: 1.0, '
                        'ax0: {amplitude: 0.5, f0: 1.0, f1: 2.0}}\n')
        params = dict(params, spec_file=str(path))
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ExcitationNode(context=ctx, parameter_overrides=overrides(finger_names=NAMES,
                                                                      **params))
        assert message in str(info.value), str(info.value)


def test_bad_bounds_exit_2_naming_them():
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.excitation',
                           '--ros-args', '-p', 'input_lower:=[0.0, 0.0, 0.0]',
                           '-p', 'input_upper:=[4.0, 4.0]'],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ))
    assert proc.returncode == 2, proc.stderr
    assert "'input_lower', 'input_upper'" in proc.stderr and 'Traceback' not in proc.stderr


@pytest.mark.parametrize('plant, rate, lower, upper', [
    ('pneumatic1', 100.0, [0.0], [60000.0]),
    ('trunk3', 250.0, [0.0, 0.0, 0.0], [4.0, 4.0, 4.0]),
])
def test_the_excitation_drives_a_foreign_gripper_without_a_command_clipped(plant, rate, lower,
                                                                           upper):
    """The excitation node answering the plant driver's best-effort tips with the gripper's
    bounds: every command decodes (no bad ones), none is clipped by the driver, the true tips
    move by millimetres, and the run ends with the rest inputs applied."""
    from soft_gripper_sdre.nodes.plant_driver import TRUE_TIP_POSITIONS, PlantDriverNode
    with ros_context('events') as (ctx, executor):
        driver = PlantDriverNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, plant=plant, rate=rate, command_timeout=0.5))
        probe = Probe(ctx)
        truth = []
        probe.create_subscription(PoseArray, TRUE_TIP_POSITIONS, truth.append, deep(LOOP_QOS))
        executor.add_node(driver)
        executor.add_node(probe)
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, signals=['x1'], duration=1.5, settle_time=0.3, settle_samples=10,
            input_lower=lower, input_upper=upper, min_command_subscribers=1,
            tips_reliability='best_effort'))
        executor.add_node(node)
        assert spin_until(executor, lambda: node.done, 30.0)
        drain(executor, 0.3)
        c = driver.diag.counters
        assert node.exit_code == 0
        # answered the driver's ticks (on a slow or loaded host the driver ticks late and
        # fewer times than its rate, each tick advancing the plant by the time elapsed)
        assert c['ticks'] > 0.2 * rate * 1.8 and c['commands'] > 0.6 * c['ticks']
        assert c['bad_commands'] == 0
        assert c['clipped_commands'] == 0 and c['nonfinite_commands'] == 0
        np.testing.assert_array_equal(driver.applied, np.zeros((2, len(lower))))
    d = 2 if plant == 'pneumatic1' else 3
    tips = np.array([[[p.position.x, p.position.y, p.position.z][:d] for p in m.poses]
                     for m in truth])
    rest = tips[0]
    assert np.max(np.linalg.norm(tips - rest, axis=-1)) > 2e-3
