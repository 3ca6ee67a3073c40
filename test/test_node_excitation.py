"""The excitation node over real DDS (loopback): answers tips with the plan's torque for their
stamp, stops with zero torque at the end, on a fault and on shutdown, and refuses bad parameters."""
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.excitation import ExcitationPlan
from soft_gripper_sdre.sim.signal_specs import builtin_signal

pytestmark = pytest.mark.ros

MS = 1_000_000
REST = np.array([[0.0, -0.0105, 0.1076]])


def start(ctx, executor, **params):
    params.setdefault('min_command_subscribers', 1)      # the probe is the only subscriber
    params.setdefault('torque_limit', 0.1)               # the probe reports no bounds
    node = ExcitationNode(context=ctx,
                          parameter_overrides=overrides(finger_names=['finger_0'], **params))
    probe = Probe(ctx)
    pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
    probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
    executor.add_node(node)
    executor.add_node(probe)
    assert spin_until(executor,
                      lambda: (pub.get_subscription_count() > 0
                               and node.pub_cmd.get_subscription_count() > 0), 20.0)
    return node, probe, pub


def commands(probe):
    return [cv.msg_to_torques(m, 1) for m in probe.received[TORQUE_COMMANDS]]


def send_tips(executor, probe, pub, ns, tips=REST):
    n = len(probe.received[TORQUE_COMMANDS])
    pub.publish(cv.tips_to_msg(ns, tips))
    return spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) > n, 5.0)


def test_each_tip_message_is_answered_with_the_torque_for_its_stamp_then_zero_at_the_end():
    with ros_context() as (ctx, executor):
        # (settle_samples: the 5 tips of settle_time at 1 ms are enough, the plan is not shifted)
        node, probe, pub = start(ctx, executor, signals=['x1'], duration=0.02, settle_time=0.005,
                                 settle_samples=5)
        plan = ExcitationPlan([builtin_signal('x1', 0.02)], 0.005, 1)
        start_ns = 7 * MS  # plan time starts at the first tips, whatever its stamp
        for k in range(30):
            assert send_tips(executor, probe, pub, start_ns + k * MS), f'tips {k} not answered'
            if node.done:
                break
        got = commands(probe)
        assert [s for s, _ in got] == [start_ns + k * MS for k in range(26)]
        for k, (_, u) in enumerate(got[:-1]):
            np.testing.assert_array_equal(u, plan.torques(k * MS / 1e9))
        assert np.all(got[-1][1] == 0.0) and np.any(got[10][1] != 0.0) and np.all(got[2][1] == 0.0)
        assert node.done and node.exit_code == 0 and node.stopped


def test_too_few_tips_in_settle_time_extend_the_settle_phase_and_shift_the_plan():
    """A driver slower than settle_time needs (here 200 Hz: 2 tips in 10 ms): zero torque until
    settle_samples tips were heard, then the plan from the end of its settle phase."""
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['x1'], duration=0.02, settle_time=0.01,
                                 settle_samples=6)
        plan = ExcitationPlan([builtin_signal('x1', 0.02)], 0.01, 1)
        period = 5 * MS
        shift = 6 * period / 1e9 - 0.01        # the 7th tip (30 ms) is the plan's 10 ms
        for k in range(20):
            assert send_tips(executor, probe, pub, 3 * MS + k * period), f'tips {k} not answered'
            if node.done:
                break
        got = commands(probe)
        assert all(np.all(u == 0.0) for _, u in got[:6])
        for k, (_, u) in enumerate(got[6:-1], start=6):
            np.testing.assert_array_equal(u, plan.torques(k * period / 1e9 - shift))
        assert len(got) == 6 + 4 + 1 and np.any(got[7][1] != 0.0)
        assert node.done and node.exit_code == 0 and node.run.settle.zero_answers >= 6
        assert node.diag.values['settle_extended'] == '0.020'


