"""What the nodes share: the executor choice, the latency window, a stepping loop's timing, the
in-place message filler."""
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rosutil import Probe, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import (
    EXECUTOR_ENV,
    LatencyWindow,
    SteppingTiming,
    flush,
    make_executor,
)
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TORQUE_COMMANDS


def test_latency_window_summarises_the_last_samples_in_microseconds():
    w = LatencyWindow(size=100)
    assert w.summary('x') == {}
    for ms in range(1, 101):                       # 1 … 100 ms
        w.add(ms * 1e-3)
    s = w.summary('lat_us')
    assert s == {'lat_us_p50': f'{np.percentile(np.arange(1, 101) * 1e3, 50):.0f}',
                 'lat_us_p99': f'{np.percentile(np.arange(1, 101) * 1e3, 99):.0f}',
                 'lat_us_max': '100000'}
    for _ in range(100):                           # the window forgets what it no longer holds
        w.add(2e-6)
    assert w.summary('lat_us') == {'lat_us_p50': '2', 'lat_us_p99': '2', 'lat_us_max': '2'}
    assert w.count == 200
    for ms in (7, 9):                              # the newest samples only, across the ring's end
        w.add(ms * 1e-3)
    assert w.summary('new_us', last=2) == {'new_us_p50': '8000', 'new_us_p99': '8980',
                                           'new_us_max': '9000'}
    assert w.summary('new_us', last=0) == {} and w.summary('all', last=10**6)['all_max'] == '9000'


def test_executor_is_events_unless_asked_otherwise(monkeypatch):
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        monkeypatch.delenv(EXECUTOR_ENV, raising=False)
        assert 'EventsExecutor' in type(make_executor(context=ctx)).__name__
        monkeypatch.setenv(EXECUTOR_ENV, 'single')
        assert type(make_executor(context=ctx)).__name__ == 'SingleThreadedExecutor'
        monkeypatch.setenv(EXECUTOR_ENV, 'threads')
        with pytest.raises(ValueError, match=f'{EXECUTOR_ENV}=.threads.'):
            make_executor(context=ctx)
    finally:
        rclpy.try_shutdown(context=ctx)


def test_messages_refilled_in_place_read_back_as_new_ones():
    rng = np.random.default_rng(0)
    tips_msg = cv.tips_to_msg(0, np.zeros((4, 3)))
    for k in range(1, 4):
        tips = rng.standard_normal((4, 3))
        ns = k * 1_000_000 + 3 * cv.NS
        cv.fill_tips(tips_msg, ns, tips)
        stamp, back = cv.msg_to_tips(tips_msg, 4)
        assert stamp == ns and np.array_equal(back, tips)
        assert cv.tips_to_msg(ns, tips) == tips_msg   # the same message field by field


def test_names_in_any_order_are_sorted_and_bad_names_still_refused():
    u = np.arange(8.0).reshape(4, 2)
    msg = cv.torques_to_msg(5, u)
    assert np.array_equal(cv.msg_to_torques(msg, 4)[1], u)       # our own order: the fast path
    shuffled = JointState(name=msg.name[::-1], effort=msg.effort[::-1])
    assert np.array_equal(cv.msg_to_torques(shuffled, 4)[1], u)
    with pytest.raises(cv.MessageError, match='duplicate'):
        cv.msg_to_torques(JointState(name=[msg.name[0]] * 8, effort=[0.0] * 8), 4)
    with pytest.raises(cv.MessageError, match='missing'):
        cv.msg_to_torques(JointState(name=msg.name[:6], effort=[0.0] * 6), 4)
    # the cached names are never handed out for a caller to mutate
    names = cv.torque_names(4)
    names.append('x')
    assert len(cv.torques_to_msg(0, u).name) == 8


