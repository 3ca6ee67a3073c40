"""The controller node over real DDS (loopback), launch-free: own Context, executor, test node."""
from node_harness import MS, TORQUE_LIMIT, commands, estimate, horizon, send_estimate
from node_harness import make_controller as make
import numpy as np
import pytest
from rosutil import overrides, ros_context, spin_until

from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.params import ParameterError

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def model():
    return SDCModel()



# the paper's law, the node's default, the baselines (Koopman too), computed torque and Q(x): the
# ``law`` / ``state_weights`` parameters
@pytest.mark.parametrize('law, weights', [('sdre', False), ('sdre_ff', False), ('lqr', False),
                                          ('pd', False), ('computed_torque', False), ('sdre', True),
                                          ('koopman_mpc', False), ('koopman_lqr', False)])
def test_torques_match_the_offline_law_and_close_the_fingers(model, law, weights):
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    offline = make_law(law, model, Weights(**DEFAULT_WEIGHTS), TORQUE_LIMIT, adaptive=weights)
    # the horizon below is constant, so the reference acceleration is zero
    zero_acc = np.zeros((4, 2))
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor, law=law, state_weights=weights)
        ref_msg, ref_pos = horizon(rest, 0)
        ref_pub.publish(ref_msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        for k in range(5):
            send_estimate(executor, node, est_pub, estimate(k * MS, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 5)
        for k, msg in enumerate(commands(probe)):
            stamp, u = cv.msg_to_torques(msg, 4)
            assert stamp == k * MS                      # stamped with the estimate's time
            expected = offline.compute(rest, np.zeros((4, 2)), ref_pos, np.zeros((4, 2)),
                                       ref_acc=zero_acc).u
            np.testing.assert_allclose(u, expected, rtol=1e-9, atol=1e-12)
        # +Y (towards the palm) is reached with negative ax0 torque on every finger
        assert np.all(u[:, 0] < 0)
        assert node.diag.counters['commands'] == 5 and node.diag.counters['fallbacks'] == 0


def test_estimate_waits_for_a_covering_plan(model):
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor)
        est_pub.publish(estimate(3 * MS, rest))
        assert spin_until(executor, lambda: node.diag.counters['estimates'] == 1)
        assert not spin_until(executor, lambda: commands(probe), 0.3)       # nothing to track yet
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: len(commands(probe)) == 1)
        assert cv.msg_to_torques(commands(probe)[0], 4)[0] == 3 * MS


def _bad_estimates(rest):
    nan = rest.copy()
    nan[2, 1] = np.nan
    wrong_names = estimate(5 * MS, rest)
    wrong_names.joint_names = ['finger_0', 'finger_1', 'finger_2', 'thumb']
    too_few = estimate(6 * MS, rest[:3])
    no_point = estimate(7 * MS, rest)
    no_point.points = []
    old = estimate(1 * MS, rest)                        # older than the accepted 2 ms
    return {'nan': estimate(4 * MS, nan), 'unknown finger': wrong_names, 'three fingers': too_few,
            'no point': no_point, 'old stamp': old}


def test_bad_estimates_are_rejected_counted_and_never_answered(model):
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor)
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        est_pub.publish(estimate(2 * MS, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 1)
        for msg in _bad_estimates(rest).values():
            send_estimate(executor, node, est_pub, msg)
        assert node.diag.counters['bad_estimate'] + node.diag.counters['old_estimate'] == 5
        assert node.diag.counters['old_estimate'] == 1
        est_pub.publish(estimate(9 * MS, rest))                # the node is alive and still tracks
        assert spin_until(executor, lambda: len(commands(probe)) == 2)
        stamps = [cv.msg_to_torques(m, 4)[0] for m in commands(probe)]
        assert stamps == [2 * MS, 9 * MS]
        assert all(np.all(np.isfinite(cv.msg_to_torques(m, 4)[1])) for m in commands(probe))


def test_bad_references_are_rejected(model):
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor)
        nan_ref, _ = horizon(rest, 0)
        nan_ref.points[3].transforms[1].translation.y = float('inf')
        backwards, _ = horizon(rest, 0)
        backwards.points[4].time_from_start = backwards.points[2].time_from_start
        ref_pub.publish(nan_ref)
        assert spin_until(executor, lambda: node.diag.counters['bad_reference'] == 1)
        ref_pub.publish(backwards)
        assert spin_until(executor, lambda: node.diag.counters['bad_reference'] == 2)
        est_pub.publish(estimate(1 * MS, rest))
        assert not spin_until(executor, lambda: commands(probe), 0.3)       # no torque from them


