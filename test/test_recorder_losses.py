"""The recorder counts the messages missing from each stream by its publisher's stamps, WARNs with
the counts in its log and reports them in /diagnostics (WARN while losses grow, OK again after a
report without a new one). Real DDS (loopback): a publisher that skips messages, the recorder in
this process and as its own process."""
import os
import signal
import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.recorder import PERIOD_WINDOW, GapCounter, RecorderNode, topic_qos
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS, TIP_POSITIONS, TORQUE_COMMANDS

pytestmark = pytest.mark.ros

MS = 1_000_000
TIPS = np.zeros((4, 3))
TORQUES = np.zeros((4, 2))


def _counts(stamps) -> list[int]:
    counter = GapCounter()
    return [counter.add(s) for s in stamps]


def test_a_regular_stream_loses_nothing_and_a_skip_counts_the_periods_it_skipped():
    stamps = [k * MS for k in range(100)]
    assert sum(_counts(stamps)) == 0
    skipped = [s for s in stamps if not 40 <= s // MS < 48]
    lost = _counts(skipped)
    assert sum(lost) == 8 and lost[40] == 8
    counter = GapCounter()
    for s in skipped:
        counter.add(s)
    assert counter.lost == 8 and counter.gaps == 1 and counter.period == MS


def test_jitter_under_one_and_a_half_periods_is_no_loss_and_the_period_follows_the_stream():
    rng = np.random.default_rng(3)
    stamps = np.cumsum(rng.uniform(0.6, 1.4, 300) * 5 * MS).astype(int)     # 200 Hz, jittery
    assert sum(_counts(stamps)) == 0
    # 1 kHz, then 100 Hz: once the window holds the new rate, nothing more is lost
    stamps = [k * MS for k in range(100)] + [100 * MS + k * 10 * MS for k in range(1, 200)]
    counter = GapCounter()
    lost = [counter.add(s) for s in stamps]
    assert counter.period == 10 * MS
    assert sum(lost[100 + PERIOD_WINDOW:]) == 0


def test_a_step_over_a_second_and_a_hundred_periods_is_a_jump_not_a_loss():
    """A half-second hole at 1 kHz is 499 lost messages; a stamp 5 s or 2⁶² ns ahead (a clock
    set forward, a bad stamp) is a jump the stream starts afresh from; at 10 Hz a 1.5 s hole is
    still losses (under 100 periods)."""
    counter = GapCounter()
    stamps = [k * MS for k in range(20)] + [519 * MS] + [5519 * MS + k * MS for k in range(20)]
    lost = [counter.add(s) for s in stamps]
    assert lost[20] == 499 and counter.lost == 499 and counter.jumps == 1
    assert sum(lost[21:]) == 0 and counter.period == MS
    assert counter.add(2**62) == 0 and counter.jumps == 2 and counter.jumped
    assert counter.add(2**62 + MS) == 0 and not counter.jumped
    slow = GapCounter()
    for k in range(20):
        slow.add(k * 100 * MS)
    assert slow.add(19 * 100 * MS + 1500 * MS) == 14 and slow.jumps == 0


def test_a_long_hole_whose_stamps_kept_pace_with_their_arrivals_is_losses():
    """A recorder starved for 2.5 s (or a publisher that stalled that long): the stamps after the
    hole advanced as the arrival clock did, so its periods are lost messages, not a jump; the
    same step arriving 1 ms after its predecessor is a jump."""
    counter = GapCounter()
    for k in range(20):
        counter.add(k * MS, received=k * MS)
    assert counter.add(2519 * MS, received=2519 * MS + 3 * MS) == 2499
    assert counter.jumps == 0 and counter.lost == 2499
    for k in range(2520, 2540):
        counter.add(k * MS, received=k * MS)
    assert counter.add(7539 * MS, received=2540 * MS) == 0 and counter.jumps == 1


def test_a_restarted_publisher_and_repeats_are_no_loss():
    stamps = [k * MS for k in range(50)] + [k * MS for k in range(50)] + [49 * MS]
    assert sum(_counts(stamps)) == 0
    counter = GapCounter()
    for s in range(5):                      # fewer steps than it learns from: nothing is judged
        counter.add(s * 100 * MS if s == 4 else s * MS)
    assert counter.period is None and counter.lost == 0


def _status(msgs, name='/recorder') -> DiagnosticStatus | None:
    """The newest status of ``name`` among received DiagnosticArrays."""
    found = [s for m in msgs for s in m.status if s.name == name]
    return found[-1] if found else None


def _value(status: DiagnosticStatus, key: str) -> str | None:
    return next((kv.value for kv in status.values if kv.key == key), None)


def test_losses_are_counted_per_topic_and_reported_while_they_grow(tmp_path):
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), topics=[TIP_POSITIONS, TORQUE_COMMANDS]))
        probe = Probe(ctx)
        tips = probe.create_publisher(PoseArray, TIP_POSITIONS, deep(topic_qos(TIP_POSITIONS)))
        torques = probe.create_publisher(JointState, TORQUE_COMMANDS,
                                           deep(topic_qos(TORQUE_COMMANDS)))
        probe.listen(DiagnosticArray, DIAGNOSTICS, deep(STREAM_QOS))
        executor.add_node(rec)
        executor.add_node(probe)
        assert spin_until(executor, lambda: tips.get_subscription_count() > 0
                          and torques.get_subscription_count() > 0, 20.0)

        def send(ks_tips, ks_torques):
            sent = rec.counts['/tip_positions'] + len(ks_tips)
            sent_t = rec.counts['/torque_commands'] + len(ks_torques)
            for k in ks_tips:
                tips.publish(cv.tips_to_msg(k * MS, TIPS))
            for k in ks_torques:
                torques.publish(cv.torques_to_msg(k * MS, TORQUES))
            assert spin_until(executor, lambda: rec.counts['/tip_positions'] == sent
                              and rec.counts['/torque_commands'] == sent_t, 10.0)

        send([k for k in range(100) if not 40 <= k < 48],
             [k for k in range(100) if k not in (70, 71)])
        assert rec.gaps['/tip_positions'].lost == 8 and rec.gaps['/torque_commands'].lost == 2
        assert rec.diag.counters['lost /tip_positions'] == 8
        assert rec.diag.counters['lost /torque_commands'] == 2
        diags = probe.received[DIAGNOSTICS]
        n = len(diags)
        rec.diag.publish()
        assert spin_until(executor, lambda: len(diags) > n, 5.0)
        status = _status(diags)
        assert status.level == DiagnosticStatus.WARN
        assert ('10 message(s) lost since the last report; lost in all: /tip_positions 8, '
                '/torque_commands 2') in status.message
        assert _value(status, 'lost /tip_positions') == '8'
        assert _value(status, 'period /tip_positions') == '1.000 ms'

        send(range(100, 130), range(100, 130))              # no new loss: back to OK
        n = len(diags)
        rec.diag.publish()
        assert spin_until(executor, lambda: len(diags) > n, 5.0)
        status = _status(diags)
        assert status.level == DiagnosticStatus.OK, status.message
        assert '10 message(s) lost earlier' in status.message
        assert _value(status, 'lost /tip_positions') == '8'

        send([135], [])                                     # 5 more: WARN again
        n = len(diags)
        rec.diag.publish()
        assert spin_until(executor, lambda: len(diags) > n, 5.0)
        assert _status(diags).level == DiagnosticStatus.WARN
        assert _value(_status(diags), 'lost /tip_positions') == '13'


