"""The controller's gains and weights changed while it runs, through its parameter service
(``/controller/set_parameters``, as ``ros2 param set`` calls it) over real DDS (loopback): an
accepted change retunes the torque from the next estimate, a refused one leaves everything as it
was."""
from node_harness import (
    MS,
    TORQUE_LIMIT,
    commands,
    estimate,
    horizon,
    make_controller,
    send_estimate,
)
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rosutil import ros_context, spin_until

from soft_gripper_sdre.control.laws import DEFAULT_CT, DEFAULT_PD
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.controller import PARAMS

pytestmark = pytest.mark.ros

REST = SDCModel().rest_tip[None, :2].repeat(4, 0)


def set_parameters(executor, probe, **values):
    """Set ``values`` through /controller/set_parameters; the (successful, reason) of each."""
    client = getattr(probe, 'param_client', None)
    if client is None:
        client = probe.create_client(SetParameters, '/controller/set_parameters')
        probe.param_client = client
    assert spin_until(executor, client.service_is_ready, 20.0), 'no parameter service'
    request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                for k, v in values.items()])
    future = client.call_async(request)
    assert spin_until(executor, future.done, 10.0), 'no answer from the parameter service'
    return [(r.successful, r.reason) for r in future.result().results]


def start(ctx, executor, **params):
    node, probe, est_pub, ref_pub = make_controller(ctx, executor, torque_limit=TORQUE_LIMIT,
                                                    **params)
    ref_pub.publish(horizon(REST, 0, close_mm=0.05)[0])
    assert spin_until(executor, lambda: node.gate.plan is not None, 5.0)
    stamps = iter(range(1, 10_000))

    def torque() -> np.ndarray:
        """The command answering one estimate at rest (zero velocity), newer than the last."""
        send_estimate(executor, node, est_pub, estimate(next(stamps) * MS, REST))
        assert spin_until(executor, lambda: len(commands(probe)) == node.diag.counters['commands'])
        return cv.msg_to_torques(commands(probe)[-1], 4)[1]
    return node, probe, torque


def test_pd_gains_set_at_runtime_scale_the_torque_and_bad_values_are_refused():
    """law pd without roll-off: u = G₂(0)⁻¹ (k_p e + k_d ė), e the constant 0.05 mm, ė = 0."""
    with ros_context() as (ctx, executor):
        node, probe, torque = start(ctx, executor, law='pd', torque_lowpass_hz=0.0)
        u1 = torque()
        assert np.abs(u1).max() > 0 and node.diag.values['pd_gains'] == 'kp=15000 kd=40'
        assert set_parameters(executor, probe, pd_kp=2 * DEFAULT_PD['kp']) == [(True, '')]
        u2 = torque()
        np.testing.assert_array_equal(u2, 2 * u1)               # exactly: the gain doubled
        assert np.abs(u2).max() < TORQUE_LIMIT
        assert node.diag.values['pd_gains'] == 'kp=30000 kd=40'

        for bad in (dict(pd_kp=-1.0), dict(pd_kd='stiff'), dict(pd_kp=float('nan'))):
            ((ok, reason),) = set_parameters(executor, probe, **bad)
            assert not ok and reason, bad
        assert node.get_parameter('pd_kp').value == 2 * DEFAULT_PD['kp']
        np.testing.assert_array_equal(torque(), u2)             # the old gains stay in force
        assert set_parameters(executor, probe, pd_kp=0) == [(True, '')]   # 0: the law's own
        np.testing.assert_array_equal(torque(), u1)
        assert node.get_parameter('pd_kp').type_ is Parameter.Type.DOUBLE


