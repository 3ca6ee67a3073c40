"""The simulation stage's loss and its gradient, compiled with numba: the windows of
:mod:`soft_gripper_sdre.learning.rollout` integrated forward and differentiated backward through
their RK4 steps by hand, window by window, in float64.

A batch of the stage is 128 windows of H steps (50 at 500 Hz), each step four evaluations of two
networks of three layers of 32 units; through autograd that is about sixty small tensor operations
per evaluation forward and as many backward, and torch's cost per operation, not the arithmetic,
set the stage's time. Here a window is integrated as :func:`~soft_gripper_sdre.learning.rollout.
simulate` integrates it (the same RK4, the same bound on the state), its error is
:func:`~soft_gripper_sdre.learning.rollout.window_errors`' (capped, a capped window passing no
gradient), and the error's gradient flows back through the steps by the adjoint of each:

* a step x⁺ = clip(x + h/6 (k₁ + 2k₂ + 2k₃ + k₄)) passes λ to x where the state was not held at
  the bound, and h/6, h/3, h/3, h/6 of it to k₁ … k₄; the stage k₄ = f(x + h k₃) passes its
  input's adjoint to x and h of it to k₃, k₃ = f(x + h/2 k₂) and k₂ = f(x + h/2 k₁) likewise;
* f(x, u) = [v; s_a ⊙ (A(x̃) x̃ + G(x̃) ũ)] (x̃ = x / s_x, ũ = u / s_u: the networks' units) passes
  λ_v to v and, with g = s_a ⊙ λ_a, ∂vec A = x̃ ⊗ g, ∂vec G = ũ ⊗ g and Aᵀg to x̃;
* each layer y = W h + c of a network passes ∂W = ∂y hᵀ, ∂c = ∂y, ∂h = Wᵀ ∂y through its ReLU
  where the ReLU's output is positive, as autograd does.

The result is autograd's on the same windows in float64 to rounding (test/test_compiled_rollout.py:
the loss and every weight's gradient against torch's autograd through
:func:`~soft_gripper_sdre.learning.rollout.window_errors`, several finger shapes, a window held at
the bound and a capped one among them). It is not torch's float32 arithmetic bit for bit, so a
model trained with it is not the one autograd's float32 gives; the hand's default preset has no
simulation stage and is not touched.

The kernels call only each other, in this file, so numba's own on-disk cache rule (a kernel's
cache is keyed on its source file) holds for them, as for :mod:`~soft_gripper_sdre.learning.
compiled_labels`.
"""
from __future__ import annotations

from numba import njit
import numpy as np
import torch

from soft_gripper_sdre.learning.model import SDCNet
from soft_gripper_sdre.learning.rollout import SIM_BOUND, SIM_ERROR_CAP, Scales

_njit = njit(cache=True, error_model='numpy', nogil=True)

#: each RK4 stage's input is x + _STAGE[s] · h · k_{s−1}
_STAGE = (0.0, 0.5, 0.5, 1.0)


@_njit
def _mlp_forward(w1t, b1, w2t, b2, w3t, b3, xs, h1, h2, out) -> None:
    """``out`` = W₃ relu(W₂ relu(W₁ xs + b₁) + b₂) + b₃, keeping both hidden activations in
    ``h1`` and ``h2`` (the weights transposed: wᵢt = Wᵢᵀ, so each input's column is contiguous)."""
    nh = b1.shape[0]
    for i in range(nh):
        h1[i] = b1[i]
    for j in range(xs.shape[0]):
        a = xs[j]
        for i in range(nh):
            h1[i] += w1t[j, i] * a
    for i in range(nh):
        h2[i] = b2[i]
    for j in range(nh):
        if h1[j] > 0.0:
            a = h1[j]
            for i in range(nh):
                h2[i] += w2t[j, i] * a
        else:
            h1[j] = 0.0
    for i in range(out.shape[0]):
        out[i] = b3[i]
    for j in range(nh):
        if h2[j] > 0.0:
            a = h2[j]
            for i in range(out.shape[0]):
                out[i] += w3t[j, i] * a
        else:
            h2[j] = 0.0


@_njit
def _mlp_backward(w1, w2, w3, xs, h1, h2, d_out, g, d_h1, d_h2, d_xs) -> None:
    """Add the gradients of the weights and biases (``g``: ∂W₁, ∂b₁, ∂W₂, ∂b₂, ∂W₃, ∂b₃) from the
    output's gradient ``d_out``, and add the input's gradient to ``d_xs``."""
    gw1, gb1, gw2, gb2, gw3, gb3 = g
    nh = h1.shape[0]
    for j in range(nh):
        d_h2[j] = 0.0
    for k in range(d_out.shape[0]):
        a = d_out[k]
        if a != 0.0:
            gb3[k] += a
            for j in range(nh):
                gw3[k, j] += a * h2[j]
                d_h2[j] += w3[k, j] * a
    for j in range(nh):
        d_h1[j] = 0.0
    for k in range(nh):
        a = d_h2[k]
        if a != 0.0 and h2[k] > 0.0:
            gb2[k] += a
            for j in range(nh):
                gw2[k, j] += a * h1[j]
                d_h1[j] += w2[k, j] * a
    for k in range(nh):
        a = d_h1[k]
        if a != 0.0 and h1[k] > 0.0:
            gb1[k] += a
            for j in range(xs.shape[0]):
                gw1[k, j] += a * xs[j]
                d_xs[j] += w1[k, j] * a