def test_a_topic_with_two_publishers_is_not_judged(tmp_path):
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), topics=[TIP_POSITIONS]))
        probe = Probe(ctx)
        a = probe.create_publisher(PoseArray, TIP_POSITIONS, deep(topic_qos(TIP_POSITIONS)))
        b = probe.create_publisher(PoseArray, TIP_POSITIONS, deep(topic_qos(TIP_POSITIONS)))
        executor.add_node(rec)
        executor.add_node(probe)
        sub = rec._subs['/tip_positions']
        assert spin_until(executor, lambda: sub.get_publisher_count() == 2
                          and rec._single.get('/tip_positions') is False, 20.0)
        for k in range(40):                 # two streams interleaved: 0, 500, 1, 501, ...
            a.publish(cv.tips_to_msg(k * MS, TIPS))
            b.publish(cv.tips_to_msg((500 + k) * MS, TIPS))
        assert spin_until(executor, lambda: rec.counts['/tip_positions'] == 80, 10.0)
        assert rec.diag.counters['lost /tip_positions'] == 0


def test_a_recorder_process_warns_with_counts_in_its_log_and_diagnostics(tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.recorder',
                             '--ros-args', '-p', f'output:={tmp_path / "bag"}',
                             '-p', 'topics:=[tip_positions]'], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with ros_context() as (ctx, executor):
            probe = Probe(ctx)
            tips = probe.create_publisher(PoseArray, TIP_POSITIONS, deep(topic_qos(TIP_POSITIONS)))
            probe.listen(DiagnosticArray, DIAGNOSTICS, deep(STREAM_QOS))
            executor.add_node(probe)
            assert spin_until(executor, lambda: tips.get_subscription_count() > 0, 60.0)
            for k in range(200):
                if not 100 <= k < 105:
                    tips.publish(cv.tips_to_msg(k * MS, TIPS))
            diags = probe.received[DIAGNOSTICS]

            def reported():
                status = _status(diags)
                return status is not None and _value(status, 'lost /tip_positions') == '5'
            assert spin_until(executor, reported, 10.0)
            status = _status(diags)
            assert status.level == DiagnosticStatus.WARN, status.message
            assert _value(status, 'messages /tip_positions') == '195'
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert ('/tip_positions: 5 message(s) missing between stamps 0.099000 and 0.105000 s '
            '(period 1.000 ms); 5 lost of this topic in all') in err
    assert ('messages missing from the streams (stamp gaps): /tip_positions 5 in 1 gap(s)'
            in err)