def test_sdre_weights_and_integral_set_at_runtime_retune_the_default_law():
    with ros_context() as (ctx, executor):
        node, probe, torque = start(ctx, executor)
        for _ in range(3):
            u1 = torque()
        # an integer for a float is taken; two values at once
        assert set_parameters(executor, probe, q_pos=4_000_000, r=8000.0) == [(True, '')] * 2
        assert node.diag.values['weights'] == 'q_pos=4e+06 q_vel=0 r=8000'
        u2 = torque()
        assert not np.allclose(u2, u1)
        assert node.get_parameter('q_pos').value == 4e6
        ((ok, reason),) = set_parameters(executor, probe, r=0.0)            # R must be > 0
        assert not ok and 'r' in reason
        ((ok, reason),) = set_parameters(executor, probe, integral_band=1.0)  # beyond 0.1 m
        assert not ok and reason
        assert node.get_parameter('r').value == 8000.0
        assert node.get_parameter('integral_band').value == 5e-4
        assert set_parameters(executor, probe, integral_gain=0.0) == [(True, '')]
        assert node.tuning.law.integral is None
        assert node.diag.values['integral'].startswith('gain=0 ')
        # a gain the law does not use is taken, and changes nothing
        law = node.tuning.law
        assert set_parameters(executor, probe, pd_kd=5.0) == [(True, '')]
        assert node.tuning.law is law
        c = node.diag.counters
        assert c['commands'] == c['estimates'] and c['nonfinite_torque'] == 0


def test_computed_torque_takes_its_own_gains_by_default():
    with ros_context() as (ctx, executor):
        node, probe, torque = start(ctx, executor, law='computed_torque')
        assert (node.tuning.law.kp, node.tuning.law.kd) == (DEFAULT_CT['kp'], DEFAULT_CT['kd'])
        assert set_parameters(executor, probe, pd_kd=20.0) == [(True, '')]
        assert (node.tuning.law.kp, node.tuning.law.kd) == (DEFAULT_CT['kp'], 20.0)
        assert np.all(np.isfinite(torque()))


def test_the_tunable_parameters_are_the_runtime_ones():
    runtime = {p.name for p in PARAMS if not p.read_only}
    assert runtime == {'q_pos', 'q_vel', 'r', 'integral_gain', 'integral_band', 'pd_kp', 'pd_kd',
                       'smc_lambda', 'smc_k', 'smc_phi', 'estimate_watchdog'}


def test_hand_over_keeps_the_command_continuous():
    """The law built again with other gains takes over the roll-off's last output and the
    integral's torque."""
    from soft_gripper_sdre.control.laws import hand_over, make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    old = make_law('sdre_ff', model, w, TORQUE_LIMIT, integral_gain=1e5, integral_band=5e-3)
    ref = REST + [0.0, 2e-4]
    for _ in range(20):
        old.compute(REST, np.zeros((4, 2)), ref, np.zeros((4, 2)))
    new = make_law('sdre_ff', model, w, TORQUE_LIMIT, integral_gain=4e5, integral_band=5e-3)
    hand_over(old, new)
    assert np.abs(old.integral.torque()).max() > 0
    np.testing.assert_allclose(new.integral.torque(), old.integral.torque(), rtol=1e-12)
    np.testing.assert_array_equal(new.io.roll_off._u, old.io.roll_off._u)
    with pytest.raises(ValueError, match='PdLaw'):
        hand_over(old, make_law('pd', model, w, TORQUE_LIMIT))


def test_feedforward_at_the_reference_is_the_law_the_node_runs():
    """feedforward_at:=ref builds sdre_ff with its model evaluated on the reference: the node's
    torque is that law's to the bit, and not the default's (the estimate is off the plan)."""
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import Weights
    with ros_context() as (ctx, executor):
        node, probe, torque = start(ctx, executor, law='sdre_ff', feedforward_at='ref',
                                    torque_lowpass_hz=0.0, integral_gain=0.0)
        assert node.tuning.law.ff_at == 'ref'
        u = torque()
        p = node.p
        pos, vel, acc = node.step.sample(node.gate.plan, 1 * MS)
        twins = {at: make_law('sdre_ff', node.model, Weights(p['q_pos'], p['q_vel'], p['r']),
                              p['torque_limit'], n_fingers=4, method=p['solver'], lowpass_hz=0.0,
                              dt=p['control_period'], ff_at=at, integral_gain=0.0)
                 for at in ('ref', 'x')}
        expect = {at: law.compute(REST, np.zeros((4, 2)), pos, vel, ref_acc=acc).u
                  for at, law in twins.items()}
        np.testing.assert_allclose(u, expect['ref'], rtol=0, atol=1e-14)
        assert np.abs(expect['ref'] - expect['x']).max() > 1e-10     # 1 µm off the plan: ~6e-9
        assert set_parameters(executor, probe, feedforward_at='x')[0][0] is False   # read-only
