"""An external tip source, as a motion-capture driver would serve it, through the estimator and the
controller over real DDS: 120 Hz, stamps jittered by ±20 % of the period around a wall-clock grid,
1 % of the messages never sent, another frame_id than the simulator's."""
import time

from geometry_msgs.msg import PoseArray
from node_harness import TORQUE_LIMIT, horizon
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import OK
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import MESSAGE_OUTCOMES, EstimatorNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)

pytestmark = pytest.mark.ros

RATE_HZ = 120.0
PERIOD_NS = int(round(1e9 / RATE_HZ))
SLOTS = 360                       # 3 s of the source
#: what the estimator and the controller count as refused, lost or reset (none of it may happen)
ESTIMATOR_PROBLEMS = ('bad_message', 'duplicate', 'out_of_order', 'dropouts', 'resets')
CONTROLLER_PROBLEMS = ('bad_estimate', 'old_estimate', 'bad_reference', 'resets',
                       'nonfinite_torque', 'unanswered_estimates')


def mocap_source(seed: int = 5):
    """(stamps [ns], tips (k, 4, 3) [m]) of the messages sent: a wall-clock grid at RATE_HZ,
    each stamp moved by up to ±20 % of the period, 1 % of the slots (never the first) dropped;
    the tips sway 2 mm at 1 Hz about the model's rest pose, with 0.05 mm noise."""
    rng = np.random.default_rng(seed)
    t0 = time.time_ns()
    grid = t0 + PERIOD_NS * np.arange(SLOTS)
    stamps = grid + (rng.uniform(-0.2, 0.2, SLOTS) * PERIOD_NS).astype(np.int64)
    kept = np.ones(SLOTS, dtype=bool)
    kept[1 + rng.choice(SLOTS - 1, SLOTS // 100, replace=False)] = False
    rest = SDCModel().rest_tip
    t = (stamps - t0) / 1e9
    tips = np.empty((SLOTS, 4, 3))
    tips[:] = rest
    tips[..., 1] += 0.002 * np.sin(2 * np.pi * t)[:, None]
    tips[..., :2] += rng.normal(size=(SLOTS, 4, 2)) * 5e-5
    return stamps, tips, kept


def test_a_jittery_120_hz_mocap_source_is_estimated_and_controlled_at_its_own_rate():
    stamps, tips, kept = mocap_source()
    params = dict(control_period=1.0 / RATE_HZ)
    with ros_context() as (ctx, executor):
        est = EstimatorNode(context=ctx, parameter_overrides=overrides(**params))
        ctrl = ControllerNode(context=ctx,
                              parameter_overrides=overrides(torque_limit=TORQUE_LIMIT, **params))
        probe = Probe(ctx, 'mocap')
        tip_pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        ref_pub = probe.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, deep(LOOP_QOS))
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        warnings = []
        probe.create_subscription(Log, '/rosout', lambda m: warnings.append(m)
                                  if m.level >= Log.WARN and m.name in ('estimator', 'controller')
                                  else None, deep(LOOP_QOS, 1000))
        for node in (est, ctrl, probe):
            executor.add_node(node)
        assert spin_until(executor, lambda: tip_pub.get_subscription_count() > 0
                          and ref_pub.get_subscription_count() > 0
                          and est.pub.get_subscription_count() > 1
                          and ctrl.pub_cmd.get_subscription_count() > 0, 20.0)
        rest = SDCModel().rest_tip[None, :2].repeat(4, 0)
        ref_pub.publish(horizon(rest, int(stamps[0]))[0])
        assert spin_until(executor, lambda: ctrl.gate.plan is not None, 5.0)

        e, c = est.diag.counters, ctrl.diag.counters
        wall0 = time.monotonic()
        for k in np.flatnonzero(kept):          # paced at the source's rate, each message taken
            before = sum(c[key] for key in ('estimates', 'bad_estimate', 'old_estimate'))
            tip_pub.publish(cv.tips_to_msg(int(stamps[k]), tips[k], frame_id='mocap_world'))
            assert spin_until(executor,
                              lambda: sum(c[key] for key in ('estimates', 'bad_estimate',
                                                             'old_estimate')) > before, 5.0)
            spin_until(executor, lambda: False, max(0.0, wall0 + k / RATE_HZ - time.monotonic()))
        sent = int(kept.sum())
        got_u = probe.received[TORQUE_COMMANDS]
        assert spin_until(executor, lambda: len(got_u) >= sent, 5.0)
        spin_until(executor, lambda: False, 0.3)     # the last /rosout lines

        # every message accounted for: accepted or refused under one reason, and the lost ones
        # seen as gaps in the stamps
        assert e['received'] == sent == sum(e[key] for key in MESSAGE_OUTCOMES)
        assert e['estimates'] == sent
        assert (e['gaps'], e['missed_periods']) == (SLOTS - sent, SLOTS - sent)
        assert {key: e[key] for key in ESTIMATOR_PROBLEMS if e[key]} == {}
        assert {key: c[key] for key in CONTROLLER_PROBLEMS if c[key]} == {}
        assert c['estimates'] == c['commands'] == sent
        assert c['skipped_estimates'] == SLOTS - sent
        assert est.diag.level == ctrl.diag.level == OK
        assert [m.msg for m in warnings] == []

        # estimates at the source's rate, on its stamps; finite torques on the same stamps
        got_x = [cv.msg_to_estimate(m, 4) for m in probe.received[STATE_ESTIMATE]]
        assert [s for s, _ in got_x] == stamps[kept].tolist()
        x = np.array([x for _, x in got_x])
        assert np.all(np.isfinite(x))
        torques = [cv.msg_to_torques(m, 4) for m in got_u]
        assert [s for s, _ in torques] == stamps[kept].tolist()
        u = np.array([u for _, u in torques])
        assert np.all(np.isfinite(u)) and np.abs(u).max() <= TORQUE_LIMIT
        # the filter steps over each stamp difference: the offline filter fed the same Δt sequence
        kf = ConstantVelocityKF(1.0 / RATE_HZ, 1.0, 5e-5, n=4)
        z, t = tips[kept][:, :, :2], stamps[kept]
        kf.reset(z[0])
        offline = [kf.x.copy()] + [kf.step(z[k], dt=(t[k] - t[k - 1]) / 1e9)
                                   for k in range(1, sent)]
        np.testing.assert_allclose(x, np.array(offline), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(x[:, :, :2], z, atol=2e-4)


@pytest.mark.parametrize('reliability, matched', [('reliable', False), ('best_effort', True)])
def test_a_sensor_data_qos_driver_is_heard_only_with_a_best_effort_tips_subscription(reliability,
                                                                                     matched):
    """A driver publishing with the sensor-data QoS (best effort) offers less than a reliable reader
    asks for, so DDS never connects them; tips_reliability:=best_effort does."""
    from rclpy.qos import qos_profile_sensor_data
    stamps, tips, _ = mocap_source()
    with ros_context() as (ctx, executor):
        est = EstimatorNode(context=ctx, parameter_overrides=overrides(
            control_period=1.0 / RATE_HZ, tips_reliability=reliability))
        probe = Probe(ctx, 'mocap')
        tip_pub = probe.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
        probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, deep(LOOP_QOS))
        for node in (est, probe):
            executor.add_node(node)
        # the probe's own estimate reader matches either way: discovery has run once it has
        assert spin_until(executor, lambda: est.pub.get_subscription_count() > 0, 20.0)
        assert spin_until(executor, lambda: tip_pub.get_subscription_count() > 0, 3.0) is matched
        if matched:                  # paced: the reader keeps only the newest message
            for k in range(20):
                tip_pub.publish(cv.tips_to_msg(int(stamps[k]), tips[k]))
                spin_until(executor, lambda: est.diag.counters['estimates'] > k, 2.0)
            assert est.diag.counters['estimates'] >= 15      # best effort may lose one now and then