def test_a_stamp_jump_is_reported_at_warn_and_the_stream_judged_afresh(tmp_path):
    """A tip 5 s ahead of its stream: /diagnostics at WARN naming the jump, no message counted
    lost; the stream's period learned again from the stamps after it (its gaps counted again);
    OK after a report without a new jump."""
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), topics=[TIP_POSITIONS]))
        probe = Probe(ctx)
        tips = probe.create_publisher(PoseArray, TIP_POSITIONS, deep(topic_qos(TIP_POSITIONS)))
        probe.listen(DiagnosticArray, DIAGNOSTICS, deep(STREAM_QOS))
        executor.add_node(rec)
        executor.add_node(probe)
        assert spin_until(executor, lambda: tips.get_subscription_count() > 0, 20.0)

        def send(ks):
            sent = rec.counts['/tip_positions'] + len(ks)
            for k in ks:
                tips.publish(cv.tips_to_msg(k * MS, TIPS))
            assert spin_until(executor, lambda: rec.counts['/tip_positions'] == sent, 10.0)

        def report() -> DiagnosticStatus:
            diags = probe.received[DIAGNOSTICS]
            n = len(diags)
            rec.diag.publish()
            assert spin_until(executor, lambda: len(diags) > n, 5.0)
            return _status(diags)

        send(range(50))
        send(range(5050, 5100))                              # 5 s ahead, then 1 kHz again
        gaps = rec.gaps['/tip_positions']
        assert gaps.jumps == 1 and gaps.lost == 0 and gaps.period == MS
        assert rec.diag.counters['jumps /tip_positions'] == 1
        status = report()
        assert status.level == DiagnosticStatus.WARN
        assert '1 stamp jump(s) over 1 s' in status.message and 'lost' not in status.message
        send([k for k in range(5100, 5140) if k != 5120])    # judged again: one lost
        assert gaps.lost == 1
        assert '1 message(s) lost since the last report' in report().message
        send(range(5140, 5160))
        status = report()
        assert status.level == DiagnosticStatus.OK
        assert '1 message(s) lost earlier and 1 stamp jump(s)' in status.message