def test_bad_and_old_tips_are_counted_and_not_answered():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u1'])
        assert send_tips(executor, probe, pub, 5 * MS)
        for msg, key, count in ((cv.tips_to_msg(6 * MS, np.full((1, 3), np.nan)), 'bad_tips', 1),
                                (cv.tips_to_msg(4 * MS, REST), 'old_tips', 1),
                                (cv.tips_to_msg(7 * MS, np.zeros((2, 3))), 'bad_tips', 2)):
            pub.publish(msg)            # one at a time: the node keeps only the newest tips
            assert spin_until(executor, lambda: node.diag.counters[key] == count), key
        assert len(commands(probe)) == 1 and not node.done
        assert send_tips(executor, probe, pub, 6 * MS)


def test_tips_that_stop_are_a_fault_answered_with_zero_torque():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u2'], tips_timeout=0.1, settle_time=0.0)
        for k in range(3):
            assert send_tips(executor, probe, pub, k * MS)
        assert np.any(commands(probe)[-1][1] != 0.0)        # u2 starts at +2 sim units
        assert spin_until(executor, lambda: node.done, 5.0)
        assert node.exit_code == 1 and 'no tip_positions for 0.1 s' in node.diag.message
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == 4)
        assert np.all(commands(probe)[-1][1] == 0.0)


def test_a_restarted_driver_is_a_fault():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u2'], settle_time=0.0)
        assert send_tips(executor, probe, pub, 500 * MS)
        assert send_tips(executor, probe, pub, 0)
        assert node.done and node.exit_code == 1 and 'jumped back' in node.diag.message
        assert commands(probe)[-1][0] == 0 and np.all(commands(probe)[-1][1] == 0.0)


def test_an_excited_tip_moving_too_far_is_a_fault():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u2'], settle_time=0.0,
                                 max_excursion=0.002)
        assert send_tips(executor, probe, pub, 0)
        assert send_tips(executor, probe, pub, MS, REST + [[0.0, 0.001, 0.0]])
        assert not node.done
        assert send_tips(executor, probe, pub, 2 * MS, REST + [[0.0, 0.003, 0.0]])
        assert node.done and node.exit_code == 1 and 'max_excursion' in node.diag.message
        assert np.all(commands(probe)[-1][1] == 0.0)


def test_shutdown_answers_the_next_tips_with_zero():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u2'], settle_time=0.0, stop_wait=5.0)
        assert send_tips(executor, probe, pub, 0)
        pub.publish(cv.tips_to_msg(MS, REST))        # arrives while the node shuts down
        node.close()
        assert node.stopped
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == 2)
        stamp, u = commands(probe)[-1]
        assert stamp == MS and np.all(u == 0.0)


def test_timer_timing_publishes_on_the_clock_and_stops_with_zero():
    with ros_context() as (ctx, executor):
        node, probe, pub = start(ctx, executor, signals=['u1'], duration=0.2, settle_time=0.0,
                                 timing='timer', period=0.01)
        pub.publish(cv.tips_to_msg(0, REST))
        assert spin_until(executor, lambda: node.done, 10.0)
        assert spin_until(executor, lambda: np.all(commands(probe)[-1][1] == 0.0), 5.0)
        got = commands(probe)
        stamps = np.array([s for s, _ in got])
        assert len(got) >= 5 and np.all(np.diff(stamps) > 0)
        assert (stamps[-1] - stamps[0]) / 1e9 >= 0.2 and np.all(got[-1][1] == 0.0)
        assert any(np.any(u != 0.0) for _, u in got) and node.exit_code == 0


@pytest.mark.parametrize('params, message', [
    (dict(signals=['u9']), "unknown signal 'u9'"),
    (dict(spec_file='/no/such.yaml', signals=['mine']), 'signal file /no/such.yaml does not exist'),
    (dict(finger=2), "parameter 'finger': 2 is not a finger of finger_names ['finger_0']"),
])
def test_bad_parameters_stop_the_node_at_start_up(params, message):
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ExcitationNode(context=ctx,
                           parameter_overrides=overrides(finger_names=['finger_0'], **params))
        assert message in str(info.value)
