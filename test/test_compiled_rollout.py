"""The simulation stage's compiled loss and gradient (learning/compiled_rollout.py) against torch's
autograd through rollout.window_errors, in float64, on several finger shapes, with a window held
at the state's bound and a window past the error's cap in the batch."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from soft_gripper_sdre.learning import compiled_rollout, rollout
from soft_gripper_sdre.learning.model import SDCNet
from soft_gripper_sdre.learning.rollout import SIM_BOUND, SIM_ERROR_CAP, Scales
from soft_gripper_sdre.sim.shape import FingerShape


def _case(shape: FingerShape, seed: int = 0):
    """A float64 network, scales and a batch of eight windows of 0.2 s at 100 Hz: window 0 driven
    hard enough to be held at the bound, window 1 aimed so far off that its error is capped."""
    torch.manual_seed(seed)
    d, m = shape.d, shape.m
    net = SDCNet(16, shape).double()
    gen = torch.Generator().manual_seed(seed)
    rand = lambda *size: torch.rand(*size, generator=gen, dtype=torch.float64)  # noqa: E731
    s = Scales(rand(2 * d) + 0.5, rand(m) + 0.5, rand(d) + 0.5)
    x0 = rand(8, 2 * d) - 0.5
    u = rand(8, 20, m) - 0.5
    p = rand(8, 20, d) - 0.5
    u[0] *= 1e6
    p[1] += 50.0 * s.x[:d]
    return net, s, 0.01, x0, u, p


def _autograd(net, s, dt, x0, u, p):
    net.zero_grad(set_to_none=True)
    loss = rollout.sim_error(net, s, dt, x0, u, p)
    loss.backward()
    return float(loss.detach()), [q.grad.clone() for q in net.parameters()]


@pytest.mark.parametrize('shape', [FingerShape(2, 2), FingerShape(2, 1), FingerShape(3, 3),
                                   FingerShape(3, 1)])
def test_the_loss_and_gradient_are_autograds(shape):
    net, s, dt, x0, u, p = _case(shape)
    with torch.no_grad():
        errors = rollout.window_errors(net, s, dt, x0, u, p).numpy()
        run = rollout.simulate(net, s, x0, u, dt).numpy()
    assert np.any(np.abs(run[0]) >= SIM_BOUND * s.x[:shape.d].numpy() * (1 - 1e-12))
    assert errors[1] == SIM_ERROR_CAP and np.all(errors[2:] < SIM_ERROR_CAP)
    ref_loss, ref_grads = _autograd(net, s, dt, x0, u, p)
    loss, grads = compiled_rollout.loss_and_grads(
        net, s, dt, x0.numpy(), u.numpy(), p.numpy())
    assert loss == pytest.approx(ref_loss, rel=1e-12)
    assert [g.shape for g in grads] == [g.shape for g in ref_grads]
    assert all(g.dtype == torch.float64 for g in grads)
    for got, ref in zip(grads, ref_grads):
        np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=1e-9,
                                   atol=1e-12 * float(ref.abs().max()))
    assert any(float(g.abs().max()) > 0 for g in grads[6:])    # G's network is trained too


def test_a_capped_window_passes_no_gradient():
    """The batch's gradient is that of the windows under the cap: the capped window adds its cap
    to the loss and nothing to any weight."""
    shape = FingerShape(2, 2)
    net, s, dt, x0, u, p = _case(shape)
    args = lambda keep: (x0[keep].numpy(), u[keep].numpy(), p[keep].numpy())  # noqa: E731
    every = list(range(8))
    without = [i for i in every if i != 1]
    loss, grads = compiled_rollout.loss_and_grads(net, s, dt, *args(every))
    rest, rest_grads = compiled_rollout.loss_and_grads(net, s, dt, *args(without))
    assert loss == pytest.approx((7 * rest + SIM_ERROR_CAP) / 8, rel=1e-12)
    for g, r in zip(grads, rest_grads):
        np.testing.assert_allclose(g.numpy(), 7 / 8 * r.numpy(), rtol=1e-12, atol=1e-300)


def test_a_network_that_is_not_finite_gives_a_loss_that_is_not_finite():
    """The training step skips a batch whose loss is not finite; the kernel reports one instead
    of a number."""
    net, s, dt, x0, u, p = _case(FingerShape(2, 2))
    with torch.no_grad():
        net.a_net[4].bias[0] = float('nan')
    loss, grads = compiled_rollout.loss_and_grads(
        net, s, dt, x0.numpy(), u.numpy(), p.numpy())
    assert np.isnan(loss)
    assert len(grads) == 12


def test_float32_networks_get_float32_gradients():
    """The training's float32 networks: their gradients come back float32, the float64
    arithmetic's rounded."""
    net, s, dt, x0, u, p = _case(FingerShape(2, 2))
    ref_loss, ref_grads = _autograd(net, s, dt, x0, u, p)
    net = net.float()
    loss, grads = compiled_rollout.loss_and_grads(
        net, Scales(*(a.float() for a in s)), dt, x0.numpy(), u.numpy(), p.numpy())
    assert all(g.dtype == torch.float32 for g in grads)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    for got, ref in zip(grads, ref_grads):
        np.testing.assert_allclose(got.double().numpy(), ref.numpy(), rtol=1e-3,
                                   atol=1e-5 * float(ref.abs().max()))
