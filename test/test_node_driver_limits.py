"""The excitation against the driver's limits (nodes/driver_limits.py): the driver's reported
bounds read, a matching limit left alone, each signal levelled within the driver's limit (real
plant_driver and excitation nodes over DDS; where the limit comes from, a driver narrower than
the limit given and clipped commands: test_excitation_limit.py)."""
import numpy as np
import pytest
from rosutil import drain, overrides, ros_context, spin_until

from soft_gripper_sdre.nodes.driver_limits import parse_bounds
from soft_gripper_sdre.nodes.excitation import ExcitationNode

NAMES = ['index', 'thumb']


def test_the_drivers_bounds_are_read_tightest_over_its_fingers():
    lower, upper = parse_bounds('ax0 [-0.02, 0.02], ax1 [-0.03, 0.01]; '
                                'ax0 [-0.01, 0.05], ax1 [-0.03, 0.02]')
    np.testing.assert_array_equal(lower, [-0.01, -0.03])
    np.testing.assert_array_equal(upper, [0.02, 0.01])
    np.testing.assert_array_equal(parse_bounds('ax0 [0, 60000]')[1], [60000.0])


@pytest.mark.parametrize('text', ['', 'bounds', 'ax1 [0, 1]', 'ax0 [a, 1]',
                                  'ax0 [0, 1]; ax0 [0, 1], ax1 [0, 1]'])
def test_a_bounds_value_that_does_not_read_is_not_used(text):
    assert parse_bounds(text) is None


def test_a_limit_matching_the_drivers_is_left_alone_and_nothing_is_clipped():
    """torque_limit given at the driver's 0.02 N·m: no refusal, no clipped command (a limit
    wider than the driver's is refused: test_excitation_limit.py)."""
    from soft_gripper_sdre.nodes.plant_driver import PlantDriverNode
    with ros_context('events') as (ctx, executor):
        driver = PlantDriverNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, plant='tendon3', rate=200.0, command_timeout=0.5))
        executor.add_node(driver)
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, signals=['u1'], duration=1.5, settle_time=0.3,
            settle_samples=10, torque_limit=0.02, min_command_subscribers=1,
            tips_reliability='best_effort'))
        executor.add_node(node)
        assert spin_until(executor, lambda: node.done, 30.0)
        drain(executor, 1.5)                      # the driver's last report
        assert node.exit_code == 0 and not node.driver_limits.refused
        assert node.diag.values['driver_bounds'].startswith('ax0 [-0.02, 0.02]')
        assert driver.diag.counters.get('clipped_commands', 0) == 0
        assert 'driver_clipped' not in node.diag.values


def test_each_signal_gets_its_own_level_on_the_drivers_gripper_over_dds():
    """level auto, level_per signal, against plant_driver's tendon gripper at the driver's limit:
    one level per signal in /diagnostics, none clipped by the driver, each signal's peak true
    excursion near the 8 mm aimed at."""
    from geometry_msgs.msg import PoseArray
    from rosutil import Probe, deep

    from soft_gripper_sdre.nodes.plant_driver import TRUE_TIP_POSITIONS, PlantDriverNode
    from soft_gripper_sdre.nodes.topics import LOOP_QOS
    with ros_context('events') as (ctx, executor):
        driver = PlantDriverNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, plant='tendon3', rate=200.0, command_timeout=0.5))
        probe = Probe(ctx)
        truth = []
        probe.create_subscription(PoseArray, TRUE_TIP_POSITIONS, truth.append, deep(LOOP_QOS))
        executor.add_node(driver)
        executor.add_node(probe)
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=NAMES, finger=0, signals=['u1', 'b1'], duration=4.0, settle_time=0.5,
            settle_samples=10, torque_limit=0.02, level='auto', max_excursion=0.016,
            level_probe_time=1.5, min_command_subscribers=1, tips_reliability='best_effort'))
        executor.add_node(node)
        assert spin_until(executor, lambda: node.done, 120.0)
        drain(executor, 1.5)
        assert node.exit_code == 0 and node.run.stage == 1
        assert [name for name, _ in node.run.levels] == ['u1', 'b1']
        levels = node.diag.values['levels']
        assert levels.startswith('u1 ') and ', b1 ' in levels
        assert driver.diag.counters.get('clipped_commands', 0) == 0
        assert not node.driver_limits.refused
        stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in truth])
        tips = np.array([[m.poses[0].position.x, m.poses[0].position.y] for m in truth])
    start = node.start_ns / 1e9
    rest = tips[np.argmin(np.abs(stamps - start))]
    plan_end = start + node.run.plan_offset + node.run.plan.duration     # the end of b1
    b1_start = plan_end - 4.0
    moved = np.linalg.norm(tips - rest, axis=1)
    for name, lo, hi in (('b1', b1_start, plan_end),):
        peak = moved[(stamps >= lo) & (stamps <= hi)].max()
        assert 0.7 * 0.008 < peak < 1.3 * 0.008, (name, peak)

