"""The simulator node over real DDS (loopback), launch-free: own Context, executor, test node."""
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosutil import Probe, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.simulator import SimulatorNode
from soft_gripper_sdre.nodes.topics import (
    DIAGNOSTICS,
    LOOP_QOS,
    STREAM_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)

pytestmark = pytest.mark.ros

#: the finger scene: one finger, exposed under its default name
FINGER_SCENE = dict(scene='finger', finger_names=['finger_0'], hand_fingers=[0])


def make_loop(ctx, executor, **params):
    """Simulator (finger scene) + a probe that answers each tip message with a command."""
    sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
        **FINGER_SCENE, startup_timeout=20.0, **params))
    probe = Probe(ctx)
    probe.listen(PoseArray, TIP_POSITIONS, LOOP_QOS)
    probe.listen(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
    pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
    executor.add_node(sim)
    executor.add_node(probe)
    assert spin_until(executor, lambda: pub.get_subscription_count() > 0 and sim.stepping.started
                      and probe.received[TIP_POSITIONS], 20.0)
    return sim, probe, pub


def answer_tips(executor, probe, pub, u, steps, start=0):
    """Lockstep partner: for each tip message stamped t_k publish u stamped t_k."""
    tips = probe.received[TIP_POSITIONS]
    for k in range(start, start + steps):
        assert spin_until(executor, lambda: len(tips) > k, 5.0), f'no tip message {k}'
        stamp, _ = cv.msg_to_tips(tips[k], 1)
        pub.publish(cv.torques_to_msg(stamp, np.asarray(u, dtype=float)))
    assert spin_until(executor, lambda: len(tips) > start + steps, 5.0)
    return cv.msg_to_tips(tips[start + steps], 1)


@pytest.mark.parametrize('u, tip_axis, sign', [
    ([[0.01, 0.0]], 1, -1), ([[-0.01, 0.0]], 1, +1), ([[0.0, 0.01]], 0, +1),
    ([[0.0, -0.01]], 0, -1)])
def test_finger_moves_the_expected_way_in_lockstep(u, tip_axis, sign):
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor)
        rest = cv.msg_to_tips(probe.received[TIP_POSITIONS][0], 1)[1][0]
        stamp, tip = answer_tips(executor, probe, pub, u, 150)
        assert stamp == 150 * 1_000_000                   # lockstep: exactly one step per command
        assert sim.diag.counters['timeouts'] == 0
        d = tip[0] - rest
        assert np.sign(d[tip_axis]) == sign and abs(d[tip_axis]) > 2e-4


@pytest.mark.parametrize('mode', ['lockstep', 'pipelined'])
def test_lockstep_holds_on_a_timeout_then_steps_lost_periods_with_zero_until_commands_return(mode):
    from rclpy.parameter import Parameter

    from soft_gripper_sdre.nodes.common import ERROR, OK
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, mode=mode, lockstep_timeout=0.05,
                                    on_timeout='hold', lost_command_wait=5.0)
        answer_tips(executor, probe, pub, [[0.02, 0.0]], 5)
        c = sim.diag.counters
        assert spin_until(executor, lambda: c['timeouts'] == 1, 10.0)          # no deadlock
        assert 'command timeout at t = 0.005 s' in sim.diag.message            # the period awaited
        np.testing.assert_allclose(sim.sim.truth().u_applied, [[0.02, 0.0]])   # the timeout holds
        assert c['safe_periods'] == 0
        assert sim.set_parameters([Parameter('lost_command_wait', value=0.005)])[0].successful
        # lost: zero, period by period
        assert spin_until(executor, lambda: c['safe_periods'] >= 5, 10.0)
        assert c['timeouts'] == 1
        np.testing.assert_array_equal(sim.sim.truth().u_applied, 0.0)
        assert sim.diag.level == ERROR and 'zero torque' in sim.diag.message
        k = sim.stepping.k                                                  # a command returns
        pub.publish(cv.torques_to_msg(k * 1_000_000, np.array([[0.01, 0.0]])))
        assert spin_until(executor, lambda: c['commands'] == 6, 5.0)
        assert not sim.stepping.lost and sim.diag.level == OK


