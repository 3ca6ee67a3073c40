"""The controller node's ``law`` parameter: the feedforward law samples p̈_d from the horizon; the
oracle (and Q(x) on a baseline) is refused at start-up; ``integral_gain`` switches the default law's
integral action.

That every graph law runs on the node and gives the offline law's torques is
test_node_controller.py's test_torques_match_the_offline_law_and_close_the_fingers.
"""
from node_harness import MS, TORQUE_LIMIT, commands, estimate, make_controller, send_estimate
import numpy as np
import pytest
from rosutil import overrides, ros_context, spin_until

from soft_gripper_sdre.control.laws import DEFAULT_INTEGRAL, ComputedTorqueLaw, make_law
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.params import ParameterError

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('params, needle', [
    (dict(law='oracle'), 'law'),
    (dict(law='pd', state_weights=True), 'state-dependent weights'),
    (dict(integral_gain=-1.0), 'integral_gain'),
])
def test_oracle_or_weights_on_a_baseline_end_the_node_at_startup(params, needle):
    """A ParameterError: the node's process exits with status 2 naming it (test_node_cli.py)."""
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            ControllerNode(context=ctx, parameter_overrides=overrides(**params))
    assert needle in str(info.value)


def test_feedforward_law_gets_the_reference_acceleration_from_the_horizon():
    """law:=sdre_ff: the node samples p̈_d from the published plan (constant acceleration here)
    and its torques match the offline law given that acceleration, not the law without it."""
    from soft_gripper_sdre.control.horizon import sample_horizon
    model = SDCModel()
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    w = Weights(**DEFAULT_WEIGHTS)
    with_acc, without = (make_law('sdre_ff', model, w, TORQUE_LIMIT) for _ in range(2))
    times = 5 * MS * np.arange(21)
    t = times[:, None, None] / 1e9
    a = np.array([0.0, 0.5])                                     # m/s² towards the palm
    pos, vel, acc = (rest[None] + 0.5 * a * t ** 2, a * t * np.ones((1, 4, 1)),
                     np.broadcast_to(a, (21, 4, 2)))
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make_controller(ctx, executor, law='sdre_ff')
        ref_pub.publish(cv.reference_to_msg(0, times, pos, vel, acc))
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        stamps = [k * MS for k in range(3)]
        for s in stamps:
            send_estimate(executor, node, est_pub, estimate(s, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 3)
        for s, msg in zip(stamps, commands(probe)):
            _, u = cv.msg_to_torques(msg, 4)
            p, v, ad = sample_horizon(times, pos, vel, acc, s, with_acc=True)
            z = np.zeros((4, 2))
            np.testing.assert_allclose(u, with_acc.compute(rest, z, p, v, ref_acc=ad).u, rtol=1e-9,
                                       atol=1e-12)
            assert not np.allclose(u, without.compute(rest, z, p, v).u, rtol=1e-3, atol=0)


def test_integral_gain_switches_the_default_laws_integral_action_and_other_laws_ignore_it():
    with ros_context() as (ctx, executor):
        def node(**params):
            n = ControllerNode(context=ctx, parameter_overrides=overrides(**params))
            executor.add_node(n)
            return n.tuning.law
        default = node()
        assert (default.integral.gain == DEFAULT_INTEGRAL['gain']
                and default.integral.band == DEFAULT_INTEGRAL['band'])
        assert node(integral_gain=0.0).integral is None  # the law without integral action
        tuned = node(integral_gain=2e4, integral_band=1e-3).integral
        assert (tuned.gain, tuned.band) == (2e4, 1e-3)
        assert isinstance(node(law='computed_torque', integral_gain=5e4), ComputedTorqueLaw)