@_njit
def _batch(pa, pg, sx, su, sa, bound, dt, x0, u, p, cap, ga, gg) -> float:
    """The batch's mean capped error (:func:`loss_and_grads`), its gradient added to ``ga`` and
    ``gg`` (the networks' weights and biases, in their layouts)."""
    wa1, ba1, wa2, ba2, wa3, ba3 = pa
    wg1, bg1, wg2, bg2, wg3, bg3 = pg
    wa1t, wa2t, wa3t = wa1.T.copy(), wa2.T.copy(), wa3.T.copy()
    wg1t, wg2t, wg3t = wg1.T.copy(), wg2.T.copy(), wg3.T.copy()
    n_win, horizon, m = u.shape
    n = x0.shape[1]
    d = n // 2
    nh = ba1.shape[0]
    n_a, n_g = ba3.shape[0], bg3.shape[0]
    # the tape of one window: each stage's input state, the networks' activations and outputs
    xst = np.empty((horizon, 4, n))
    h1a = np.empty((horizon, 4, nh))
    h2a = np.empty((horizon, 4, nh))
    h1g = np.empty((horizon, 4, nh))
    h2g = np.empty((horizon, 4, nh))
    oa = np.empty((horizon, 4, n_a))
    og = np.empty((horizon, 4, n_g))
    held = np.empty((horizon, n), dtype=np.bool_)
    xs_run = np.empty((horizon, n))
    ks = np.empty((4, n))
    x = np.empty(n)
    xs = np.empty(n)
    us = np.empty(m)
    lam = np.empty(n)
    lam_x = np.empty(n)
    lam_k = np.empty((4, n))
    d_xs = np.empty(n)
    d_oa = np.empty(n_a)
    d_og = np.empty(n_g)
    d_h1 = np.empty(nh)
    d_h2 = np.empty(nh)
    total = 0.0
    inv_n = 1.0 / n_win
    for b in range(n_win):
        # forward: rollout.simulate's RK4, taped
        for i in range(n):
            x[i] = x0[b, i]
        err = 0.0
        for k in range(horizon):
            for j in range(m):
                us[j] = u[b, k, j] / su[j]
            for s in range(4):
                c = _STAGE[s] * dt
                for i in range(n):
                    xst[k, s, i] = x[i] + c * ks[s - 1, i] if s > 0 else x[i]
                    xs[i] = xst[k, s, i] / sx[i]
                _mlp_forward(wa1t, ba1, wa2t, ba2, wa3t, ba3, xs, h1a[k, s], h2a[k, s], oa[k, s])
                _mlp_forward(wg1t, bg1, wg2t, bg2, wg3t, bg3, xs, h1g[k, s], h2g[k, s], og[k, s])
                for i in range(d):
                    ks[s, i] = xst[k, s, d + i]
                    acc = 0.0
                    for j in range(n):
                        acc += oa[k, s, j * d + i] * xs[j]
                    for j in range(m):
                        acc += og[k, s, j * d + i] * us[j]
                    ks[s, d + i] = sa[i] * acc
            for i in range(n):
                y = x[i] + dt / 6.0 * (ks[0, i] + 2.0 * ks[1, i] + 2.0 * ks[2, i] + ks[3, i])
                held[k, i] = y > bound[i] or y < -bound[i]
                x[i] = min(max(y, -bound[i]), bound[i])
                xs_run[k, i] = x[i]
            for i in range(d):
                e = (x[i] - p[b, k, i]) / sx[i]
                err += e * e
        err /= horizon
        if not np.isfinite(err):
            return np.nan
        if err > cap:
            total += cap
            continue
        total += err
        # backward: the adjoint of each step, last to first
        for i in range(n):
            lam[i] = 0.0
        for k in range(horizon - 1, -1, -1):
            for i in range(d):
                lam[i] += inv_n * 2.0 / horizon * (xs_run[k, i] - p[b, k, i]) / (sx[i] * sx[i])
            for i in range(n):
                if held[k, i]:
                    lam[i] = 0.0
                lam_x[i] = lam[i]
                lam_k[0, i] = dt / 6.0 * lam[i]
                lam_k[1, i] = dt / 3.0 * lam[i]
                lam_k[2, i] = dt / 3.0 * lam[i]
                lam_k[3, i] = dt / 6.0 * lam[i]
            for j in range(m):
                us[j] = u[b, k, j] / su[j]
            for s in range(3, -1, -1):
                for i in range(n):
                    xs[i] = xst[k, s, i] / sx[i]
                    d_xs[i] = 0.0
                for i in range(d):
                    g = sa[i] * lam_k[s, d + i]
                    for j in range(n):
                        d_oa[j * d + i] = g * xs[j]
                        d_xs[j] += oa[k, s, j * d + i] * g
                    for j in range(m):
                        d_og[j * d + i] = g * us[j]
                _mlp_backward(wa1, wa2, wa3, xs, h1a[k, s], h2a[k, s], d_oa, ga, d_h1, d_h2, d_xs)
                _mlp_backward(wg1, wg2, wg3, xs, h1g[k, s], h2g[k, s], d_og, gg, d_h1, d_h2, d_xs)
                # the stage's input adjoint: through x̃ = x / s_x, and v passed on as f's first half
                for i in range(n):
                    d_xs[i] /= sx[i]
                for i in range(d):
                    d_xs[d + i] += lam_k[s, i]
                for i in range(n):
                    lam_x[i] += d_xs[i]
                    if s > 0:
                        lam_k[s - 1, i] += _STAGE[s] * dt * d_xs[i]
            for i in range(n):
                lam[i] = lam_x[i]
    return total * inv_n