def pattern(k: int) -> np.ndarray:
    """A torque of its own for each period k, within the actuator limit."""
    return np.array([[0.03 * np.sin(0.3 * k + 0.5), 0.02 * np.cos(0.2 * k)]])


def replay(config, torques) -> np.ndarray:
    """The tips a fresh simulator with ``config`` measures before each of the steps ``torques``
    and after the last."""
    from soft_gripper_sdre.sim.hand import GripperSim
    with GripperSim(config) as sim:
        tips = [sim.measure()]
        for u in torques:
            sim.step(u)
            tips.append(sim.measure())
    return np.array(tips)


def test_pipelined_steps_the_physics_with_the_command_that_answered_the_previous_tips():
    """The tips of t_k go out before the physics steps from t_k to t_(k+1), with the command
    stamped t_(k−1): a fresh simulator given zero, then the answers to t_0, t_1, … measures
    exactly the published tips; given the answers in lockstep's order it does not."""
    steps = 30
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, mode='pipelined', lockstep_timeout=5.0)
        tips = probe.received[TIP_POSITIONS]
        for k in range(steps):
            assert spin_until(executor, lambda: len(tips) > k, 5.0), f'no tip message {k}'
            stamp, _ = cv.msg_to_tips(tips[k], 1)
            assert stamp == k * 1_000_000
            pub.publish(cv.torques_to_msg(stamp, pattern(k)))
        assert spin_until(executor, lambda: len(tips) > steps, 5.0)
        assert sim.diag.counters['timeouts'] == 0 and sim.stepping.k == steps
        # the physics is a period ahead of the newest tips, driven by the answer to t_(steps−1)
        np.testing.assert_array_equal(sim.sim.truth().u_applied, pattern(steps - 1))
        assert sim.sim.t == pytest.approx((steps + 1) * 1e-3)
        published = np.array([cv.msg_to_tips(m, 1)[1] for m in tips[:steps + 1]])
        config = sim.sim.config
    answers = [pattern(k) for k in range(steps)]
    np.testing.assert_array_equal(published, replay(config, [np.zeros((1, 2))] + answers[:-1]))
    lockstep_order = replay(config, answers)
    assert not np.array_equal(published, lockstep_order)
    assert np.abs(published - lockstep_order).max() > 1e-7    # more than rounding: a period's drift


def test_pipelined_run_ends_with_the_physics_at_its_duration():
    """The final command is not applied: the physics stops at t_N, as in lockstep."""
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, mode='pipelined', duration=0.01)
        answer_tips(executor, probe, pub, [[0.01, 0.0]], 10)
        assert sim.done and sim.stepping.k == 10 and sim.sim.t == pytest.approx(0.01)
        assert sim.diag.counters['steps'] == 10 and sim.diag.counters['commands'] == 10


def test_lockstep_timeout_with_zero_policy_applies_zero():
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, lockstep_timeout=0.05, on_timeout='zero')
        answer_tips(executor, probe, pub, [[0.02, 0.0]], 3)
        assert spin_until(executor, lambda: sim.diag.counters['safe_periods'] >= 2, 10.0)
        assert sim.diag.counters['timeouts'] == 1
        np.testing.assert_array_equal(sim.sim.truth().u_applied, 0.0)