def test_the_watchdog_reports_lost_estimates_and_nothing_is_sent_without_one(model):
    """No estimate for estimate_watchdog of wall time: ERROR, and no command; OK with the next."""
    from soft_gripper_sdre.nodes.common import ERROR, OK
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor, estimate_watchdog=0.2)
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        send_estimate(executor, node, est_pub, estimate(4 * MS, rest + 0.002))
        assert spin_until(executor, lambda: len(commands(probe)) == 1)
        assert node.diag.level == OK
        assert spin_until(executor, lambda: node.gate.estimates_lost, 5.0)
        assert node.diag.level == ERROR and 'no state_estimate' in node.diag.message
        assert not spin_until(executor, lambda: len(commands(probe)) > 1, 0.5)   # nothing sent
        send_estimate(executor, node, est_pub, estimate(9 * MS, rest + 0.002))
        assert spin_until(executor, lambda: len(commands(probe)) == 2)
        assert not node.gate.estimates_lost and node.diag.level == OK
        assert node.diag.counters['skipped_estimates'] == 4               # 5 … 8 ms never came


def test_estimates_stopping_past_the_plans_end_end_the_run_without_an_error(model, capfd):
    """The run's end (the simulator or driver finished after the plan's last point): the same
    silence is reported at INFO with status OK, and nothing is sent."""
    from soft_gripper_sdre.nodes.common import OK
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor, estimate_watchdog=0.2)
        ref_pub.publish(horizon(rest, 0)[0])                 # 21 points 5 ms apart: ends at 100 ms
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        send_estimate(executor, node, est_pub, estimate(100 * MS, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 1)
        assert spin_until(executor, lambda: node.gate.estimates_lost, 5.0)
        assert node.diag.level == OK and 'the run is over' in node.diag.message
        assert "the last stamped t = 0.1000 s, at or past the plan's end" in node.diag.message
        assert not spin_until(executor, lambda: len(commands(probe)) > 1, 0.3)   # nothing sent
    lines = [line for line in capfd.readouterr().err.splitlines() if 'state_estimate' in line]
    assert [line.split(']')[0] for line in lines] == ['[INFO'], lines        # logged once, as INFO


def test_a_controller_that_fell_behind_answers_only_the_newest_estimate(model):
    """Estimates that queued while the node could not run: it answers the newest (its reader keeps
    one message) and counts the skipped ones, instead of working off a queue of stale ones."""
    import time
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor)
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        send_estimate(executor, node, est_pub, estimate(0, rest))
        for k in range(1, 21):                       # the node's executor does not run meanwhile
            est_pub.publish(estimate(k * MS, rest))
        time.sleep(0.3)
        spin_until(executor, lambda: False, 0.5)
        assert [cv.msg_to_torques(m, 4)[0] for m in commands(probe)] == [0, 20 * MS]
        assert node.diag.counters['skipped_estimates'] == 19


@pytest.mark.parametrize('changes, needle', [
    ({'estimate_watchdog': 0.0}, ''),
    ({'estimate_watchdog': -1.0}, ''),
    ({'q_pos': -1.0}, ''),
    ({'solver': 'magic'}, ''),
])
def test_runtime_parameter_changes_are_refused_with_the_reason_and_the_old_value_stays(
        model, changes, needle):
    from rclpy.parameter import Parameter
    with ros_context() as (ctx, executor):
        node = ControllerNode(context=ctx)
        before = {k: node.get_parameter(k).value for k in changes}
        result = node.set_parameters([Parameter(k, value=v) for k, v in changes.items()])[0]
        assert not result.successful and result.reason
        assert needle in result.reason
        assert {k: node.get_parameter(k).value for k in changes} == before
        assert node.gate.watchdog == 0.5 and node.p['estimate_watchdog'] == 0.5
        assert node.set_parameters([Parameter('estimate_watchdog', value=2.0)])[0].successful
        assert node.gate.watchdog == 2.0


@pytest.mark.parametrize('params, needle', [
    (dict(model_path='/nonexistent/model.pt'), 'model_path'),
    (dict(r=0.0), "'r'"),
    (dict(solver='magic'), 'solver'),
])
def test_bad_model_or_parameters_end_the_node_at_startup(params, needle):
    """A ParameterError, with which the node's process exits with status 2 naming it (that path:
    test_node_cli.py)."""
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(**params))
    assert needle in str(info.value)


def test_truncated_model_file_is_refused(tmp_path):
    from soft_gripper_sdre.learning.model import DEFAULT_MODEL
    bad = tmp_path / 'half.pt'
    bad.write_bytes(DEFAULT_MODEL.read_bytes()[:2000])
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(model_path=str(bad)))
    assert 'truncated' in str(info.value)


def test_time_jumping_back_resets_instead_of_rejecting(model):
    """A simulator restart (stamps from 0 again) is followed, not rejected as old: the old run's
    plan is forgotten and the new run is tracked once its plan arrives."""
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor, reset_on_jump=0.5)
        late = 2_000 * MS
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        send_estimate(executor, node, est_pub, estimate(late, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 1)
        send_estimate(executor, node, est_pub, estimate(0, rest))        # restart: 2 s back
        assert node.diag.counters['resets'] == 1 and node.gate.plan is None
        assert not spin_until(executor, lambda: len(commands(probe)) > 1, 0.3)  # waits for its plan
        ref_pub.publish(horizon(rest, 0, close_mm=3.0)[0])
        assert spin_until(executor, lambda: len(commands(probe)) == 2)
        assert cv.msg_to_torques(commands(probe)[1], 4)[0] == 0
        assert node.diag.counters['old_estimate'] == 0