@_njit
def free_runs(w1, b1, w2, b2, w3, b3, d, x0, u, dt, bound, out) -> None:
    """out (B, H, d): the positions of B runs of the fused float64 network
    (:func:`~soft_gripper_sdre.learning.rollout.fused_network`: each layer's weights (inputs,
    outputs), the output row-major [A21 A22] (d, 2d) then G2 (d, m), SI) from x0 (B, 2d) under
    the inputs u (B, H, m), one RK4 step of ``dt`` per input held, each state then held within
    ±``bound`` (2d,), a NaN kept: :func:`~soft_gripper_sdre.learning.rollout.simulate_numpy`'s
    runs to rounding, for the epochs' validation scores."""
    n, m = x0.shape[1], u.shape[2]
    nh, n_a = b1.shape[0], 2 * d * d
    h1, h2, o = np.empty(nh), np.empty(nh), np.empty(b3.shape[0])
    ks = np.empty((4, n))
    x, xt = np.empty(n), np.empty(n)
    for b in range(x0.shape[0]):
        for i in range(n):
            x[i] = x0[b, i]
        for k in range(u.shape[1]):
            for s in range(4):
                c = _STAGE[s] * dt
                for i in range(n):
                    xt[i] = x[i] + c * ks[s - 1, i] if s > 0 else x[i]
                _mlp_forward(w1, b1, w2, b2, w3, b3, xt, h1, h2, o)
                for i in range(d):
                    ks[s, i] = xt[d + i]
                    acc = 0.0
                    for j in range(n):
                        acc += o[i * n + j] * xt[j]
                    for j in range(m):
                        acc += o[n_a + i * m + j] * u[b, k, j]
                    ks[s, d + i] = acc
            for i in range(n):
                y = x[i] + dt / 6.0 * (ks[0, i] + 2.0 * ks[1, i] + 2.0 * ks[2, i] + ks[3, i])
                if y > bound[i]:
                    y = bound[i]
                elif y < -bound[i]:
                    y = -bound[i]
                x[i] = y
            for i in range(d):
                out[b, k, i] = x[i]


def _arrays(seq) -> tuple[np.ndarray, ...]:
    return tuple(np.ascontiguousarray(t.detach().numpy(), dtype=np.float64) for t in seq)


def loss_and_grads(net: SDCNet, s: Scales, dt: float, x0: np.ndarray, u: np.ndarray,
                   p: np.ndarray) -> tuple[float, list[torch.Tensor]]:
    """The mean over the windows of each window's L_sim capped at
    :data:`~soft_gripper_sdre.learning.rollout.SIM_ERROR_CAP`, the state held within
    :data:`~soft_gripper_sdre.learning.rollout.SIM_BOUND` data standard deviations (as
    :func:`~soft_gripper_sdre.learning.rollout.sim_error`), and its gradient with respect to
    ``net.parameters()``, in that order (tensors of the networks' dtype; float64 arithmetic).

    ``s`` the data's scales; ``x0`` (B, 2d), ``u`` (B, H, m), ``p`` (B, H, d) float64 arrays (SI).
    A loss that is not finite comes back as NaN."""
    params = list(net.parameters())
    pa, pg = _arrays(params[:6]), _arrays(params[6:])
    ga = tuple(np.zeros_like(a) for a in pa)
    gg = tuple(np.zeros_like(a) for a in pg)
    sx, su, sa = _arrays((s.x, s.u, s.acc))
    loss = _batch(pa, pg, sx, su, sa, SIM_BOUND * sx, float(dt), x0, u, p, SIM_ERROR_CAP, ga, gg)
    return float(loss), [torch.from_numpy(g).to(params[0].dtype) for g in ga + gg]
