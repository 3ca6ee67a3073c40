"""The controller node's ``law`` parameter: the baselines run on the graph, the oracle is refused."""
import subprocess
import sys

import numpy as np
import pytest

from rosutil import ros_context, spin_until
from soft_gripper_sdre.control import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.laws import make_law
from soft_gripper_sdre.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from test_node_controller import LIMIT, MS, commands, estimate, horizon, make

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('law, weights', [('lqr', False), ('pd', False), ('sdre', True)])
def test_law_parameter_selects_the_law(law, weights):
    model = SDCModel()
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    offline = make_law(law, model, Weights(**DEFAULT_WEIGHTS), LIMIT, adaptive=weights)
    with ros_context() as (ctx, executor):
        node, probe, est_pub, ref_pub = make(ctx, executor, law=law, state_weights=weights)
        ref_msg, ref_pos = horizon(rest, 0)
        ref_pub.publish(ref_msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)
        for k in range(3):
            est_pub.publish(estimate(k * MS, rest))
        assert spin_until(executor, lambda: len(commands(probe)) == 3)
        for msg in commands(probe):
            _, u = cv.msg_to_torques(msg, 4)
            expected = offline.compute(rest, np.zeros((4, 2)), ref_pos, np.zeros((4, 2))).u
            np.testing.assert_allclose(u, expected, rtol=1e-9, atol=1e-12)
        assert np.all(u[:, 0] < 0)                      # every law closes toward +Y with −ax0


@pytest.mark.parametrize('args, needle', [
    (['-p', 'law:=oracle'], 'law'),
    (['-p', 'law:=pd', '-p', 'state_weights:=true'], 'state-dependent weights'),
])
def test_oracle_or_weights_on_a_baseline_end_the_node_at_startup(args, needle):
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.controller', '--ros-args', *args],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert needle in proc.stderr + proc.stdout
