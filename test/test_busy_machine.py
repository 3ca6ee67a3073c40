"""Loud on a busy machine, over real DDS: a controller that falls behind, an estimator whose tips
jump forward past reset_on_jump, a driver that zeroes a stale command or ticks late: each WARNs
in /diagnostics and in the log (/rosout) with its counts; and the command lines say so."""
import os
import subprocess
import sys
import time

from node_harness import MS, commands, estimate, horizon, make_controller, make_estimator
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rosutil import Probe, deep, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import OK, WARN
from soft_gripper_sdre.nodes.controller import SKIP_WARN_MIN
from soft_gripper_sdre.nodes.plant_driver import PlantDriverNode
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TORQUE_COMMANDS

pytestmark = pytest.mark.ros


def rosout(ctx, executor, *names):
    """A probe recording the WARN-or-worse /rosout lines of the nodes ``names``."""
    probe = Probe(ctx, 'log_reader')
    lines = []
    probe.create_subscription(Log, '/rosout', lambda m: lines.append(m.msg)
                              if m.level >= Log.WARN and m.name in names else None,
                              deep(LOOP_QOS, 1000))
    executor.add_node(probe)
    return lines


def test_a_controller_that_skips_many_estimates_warns_with_the_counts_then_recovers():
    rest = np.repeat(SDCModel().rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(ctx, executor)
        lines = rosout(ctx, executor, 'controller')
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        got = commands(probe)

        def play(stamps):
            for s in stamps:
                before = len(got)
                est_pub.publish(estimate(s, rest))
                assert spin_until(executor, lambda: len(got) > before, 5.0)

        play(range(0, 20 * MS, MS))          # every period answered
        node.diag.publish()
        assert node.diag.level == OK and node.diag.values['skipped_share'] == '0.000'
        play(range(20 * MS, 80 * MS, 2 * MS))  # every other period skipped: 29 of 59
        node.diag.publish()
        assert node.diag.level == WARN
        assert 'falling behind: 29 of 59 estimates skipped' in node.diag.message
        assert node.diag.counters['skipped_estimates'] == 29
        play(range(80 * MS, 100 * MS, MS))    # (78 → 80 ms skips one more)
        node.diag.publish()
        assert node.diag.level == OK and '30 estimates skipped earlier' in node.diag.message
        play([400 * MS])                      # a forward jump over reset_on_jump (0.1 s)
        assert node.diag.counters['estimate_jumps'] == 1
        assert spin_until(executor, lambda: any('jumped forward by 301.0 ms' in m for m in lines),
                          5.0)
        assert any('falling behind: 29 of 59' in m for m in lines)


def test_a_few_skipped_estimates_stay_quiet():
    rest = np.repeat(SDCModel().rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(ctx, executor)
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        got = commands(probe)
        stamps = [k * MS for k in range(200) if k % 25 != 24]   # 4 % lost upstream
        for s in stamps:
            before = len(got)
            est_pub.publish(estimate(s, rest))
            assert spin_until(executor, lambda: len(got) > before, 5.0)
        node.diag.publish()
        assert 0 < node.diag.counters['skipped_estimates'] < SKIP_WARN_MIN
        assert node.diag.level == OK


def test_the_estimator_resets_on_a_forward_jump_and_says_so_with_the_counts():
    tips = np.zeros((4, 3))
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor)
        lines = rosout(ctx, executor, 'estimator')
        c = node.diag.counters
        for stamp in (0, MS, 2 * MS, 62 * MS, 300 * MS):   # a dropout (60 ms), then 238 ms
            before = c['received']
            pub.publish(cv.tips_to_msg(stamp, tips))
            assert spin_until(executor, lambda: c['received'] > before, 5.0)
        assert (c['dropouts'], c['resets']) == (1, 1) and node.diag.level == WARN
        assert spin_until(executor, lambda: len(lines) >= 2, 5.0), lines
        assert 'predicting through it (1 dropout(s), 59 missed period(s) in all)' in lines[0]
        assert 'jumped forward' in lines[1] and '+238.0 ms' in lines[1]
        assert '(1 reset(s) in all)' in lines[1]


def test_the_driver_warns_on_late_ticks_and_on_zeroing_a_stale_command():
    with ros_context() as (ctx, executor):
        node = PlantDriverNode(context=ctx)
        probe = Probe(ctx)
        cmd_pub = probe.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        executor.add_node(node)
        executor.add_node(probe)
        lines = rosout(ctx, executor, 'plant_driver')
        c = node.diag.counters
        assert spin_until(executor, lambda: cmd_pub.get_subscription_count() > 0
                          and c['ticks'] > 20, 10.0)
        node.diag.publish()
        late = c['late_ticks']
        time.sleep(0.05)                     # the process starved: the next tick is 10 periods late
        assert spin_until(executor, lambda: c['late_ticks'] > late, 5.0)
        node.diag.publish()
        assert node.diag.level == WARN and node.diag.message.startswith('late ticks')
        assert spin_until(executor, lambda: any('late tick(s) in all' in m for m in lines), 5.0)

        u = np.full((2, 2), 0.01)
        cmd_pub.publish(cv.torques_to_msg(time.time_ns(), u, ['index', 'thumb']))
        assert spin_until(executor, lambda: c['commands'] == 1, 5.0)
        assert spin_until(executor, lambda: c['stale_ticks'] > 0, 5.0)   # 50 ms without one
        np.testing.assert_array_equal(node.applied, np.zeros((2, 2)))
        assert node.diag.level == WARN and 'stale' in node.diag.message
        assert spin_until(executor, lambda: any(
            'applying the rest input' in m and 'stale tick(s) in all' in m for m in lines), 5.0)


def _help(*args):
    return subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.controller', *args],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ))


def test_controller_help_names_with_estimator_and_the_composed_help_the_estimators_resets():
    out = _help('--help')
    assert out.returncode == 0 and '[--with-estimator]' in out.stdout.splitlines()[0]
    assert 'also run the estimator node in this process' in out.stdout
    assert 'parameters of the estimator node' not in out.stdout
    composed = _help('--with-estimator', '--help')
    assert composed.returncode == 0, composed.stderr
    text = composed.stdout
    head, estimator = text.split('parameters of the estimator node in this process')
    assert 'reset_on_jump = 0.1' in head and 'behind the last one' in head
    assert 'reset_on_jump set both' in estimator.splitlines()[0]
    assert 'reset_on_jump = 0.1' in estimator and 'either direction' in estimator
    assert 'max_bridge = 0.05' in estimator and 'up to reset_on_jump' in estimator
    assert 'Traceback' not in composed.stderr