def test_flush_returns_once_the_reliable_subscriber_has_everything():
    with ros_context('events') as (ctx, executor):
        sender, receiver = Probe(ctx, 'sender'), Probe(ctx, 'receiver')
        receiver.listen(JointState, TORQUE_COMMANDS, LOOP_QOS)
        got = receiver.received[TORQUE_COMMANDS]
        pub = sender.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        executor.add_node(receiver)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 10.0)
        for k in range(20):
            pub.publish(cv.torques_to_msg(k, np.zeros((4, 2))))
        assert flush(sender, timeout=5.0)            # acknowledged by the reader's DDS history
        assert spin_until(executor, lambda: len(got) == 20, 5.0)
        sender.destroy_node()


def test_diagnostics_are_stamped_with_wall_time_and_named_by_the_full_node_name():
    """/diagnostics is published on a wall timer, so its stamp is wall time (the loop topics carry
    sim time); the status is named by the node's namespace and name."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray

    from soft_gripper_sdre.nodes.common import Diagnostics
    from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS
    with ros_context('events') as (ctx, executor):
        node = rclpy.create_node('diag_source', namespace='/left_hand', context=ctx)
        diag = Diagnostics(node, period=0.05)
        diag.count('steps', 3)
        listener = Probe(ctx, 'listener')
        listener.listen(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
        executor.add_node(node)
        executor.add_node(listener)
        got = listener.received[DIAGNOSTICS]
        before = time.time()
        assert spin_until(executor, lambda: len(got) >= 2, 10.0)
        stamp = got[-1].header.stamp.sec + got[-1].header.stamp.nanosec * 1e-9
        assert before - 5.0 < stamp < time.time() + 1.0
        status = got[-1].status[0]
        assert status.name == '/left_hand/diag_source'
        assert {kv.key: kv.value for kv in status.values}['steps'] == '3'


def test_stepping_timing_reports_the_real_time_factor_cpu_per_step_and_latencies():
    clocks = {'wall': 100.0, 'cpu': 5.0, 'perf': 0.0}
    timing = SteppingTiming(4, wall=lambda: clocks['wall'], cpu=lambda: clocks['cpu'],
                            perf=lambda: clocks['perf'])
    assert timing.report(0.0, 0) == {}                       # not started, nothing answered
    timing.start()
    for k in range(6):                                       # the ring wraps: k % 4
        clocks['perf'] = k * 1.0
        timing.tips_sent(k)
        clocks['perf'] += 0.001 * (k + 1)                    # answered after (k + 1) ms
        timing.answered(k)
    clocks['wall'], clocks['cpu'] = 102.0, 5.5
    out = timing.report(1.0, 500)                            # 1 s of sim time in 2 s of wall time
    assert out['real_time_factor'] == '0.5000' and out['cpu_per_step_us'] == '1000'
    assert out['loop_latency_us_max'] == '6000' and out['recent_latency_us_max'] == '6000'
    timing.finish()
    clocks['wall'] = 200.0                                   # after the end, the run's figures stay
    again = timing.report(1.0, 500)
    assert again['real_time_factor'] == '0.5000' and 'recent_latency_us_p50' not in again


def test_stepping_timing_reports_the_first_command_accepted_after_the_start():
    clocks = {'wall': 100.0}
    timing = SteppingTiming(4, wall=lambda: clocks['wall'])
    timing.accepted(0)                                       # before the start: not counted
    assert 'first_command_monotonic_s' not in timing.report(0.0, 0)
    timing.start()
    clocks['wall'] = 100.25
    timing.accepted(1)
    assert 'step_period_us' not in timing.report(0.001, 1)   # no step since it
    clocks['wall'] = 101.0
    timing.accepted(2)                                       # the later ones change nothing
    out = timing.report(0.0, 0)
    assert out['first_command_monotonic_s'] == '100.250000'
    assert out['first_command_after_tips_ms'] == '250.0'
    clocks['wall'] = 101.25
    timing.finish()                                          # 500 steps in all, 499 in 1 s
    clocks['wall'] = 300.0
    out = timing.report(0.5, 500)
    assert out['step_period_us'] == '2004'                   # 1 s / 499, the 250 ms wait left out
    assert out['real_time_factor'] == '0.4000'               # 0.5 s of sim time in 1.25 s
