"""The estimator node over real DDS (loopback), launch-free: own Context, executor, test node."""
from pathlib import Path
import time

from geometry_msgs.msg import PoseArray
from node_harness import MS, make_estimator
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import overrides, ros_context, spin_until
import yaml

from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import OK, WARN
from soft_gripper_sdre.nodes.estimator import MESSAGE_OUTCOMES, PARAMS, EstimatorNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.topics import STATE_ESTIMATE

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'estimator.yaml'


def handled(node) -> int:
    """Messages the node has dealt with: each is accepted or rejected under one reason."""
    return sum(node.diag.counters[k] for k in MESSAGE_OUTCOMES)


def send(executor, node, pub, msg) -> None:
    """Publish one tip message and spin until the node has handled it (in-order, reliable)."""
    before = handled(node)
    pub.publish(msg)
    assert spin_until(executor, lambda: handled(node) > before, 5.0), 'tip message not handled'


def estimates(executor, probe, count):
    got = probe.received[STATE_ESTIMATE]
    assert spin_until(executor, lambda: len(got) >= count, 5.0)
    assert len(got) == count
    return [cv.msg_to_estimate(m, 4) for m in got]


def tips(ns, z):
    return cv.tips_to_msg(ns, np.hstack([z, np.full((len(z), 1), 0.1)]))


def test_constant_velocity_is_tracked_exactly_like_the_offline_filter():
    rng = np.random.default_rng(3)
    p0 = np.array([[0.0, -0.002], [0.001, -0.002], [0.0, -0.002], [0.0, 0.0]])
    v = np.array([[0.02, -0.01], [0.0, 0.015], [-0.03, 0.0], [0.005, 0.005]])
    steps, t0, sigma = 400, 7 * MS, 1e-6
    stamps = t0 + MS * np.arange(steps)
    z = p0 + v * (stamps[:, None, None] - t0) / cv.NS + rng.normal(size=(steps, 4, 2)) * sigma
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor)
        for k in range(steps):
            send(executor, node, pub, tips(int(stamps[k]), z[k]))
        got = estimates(executor, probe, steps)
        first = probe.received[STATE_ESTIMATE][0]
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
    kf.reset(z[0])
    offline = [kf.x.copy()] + [kf.step(z[k]) for k in range(1, steps)]
    assert [s for s, _ in got] == stamps.tolist()
    np.testing.assert_array_equal(np.array([x for _, x in got]), np.array(offline))
    assert first == cv.estimate_to_msg(int(stamps[0]), z[0], np.zeros((4, 2)))
    est = np.array([x for _, x in got])
    vel_err = np.abs(est[:, :, 2:] - v).max(axis=(1, 2))
    assert vel_err[0] > 0.02 and vel_err[100:].max() < 2e-3      # from zero velocity to the truth
    truth = p0 + v * (stamps[:, None, None] - t0) / cv.NS
    np.testing.assert_allclose(est[:, :, :2], truth, rtol=0, atol=5 * sigma)
    assert node.diag.counters['gaps'] == node.diag.counters['resets'] == 0


def test_bad_inputs_are_counted_gaps_predicted_and_jumps_reset():
    z = np.array([[0.001, -0.002], [0.0, 0.003], [0.002, 0.0], [0.0, 0.0]])
    v = np.array([[0.01, 0.0], [0.0, -0.01], [0.0, 0.0], [0.02, 0.01]])
    meas = lambda ns: z + v * ns / cv.NS                                       # noqa: E731
    nan = tips(11 * MS, meas(11 * MS))
    nan.poses[2].position.y = float('nan')
    three = tips(11 * MS, meas(11 * MS)[:3])
    five = tips(11 * MS, np.vstack([meas(11 * MS), [[0.0, 0.0]]]))
    empty = PoseArray()
    empty.header.stamp = cv.to_time(11 * MS)
    sequence = ([(k * MS, 'ok') for k in range(10)]
                + [(nan, 'bad_message'), (three, 'bad_message'), (five, 'bad_message'),
                   (empty, 'bad_message'), (8 * MS, 'out_of_order'), (5 * MS, 'out_of_order'),
                   (9 * MS, 'duplicate'), (10 * MS, 'ok'), (13 * MS, 'gap'),
                   (13 * MS + MS // 2, 'off_grid'), (0, 'reset'), (60 * MS, 'reset'),
                   (61 * MS, 'ok')])
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
    expected = []
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor, reset_on_jump=0.01)
        for item, kind in sequence:
            if not isinstance(item, int):
                send(executor, node, pub, item)
                continue
            send(executor, node, pub, tips(item, meas(item)))
            if kind in ('out_of_order', 'duplicate'):
                continue
            if kind == 'reset' or not expected:
                kf.reset(meas(item))
                x = kf.x.copy()
            else:
                if kind == 'gap':
                    kf.step(meas(item), np.zeros(4, dtype=bool))
                    kf.step(meas(item), np.zeros(4, dtype=bool))
                x = kf.step(meas(item), dt=MS / 2 / cv.NS if kind == 'off_grid' else None)
            expected.append((item, x))
        got = estimates(executor, probe, len(expected))
        c = node.diag.counters
        assert (c['bad_message'], c['out_of_order'], c['duplicate'], c['gaps'], c['missed_periods'],
                c['resets'], c['dropouts']) == (4, 2, 1, 1, 2, 2, 0)
        assert c['estimates'] == len(expected) == 16
        assert c['received'] == len(sequence) == sum(c[k] for k in MESSAGE_OUTCOMES)
    assert [s for s, _ in got] == [s for s, _ in expected]
    np.testing.assert_array_equal(np.array([x for _, x in got]), np.array([x for _, x in expected]))
    reset_at_zero = dict(got)[0]
    np.testing.assert_array_equal(reset_at_zero[:, 2:], 0.0)   # a reset starts at zero velocity