def test_bad_commands_are_rejected_counted_and_never_stepped():
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, lockstep_timeout=5.0)
        answer_tips(executor, probe, pub, [[0.01, 0.0]], 2)
        now = 2 * 1_000_000
        bad = []
        m = cv.torques_to_msg(now, np.array([[np.nan, 0.0]]))
        bad.append(m)
        m = cv.torques_to_msg(now, np.array([[0.0, 0.0]]))
        m.effort = [0.0]                                   # wrong length
        bad.append(m)
        m = cv.torques_to_msg(now, np.array([[0.0, 0.0]]))
        m.name = ['finger_0/ax0', 'finger_9/ax1']          # unknown name
        bad.append(m)
        m = cv.torques_to_msg(now, np.array([[0.0, 0.0]]))
        m.name = ['finger_0/ax0', 'finger_0/ax0']          # duplicate
        bad.append(m)
        bad.append(cv.torques_to_msg(1 * 1_000_000, np.array([[0.0, 0.0]])))   # old stamp
        bad.append(cv.torques_to_msg(9 * 1_000_000, np.array([[0.0, 0.0]])))   # future stamp
        c = sim.diag.counters
        for i, m in enumerate(bad):        # one at a time: the simulator keeps only the newest
            pub.publish(m)
            assert spin_until(executor, lambda: c['bad_command'] + c['stale_command']
                              + c['future_command'] > i, 10.0)
        assert c['bad_command'] == 4 and c['stale_command'] == 1 and c['future_command'] == 1
        assert sim.stepping.k == 2                          # none of them stepped the simulator
        assert np.all(np.isfinite(sim.sim.truth().q))
        # a good command still works afterwards
        pub.publish(cv.torques_to_msg(now, np.array([[0.01, 0.0]])))
        assert spin_until(executor, lambda: sim.stepping.k == 3, 5.0)


def test_duration_stops_the_simulator():
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, duration=0.01)
        answer_tips(executor, probe, pub, [[0.0, 0.0]], 10)
        assert sim.done and sim.stepping.k == 10


def test_realtime_mode_steps_without_commands():
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor, mode='realtime', control_period=0.002)
        assert spin_until(executor, lambda: sim.stepping.k >= 20, 10.0)
        assert sim.diag.counters['late_periods'] >= 20


@pytest.mark.parametrize('params, name', [
    (dict(mode='warp'), "'mode': mode must be one of .*'pipelined'.*got 'warp'"),
    (dict(control_period=-0.001), 'control_period'),
    (dict(noise_std=1.0), 'noise_std'), (dict(scene='arm'), 'scene'),
    (dict(physics_substeps=1.5), 'physics_substeps'), (dict(scene='finger'), 'hand_fingers'),
    (dict(finger_names=['a', 'b'], hand_fingers=[0, 0]), 'hand_fingers'),
    (dict(finger_names=['a', 'b'], hand_fingers=[0, 4]), 'hand_fingers'),
    (dict(finger_names=['left', 'left']), 'finger_names'),
    (dict(finger_names=['0left']), 'finger_names')])
def test_bad_parameters_fail_at_startup_naming_the_parameter(params, name):
    with ros_context() as (ctx, executor):
        with pytest.raises(ParameterError, match=name):
            SimulatorNode(context=ctx, parameter_overrides=overrides(**params))


def test_runtime_parameter_refusal_keeps_the_old_value():
    from rclpy.parameter import Parameter
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx,
                            parameter_overrides=overrides(**FINGER_SCENE, startup_timeout=0.0))
        executor.add_node(sim)
        res = sim.set_parameters([Parameter('on_timeout', value='explode')])[0]
        assert not res.successful and 'on_timeout' in res.reason
        assert sim.get_parameter('on_timeout').value == 'hold'
        res = sim.set_parameters([Parameter('scene', value='hand')])[0]
        assert not res.successful


def test_diagnostics_report_the_loop_latency_of_every_answered_period():
    with ros_context() as (ctx, executor):
        sim, probe, pub = make_loop(ctx, executor)
        answer_tips(executor, probe, pub, [[0.0, 0.0]], 20)
        assert sim.timing.latency.count == 20       # one sample per period answered in lockstep
        sim.diag.publish()

        def latest():
            for msg in reversed(probe.received[DIAGNOSTICS]):
                for status in msg.status:
                    values = {kv.key: kv.value for kv in status.values}
                    if status.name.endswith('simulator') and values.get('sim_time') == '0.020':
                        return values
            return None
        assert spin_until(executor, lambda: latest() is not None, 5.0)
        v = latest()
        p50, p99, top = (float(v[f'loop_latency_us_{k}']) for k in ('p50', 'p99', 'max'))
        assert 0 < p50 <= p99 <= top
        assert float(v['real_time_factor']) > 0
