"""The label stage's step without autograd (learning/label_step.py) against torch's own pieces, bit
for bit: the closed-form gradient against autograd, Adam against ``torch.optim.Adam``, the
schedule against ``CosineAnnealingLR``, and a whole label stage against one built from them."""
from dataclasses import replace
import math

import numpy as np
import pytest
import torch

from soft_gripper_sdre.learning import label_step
from soft_gripper_sdre.learning.model import SDCNet
from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import deterministic_torch, train
from soft_gripper_sdre.sim.shape import FingerShape

SHAPES = [FingerShape(2, 2), FingerShape(3, 3), FingerShape(2, 1), FingerShape(3, 1),
          FingerShape(2, 4)]


def batch(shape, size, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(size, shape.n_state, generator=g)
    u = torch.randn(size, shape.m, generator=g)
    return x, u, torch.randn(size, shape.d, generator=g) + x[:, :shape.d]


def autograd_loss_and_grads(net, xs, us, acc):
    net.zero_grad(set_to_none=True)
    loss = ((net.accel(xs, us) - acc) ** 2).sum(dim=1).mean()
    loss.backward()
    return loss.detach(), [p.grad for p in net.parameters()]


@pytest.mark.parametrize('shape', SHAPES, ids=str)
@pytest.mark.parametrize('size', [256, 80, 1])
def test_the_closed_form_gradient_is_autograds_bit_for_bit(shape, size):
    """Every weight's and bias's gradient and the loss, the same bits as autograd's, for every
    finger shape and for batches whose size is not a power of two (the mean's 1/B rounds)."""
    with deterministic_torch():
        torch.manual_seed(size)
        net = SDCNet(shape=shape)
        data = batch(shape, size, seed=size)
        loss, grads = label_step.label_loss_and_grads(net, *data)
        ref_loss, ref_grads = autograd_loss_and_grads(net, *data)
    assert torch.equal(loss, ref_loss)
    assert len(grads) == len(ref_grads) == len(list(net.parameters()))
    for got, want, p in zip(grads, ref_grads, net.parameters()):
        assert got.shape == p.shape
        assert torch.equal(got, want)
    assert not any(p.grad is None for p in net.parameters())     # the reference ran
    assert any(float(g.abs().max()) > 0 for g in grads)


@pytest.mark.parametrize('shape', SHAPES, ids=str)
@pytest.mark.parametrize('size', [10000, 77])
def test_the_loss_alone_is_the_modules_bit_for_bit(shape, size):
    """The validation loss through the step's forward pass: the bits of the module's, which
    selects the kept epoch."""
    with deterministic_torch():
        torch.manual_seed(size)
        net = SDCNet(shape=shape)
        data = batch(shape, size, seed=size + 1)
        with torch.no_grad():
            want = ((net.accel(*data[:2]) - data[2]) ** 2).sum(dim=1).mean()
        assert torch.equal(label_step.LabelStep(net).loss(*data), want)


def test_the_step_follows_its_weights_when_they_are_moved_or_reloaded():
    """A step built before Adam re-points the weights into its flat tensor, and used before and
    after, gives autograd's gradient of the weights the module holds each time."""
    torch.manual_seed(11)
    net, other = SDCNet(shape=FingerShape(3, 2)), SDCNet(shape=FingerShape(3, 2))
    step = label_step.LabelStep(net)
    data = batch(net.shape, 64, seed=2)

    def same_as_autograd(what):
        loss, grads = step(*data)
        ref_loss, ref_grads = autograd_loss_and_grads(net, *data)
        assert torch.equal(loss, ref_loss), what
        assert all(torch.equal(a, b) for a, b in zip(grads, ref_grads)), what
        return grads

    with deterministic_torch():
        step(*data)
        # the last two layers' weights alone moved, then the module's weights reloaded
        label_step.Adam([net.a_net[2].weight, net.a_net[4].weight], 1e-2)
        net.load_state_dict(other.state_dict())
        same_as_autograd('two weights re-pointed')
        opt = label_step.Adam(list(net.parameters()), 1e-2)
        net.load_state_dict(SDCNet(shape=net.shape).state_dict())
        for k in range(3):
            opt.step(same_as_autograd(f'all re-pointed, step {k}'))


def test_the_closed_form_gradient_records_no_graph():
    net = SDCNet()
    loss, grads = label_step.label_loss_and_grads(net, *batch(net.shape, 16, seed=1))
    assert loss.grad_fn is None and all(g.grad_fn is None for g in grads)
    assert all(p.grad is None for p in net.parameters())


@pytest.mark.parametrize('weight_decay', [0.0, 1e-3])
def test_adam_is_torchs_multi_tensor_adam_bit_for_bit(weight_decay):
    """Twenty steps with the rate changed between them: the same weights as
    ``torch.optim.Adam(foreach=True)`` after every step."""
    torch.manual_seed(3)
    ours_net, ref_net = SDCNet(shape=FingerShape(3, 2)), SDCNet(shape=FingerShape(3, 2))
    ref_net.load_state_dict(ours_net.state_dict())
    ours = label_step.Adam(list(ours_net.parameters()), 1e-3, weight_decay=weight_decay)
    ref = torch.optim.Adam(ref_net.parameters(), lr=1e-3, weight_decay=weight_decay, foreach=True)
    with deterministic_torch():
        for k in range(20):
            data = batch(ours_net.shape, 64, seed=k)
            _, grads = autograd_loss_and_grads(ours_net, *data)
            ours.step(grads)
            autograd_loss_and_grads(ref_net, *data)
            ref.step()
            ours.lr = ref.param_groups[0]['lr'] = 1e-3 * (0.9 ** (k + 1))
            for a, b in zip(ours_net.parameters(), ref_net.parameters()):
                assert torch.equal(a, b), f'step {k + 1}'


@pytest.mark.parametrize('scale', [1e-4, 1.0, 1e3])
def test_the_simulation_stages_clipping_is_clip_grad_norms_bit_for_bit(scale):
    """training._clipped on gradients whose norm is under the clip and over it: the same tensors
    as torch.nn.utils.clip_grad_norm_ leaves in the parameters' .grad; a non-finite one: None."""
    from soft_gripper_sdre.learning.training import _clipped
    torch.manual_seed(11)
    net = SDCNet(shape=FingerShape(2, 2))
    with deterministic_torch():
        _, grads = autograd_loss_and_grads(net, *batch(net.shape, 64, seed=2))
        grads = [g * scale for g in grads]
        ours = _clipped(grads, 1.0)
        for param, g in zip(net.parameters(), grads):
            param.grad = g.clone()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
    assert all(torch.equal(a, p.grad) for a, p in zip(ours, net.parameters()))
    assert (scale < 1) == all(torch.equal(a, g) for a, g in zip(ours, grads))
    grads[3] = grads[3].clone()
    grads[3][0] = float('nan')
    assert _clipped(grads, 1.0) is None


def test_adam_steps_the_modules_own_weights_after_they_are_loaded():
    """The parameters are views into Adam's flat tensor: weights loaded into the module
    (``load_state_dict``, as training does with its best epoch) are the ones the next step moves,
    and the module's tensors keep their shapes and names."""
    torch.manual_seed(5)
    net, other = SDCNet(shape=FingerShape(2, 1)), SDCNet(shape=FingerShape(2, 1))
    shapes = {k: v.shape for k, v in net.state_dict().items()}
    opt = label_step.Adam(list(net.parameters()), 1e-2)
    net.load_state_dict(other.state_dict())
    assert {k: v.shape for k, v in net.state_dict().items()} == shapes
    assert torch.equal(opt.flat, torch.cat([p.reshape(-1) for p in other.parameters()]))
    with deterministic_torch():
        _, grads = autograd_loss_and_grads(net, *batch(net.shape, 32, seed=1))
        opt.step(grads)
    moved = [not torch.equal(a, b) for a, b in zip(net.parameters(), other.parameters())]
    assert all(moved)
    assert torch.equal(opt.flat, torch.cat([p.reshape(-1) for p in net.parameters()]))


def test_cosine_lr_is_torchs_recursive_schedule_bit_for_bit():
    net = SDCNet()
    opt = torch.optim.SGD(net.parameters(), lr=1.5e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=300)
    lr = 1.5e-3
    for epoch in range(1, 301):
        opt.step()
        sched.step()
        lr = label_step.cosine_lr(lr, epoch, 300)
        assert lr == opt.param_groups[0]['lr'], f'epoch {epoch}'
    assert lr == 0.0


def test_cosine_lr_refuses_an_epoch_past_its_schedule():
    with pytest.raises(ValueError, match='epoch 301 is past the schedule of 300'):
        label_step.cosine_lr(1e-3, 301, 300)


def reference_label_stage(x, u, acc, x_val, u_val, acc_val, settings, shape):
    """The label stage built from autograd, torch.optim.Adam and CosineAnnealingLR, as
    training.py ran it with them (same seeds, scaling and order)."""
    scale = [np.where(a.std(axis=0) > 0, a.std(axis=0), 1.0) for a in (x, u, acc)]
    tr = [torch.as_tensor(a / s, dtype=torch.float32) for a, s in zip((x, u, acc), scale)]
    va = [torch.as_tensor(a / s, dtype=torch.float32)
          for a, s in zip((x_val, u_val, acc_val), scale)]
    torch.manual_seed(settings.seed)
    gen = torch.Generator().manual_seed(settings.seed)
    net = SDCNet(settings.hidden, shape)
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr, foreach=True)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=settings.epochs)
    best, best_state, vals = math.inf, None, []
    for _ in range(settings.epochs):
        perm = torch.randperm(tr[0].shape[0], generator=gen)
        for i in range(0, tr[0].shape[0], settings.batch_size):
            idx = perm[i:i + settings.batch_size]
            opt.zero_grad(set_to_none=True)
            ((net.accel(tr[0][idx], tr[1][idx]) - tr[2][idx]) ** 2).sum(dim=1).mean().backward()
            opt.step()
        sched.step()
        with torch.no_grad():
            val = float(((net.accel(va[0], va[1]) - va[2]) ** 2).sum(dim=1).mean())
        vals.append(val)
        if val < best:
            best, best_state = val, {k: v.clone() for k, v in net.state_dict().items()}
    return best_state, vals


@pytest.mark.parametrize('shape', [FingerShape(2, 2), FingerShape(3, 1)], ids=str)
def test_a_label_stage_gives_the_weights_of_autograd_and_torchs_adam(shape):
    """Four epochs of the default preset (cosine schedule over them, batches of 256 and a last
    batch of 104): train()'s validation loss of every epoch and its kept weights are the
    reference stage's, bit for bit."""
    rng = np.random.default_rng(7)
    n, d, m = 2152, shape.d, shape.m
    x = rng.normal(size=(n, 2 * d))
    u = rng.normal(size=(n, m))
    acc = -3 * x[:, :d] + u @ rng.normal(size=(m, d)) + 0.1 * rng.normal(size=(n, d))
    val = (rng.normal(size=(300, 2 * d)), rng.normal(size=(300, m)), rng.normal(size=(300, d)))
    settings = replace(PRESETS['default'], epochs=4)
    with deterministic_torch():
        want, want_val = reference_label_stage(x, u, acc, *val, settings, shape)
    result = train(x, u, acc, *val, settings, shape=shape)
    assert result.val_loss == want_val
    got = result.net.state_dict()
    assert set(got) == set(want)
    for k in want:
        assert torch.equal(got[k], want[k]), k
