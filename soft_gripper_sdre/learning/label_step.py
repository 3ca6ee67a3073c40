"""The label stage's step without autograd: eq. 18's gradient in closed form, Adam, and the cosine
schedule, each the same arithmetic as torch's, so a label epoch gives the same weights bit for bit
at about half the cost.

A batch of the label stage is a few hundred states through two networks of three small layers; at
that size a step's cost is torch's per-operation overhead, not arithmetic: recording the graph and
running autograd's engine, and ``torch.optim.Adam``'s bookkeeping around its multi-tensor kernels.
This module calls the kernels autograd and Adam would call, in the same order, and nothing else:

* **The gradient** of L = mean_b ‖p̈̂_b − p̈_b‖² (scaled units; :class:`~soft_gripper_sdre.learning.
  model.SDCNet`): with r = p̈̂ − p̈ and the residual's gradient g = (1/B)·2r, the network outputs'
  gradients are outer products, ∂L/∂vec([A21 A22])_b = x_b ⊗ g_b and ∂L/∂vec(G2)_b = u_b ⊗ g_b
  (single products: the batched matmuls autograd runs for them have an inner dimension of one),
  and each layer y = h Wᵀ + c passes back ∂W = ∂yᵀ h, ∂c = Σ_b ∂y, ∂h = ∂y W, through each ReLU
  where its output is positive (``threshold_backward``). These are the matrix products, in the
  operand layouts, that ``AddmmBackward`` forms for ``nn.Linear`` (its weight enters transposed,
  as a column-major operand, so ∂W comes out as ``∂yᵀ.mm(h)``).
* **The forward pass** calls what ``nn.Linear`` and ``matmul`` call underneath: ``addmm`` of the
  bias, the batch and the weight's transposed view (kept per place the weights are stored at) and
  ``bmm``, without the wrappers' dispatch.
* **Adam**: torch's multi-tensor update (``foreach``, not capturable) with the step count kept as a
  Python number: the bias corrections in double precision, each operation on all the weights at
  once (:class:`Adam`).
* **Cosine annealing**: torch's recursive form of the schedule (each epoch's rate from the last),
  which differs from the closed form in the last bits.

``test/test_label_step.py`` holds every piece to the bits of autograd, ``torch.optim.Adam`` and
``CosineAnnealingLR`` on several finger shapes; the shipped checkpoint is reproduced from nothing
through this path (``test/test_model_reproducible.py``).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from soft_gripper_sdre.learning.model import SDCNet


class LabelStep:
    """Eq. 18's loss on a batch (as ``training._label_loss``) and its gradient with respect to
    ``net.parameters()``, in that order, without recording a graph.

    Holds the networks' weight tensors, so a call reaches them without the modules' attribute
    lookups (a step's Python work costs as much as its arithmetic at these sizes); the
    parameters may be re-pointed (:class:`Adam` makes them views of one flat tensor) and the
    steps see it. The gradients come out as new tensors: ``mm`` written into a given tensor
    (``out=``) can take another kernel and part from autograd's in the last bit."""

    def __init__(self, net: SDCNet) -> None:
        self.d, self.m = net.shape.d, net.shape.m
        self.a_params = tuple(net.a_net.parameters())        # w1, c1, w2, c2, w3, c3
        self.g_params = tuple(net.g_net.parameters())
        self._mean_grads: dict[tuple[int, torch.dtype], torch.Tensor] = {}
        self._transposed: dict[tuple[int, int, int], tuple[torch.Tensor, ...]] = {}

    def _mean_grad(self, b: int, dtype: torch.dtype) -> torch.Tensor:
        """The mean's gradient 1/b per sample and coordinate, (b, d), as autograd's
        ``MeanBackward`` forms it (ones divided by b), kept per batch size."""
        key = (b, dtype)
        if key not in self._mean_grads:
            self._mean_grads[key] = ((torch.ones((), dtype=dtype).expand(b) / b)
                                     .unsqueeze(1).expand(b, self.d))
        return self._mean_grads[key]

    def _forward(self, params: tuple[torch.Tensor, ...], xs: torch.Tensor) -> tuple[
            torch.Tensor, torch.Tensor, torch.Tensor]:
        """:func:`mlp_forward` as ``nn.functional.linear`` runs it on a batch (``addmm`` of the
        bias, the input and the weight transposed), the weights' transposed views kept per place
        the weights are stored at."""
        w1, c1, w2, c2, w3, c3 = params
        key = (w1.data_ptr(), w2.data_ptr(), w3.data_ptr())
        if key not in self._transposed:
            self._transposed[key] = (w1.t(), w2.t(), w3.t())
        t1, t2, t3 = self._transposed[key]
        h1 = torch.relu(torch.addmm(c1, xs, t1))
        h2 = torch.relu(torch.addmm(c2, h1, t2))
        return torch.addmm(c3, h2, t3), h1, h2

    @torch.no_grad()
    def __call__(self, xs: torch.Tensor, us: torch.Tensor,
                 acc: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        d, m = self.d, self.m
        out_a, a1, a2 = self._forward(self.a_params, xs)
        out_g, g1, g2 = self._forward(self.g_params, xs)
        r = self._residual(out_a, out_g, xs, us, acc)
        loss = (r ** 2).sum(dim=1).mean()
        b = xs.shape[0]
        d_r = (self._mean_grad(b, r.dtype) * (2.0 * r)).unsqueeze(1)
        d_a = (xs.unsqueeze(2) * d_r).view(b, 2 * d * d)     # vec, columns stacked
        d_g = (us.unsqueeze(2) * d_r).view(b, m * d)
        return loss, (_backward(self.a_params, xs, a1, a2, d_a)
                      + _backward(self.g_params, xs, g1, g2, d_g))

    @torch.no_grad()
    def loss(self, xs: torch.Tensor, us: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
        """Eq. 18's loss alone (a validation set's), by :meth:`__call__`'s forward pass."""
        r = self._residual(self._forward(self.a_params, xs)[0],
                           self._forward(self.g_params, xs)[0], xs, us, acc)
        return (r ** 2).sum(dim=1).mean()

    def _residual(self, out_a: torch.Tensor, out_g: torch.Tensor, xs: torch.Tensor,
                  us: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
        """r = [A21 A22] x + G2 u − p̈ (B, d) from the networks' outputs, as
        :meth:`~soft_gripper_sdre.learning.model.SDCNet.accel` forms it (``matmul`` of the
        batched matrices is ``bmm``)."""
        d, m = self.d, self.m
        a = out_a.view(-1, 2 * d, d).transpose(1, 2)
        g = out_g.view(-1, m, d).transpose(1, 2)
        return (torch.bmm(a, xs.unsqueeze(-1)) + torch.bmm(g, us.unsqueeze(-1))).squeeze(-1) - acc


def mlp_forward(params: tuple[torch.Tensor, ...], xs: torch.Tensor) -> tuple[torch.Tensor,
                                                                              torch.Tensor,
                                                                              torch.Tensor]:
    """The network's output and its two hidden activations (after ReLU) for the weights and
    biases ``params`` of :func:`~soft_gripper_sdre.learning.model.mlp`'s three layers: the
    operations the module runs, so the same bits, without its dispatch; a graph is recorded
    where grad mode is on."""
    w1, c1, w2, c2, w3, c3 = params
    h1 = torch.relu(nn.functional.linear(xs, w1, c1))
    h2 = torch.relu(nn.functional.linear(h1, w2, c2))
    return nn.functional.linear(h2, w3, c3), h1, h2


def _backward(params: tuple[torch.Tensor, ...], xs: torch.Tensor, h1: torch.Tensor,
              h2: torch.Tensor, d_out: torch.Tensor) -> list[torch.Tensor]:
    """The gradients of the network's weights and biases, in ``parameters()`` order, from its
    output's gradient ``d_out``."""
    _, _, w2, _, w3, _ = params
    d2 = _threshold_backward(d_out.mm(w3), h2, 0)
    d1 = _threshold_backward(d2.mm(w2), h1, 0)
    return [d1.t().mm(xs), d1.sum(0), d2.t().mm(h1), d2.sum(0), d_out.t().mm(h2), d_out.sum(0)]


#: ReLU's backward as autograd runs it (the gradient where the output is positive, else +0)
_threshold_backward = torch.ops.aten.threshold_backward.default


def label_loss_and_grads(net: SDCNet, xs: torch.Tensor, us: torch.Tensor,
                         acc: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`LabelStep` of ``net`` on one batch: eq. 18's loss and its gradient with respect to
    ``net.parameters()``, in that order, without recording a graph."""
    return LabelStep(net)(xs, us, acc)


class Adam:
    """Adam over ``params`` (L2 ``weight_decay`` added to the gradient, as ``torch.optim.Adam``);
    :meth:`step` takes the gradients as a list of contiguous tensors in ``params`` order. ``lr``
    may be changed between steps.

    The parameters become views into one flat tensor, and the moments are flat too, so a step is
    seven element-wise operations on one tensor instead of torch's multi-tensor kernels, which on
    the CPU loop over the tensors one operation at a time. Every operation is element-wise, so
    each weight gets the arithmetic of ``torch.optim.Adam(foreach=True)`` to the bit whatever the
    layout (``test/test_label_step.py``)."""

    def __init__(self, params: list[torch.Tensor], lr: float,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 weight_decay: float = 0.0) -> None:
        params = list(params)
        self.lr, self.eps = float(lr), eps
        self.weight_decay = weight_decay
        self.beta1, self.beta2 = betas
        with torch.no_grad():
            self.flat = torch.cat([p.detach().reshape(-1) for p in params])
        offset = 0
        for p in params:
            p.data = self.flat[offset:offset + p.numel()].view_as(p)
            offset += p.numel()
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        self.steps = 0

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor]) -> None:
        self.steps += 1
        grad = torch.cat([g if g.dim() == 1 else g.view(-1) for g in grads])  # view(): µs a call
        if self.weight_decay != 0:
            grad = grad.add(self.flat, alpha=self.weight_decay)
        self.exp_avg.lerp_(grad, 1 - self.beta1)
        self.exp_avg_sq.mul_(self.beta2)
        self.exp_avg_sq.addcmul_(grad, grad, value=1 - self.beta2)
        count = float(self.steps)
        correction1 = 1 - self.beta1 ** count
        correction2_sqrt = (1 - self.beta2 ** count) ** 0.5
        denom = self.exp_avg_sq.sqrt()
        denom.div_(correction2_sqrt)
        denom.add_(self.eps)
        self.flat.addcdiv_(self.exp_avg, denom, value=(self.lr / correction1) * -1)


def cosine_lr(lr: float, epoch: int, epochs: int) -> float:
    """The rate of ``epoch`` (1 … epochs) from the previous epoch's ``lr``, annealed to zero over
    ``epochs`` (torch's ``CosineAnnealingLR`` with ``eta_min`` = 0, stepped once per epoch)."""
    if (epoch - 1 - epochs) % (2 * epochs) == 0:
        raise ValueError(f'epoch {epoch} is past the schedule of {epochs} epochs')
    return ((1 + math.cos(math.pi * epoch / epochs))
            / (1 + math.cos(math.pi * (epoch - 1) / epochs)) * (lr - 0) + 0)