def test_a_node_that_fell_behind_takes_only_the_newest_tips_and_predicts_through_the_rest():
    """Tips that queued while the node could not run: it goes on from the newest (its reader
    keeps one message), predicting through the skipped periods, instead of working off a queue."""
    z = np.array([[0.001, -0.002], [0.0, 0.003], [0.002, 0.0], [0.0, 0.0]])
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor)
        send(executor, node, pub, tips(0, z))
        for k in range(1, 21):                       # the node's executor does not run meanwhile
            pub.publish(tips(k * MS, z))
        time.sleep(0.3)
        spin_until(executor, lambda: False, 0.5)
        c = node.diag.counters
        assert (c['estimates'], c['gaps'], c['missed_periods']) == (2, 1, 19)
        assert [s for s, _ in estimates(executor, probe, 2)] == [0, 20 * MS]


@pytest.mark.parametrize('rate_hz', [100.0, 400.0])
def test_a_clean_source_with_jittery_stamps_raises_nothing(rate_hz):
    """Stamps ±20 % of the period about a wall-clock grid, none lost: every message is estimated
    over its own stamp step, nothing is counted as a gap or reported, the node stays OK."""
    rng = np.random.default_rng(int(rate_hz))
    period = int(round(1e9 / rate_hz))
    stamps = (1_764_000_000 * 10**9 + period * np.arange(200)
              + (rng.uniform(-0.2, 0.2, 200) * period).astype(int))
    z = np.array([[0.001, -0.002], [0.0, 0.003], [0.002, 0.0], [0.0, 0.0]])
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor, control_period=1.0 / rate_hz)
        for stamp in stamps:
            send(executor, node, pub, tips(int(stamp), z))
        got = estimates(executor, probe, len(stamps))
        c = node.diag.counters
        assert c['received'] == c['estimates'] == len(stamps)
        assert {k: v for k, v in c.items() if k not in ('received', 'estimates') and v} == {}
        assert node.diag.level == OK
        node.diag.publish()
        assert float(node.diag.values['stamp_period_ms']) == pytest.approx(1e3 / rate_hz, rel=0.02)
    assert [s for s, _ in got] == stamps.tolist()


def test_a_dropout_longer_than_max_bridge_is_reported_and_predicted_through():
    z = np.array([[0.001, -0.002], [0.0, 0.003], [0.002, 0.0], [0.0, 0.0]])
    v = np.array([[0.01, 0.0], [0.0, -0.01], [0.0, 0.0], [0.02, 0.01]])
    meas = lambda ns: z + v * ns / cv.NS                                       # noqa: E731
    sequence = [0, MS, 2 * MS, 12 * MS, 42 * MS, 43 * MS]     # 9 then 29 periods lost
    with ros_context() as (ctx, executor):
        node, probe, pub = make_estimator(ctx, executor, max_bridge=0.02, reset_on_jump=0.1)
        for stamp in sequence:
            send(executor, node, pub, tips(stamp, meas(stamp)))
        got = estimates(executor, probe, len(sequence))
        c = node.diag.counters
        assert (c['gaps'], c['missed_periods'], c['dropouts'], c['resets']) == (2, 38, 1, 0)
        assert node.diag.level == WARN and 'max_bridge' in node.diag.message
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
    kf.reset(meas(0))
    expected = [kf.x.copy()]
    for last, stamp in zip(sequence, sequence[1:]):
        for _ in range((stamp - last) // MS - 1):
            kf.step(meas(stamp), np.zeros(4, dtype=bool))
        expected.append(kf.step(meas(stamp)))
    np.testing.assert_array_equal(np.array([x for _, x in got]), np.array(expected))
    np.testing.assert_allclose(got[-1][1][:, 2:], v, atol=1e-3)      # the velocity was kept


@pytest.mark.parametrize('params, name', [
    (dict(process_noise='coloured'), 'process_noise'), (dict(control_period=0.0), 'control_period'),
    (dict(meas_std=0.0), 'meas_std'),
    (dict(finger_names=[f'f{i}' for i in range(5)]), 'finger_names'),
    (dict(finger_names=['a/b']), 'finger_names'),
    (dict(accel_psd=float('nan')), 'accel_psd'), (dict(reset_on_jump='far'), 'reset_on_jump')])
def test_bad_parameters_fail_at_startup_naming_the_parameter(params, name):
    with ros_context() as (ctx, executor):
        with pytest.raises(ParameterError, match=name):
            EstimatorNode(context=ctx, parameter_overrides=overrides(**params))


def test_runtime_changes_reset_on_jump_only():
    with ros_context() as (ctx, executor):
        node = EstimatorNode(context=ctx)
        assert node.set_parameters([Parameter('reset_on_jump', value=0.5)])[0].successful
        assert node.jump_ns == 500 * MS
        assert not node.set_parameters([Parameter('reset_on_jump', value=0.0)])[0].successful
        assert not node.set_parameters([Parameter('accel_psd', value=2.0)])[0].successful
        assert node.jump_ns == 500 * MS and node.get_parameter('accel_psd').value == 1.0


def test_config_file_holds_the_declared_defaults():
    doc = yaml.safe_load(CONFIG.read_text())
    assert doc == {'/**/estimator': {'ros__parameters': {p.name: p.default for p in PARAMS}}}
