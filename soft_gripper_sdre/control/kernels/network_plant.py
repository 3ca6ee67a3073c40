"""The learned model as a plant, compiled: ẋ = A(x)x + G(x)u of the fused SDC network
(``SDCModel.fused_network``: its layers w1, b1, w2, b2, w3, b3 as float64 arrays, the output
row-major [A21 A22] (d, 2d) then G2 (d, m)) for one state, and its classical Runge–Kutta steps
with the input held (:class:`~soft_gripper_sdre.analysis.model_fitness.CompiledRK4`, the
closed-loop checks' plant, :mod:`~soft_gripper_sdre.control.kernels.check_loop`).
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel


@kernel
def _layer(h, w, b, out, relu):
    """out = h @ w + b, then ReLU (one that keeps NaN, as np.maximum) when ``relu``. Each output
    sums its products in the order of h's entries from 0.0, then adds its bias; the loops run
    along w's rows, so the products of one entry of h with a row are independent and run as
    vector instructions."""
    out[:] = 0.0
    for k in range(h.shape[0]):
        hk = h[k]
        for j in range(out.shape[0]):
            out[j] += hk * w[k, j]
    for j in range(out.shape[0]):
        v = out[j] + b[j]
        out[j] = 0.0 if relu and v < 0.0 else v


@kernel
def network_xdot(x, u, w1, b1, w2, b2, w3, b3, d, h1, h2, out, dx):
    """dx (2d,) = ẋ = [ṗ; A₂(x) x + G₂(x) u] for one state x (2d,) and input u (m,): the fused
    network's blocks (``SDCModel.fused_network``), row-major [A21 A22] (d, 2d) then G2 (d, m);
    h1, h2 and out are the activations' scratch."""
    ns, m = 2 * d, u.shape[0]
    _layer(x, w1, b1, h1, True)
    _layer(h1, w2, b2, h2, True)
    _layer(h2, w3, b3, out, False)
    for i in range(d):
        dx[i] = x[d + i]
        acc = 0.0
        for j in range(ns):
            acc += out[i * ns + j] * x[j]
        for j in range(m):
            acc += out[2 * d * d + i * m + j] * u[j]
        dx[d + i] = acc


@kernel
def network_rk4(x, u, dt, substeps, w1, b1, w2, b2, w3, b3, d):
    """``substeps`` classical Runge–Kutta steps of dt / substeps [s] of ẋ = A(x)x + G(x)u for one
    state x (2d,), in place, the input u (m,) held
    (:func:`~soft_gripper_sdre.analysis.model_fitness.rk4_step`'s arithmetic)."""
    ns, hidden = 2 * d, b1.shape[0]
    h1, h2, out = np.empty(hidden), np.empty(hidden), np.empty(b3.shape[0])
    k1, k2, k3, k4, xt = (np.empty(ns), np.empty(ns), np.empty(ns), np.empty(ns),
                          np.empty(ns))
    h = dt / substeps
    for _ in range(substeps):
        network_xdot(x, u, w1, b1, w2, b2, w3, b3, d, h1, h2, out, k1)
        for i in range(ns):
            xt[i] = x[i] + 0.5 * h * k1[i]
        network_xdot(xt, u, w1, b1, w2, b2, w3, b3, d, h1, h2, out, k2)
        for i in range(ns):
            xt[i] = x[i] + 0.5 * h * k2[i]
        network_xdot(xt, u, w1, b1, w2, b2, w3, b3, d, h1, h2, out, k3)
        for i in range(ns):
            xt[i] = x[i] + h * k3[i]
        network_xdot(xt, u, w1, b1, w2, b2, w3, b3, d, h1, h2, out, k4)
        for i in range(ns):
            x[i] = x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@kernel
def network_run(x0, u, dt, substeps, bound, w1, b1, w2, b2, w3, b3, d, out):
    """out (T + 1, 2d): the run from x0 (2d,) under the inputs u (T, m), each held over ``dt``
    [s] in ``substeps`` RK4 steps; NaN from the first state that leaves ``bound`` or is not
    finite on (:func:`~soft_gripper_sdre.analysis.model_fitness.simulate`'s rule)."""
    x = x0.copy()
    out[:] = np.nan
    out[0] = x
    for k in range(u.shape[0]):
        network_rk4(x, u[k], dt, substeps, w1, b1, w2, b2, w3, b3, d)
        for i in range(x.shape[0]):
            if not (np.isfinite(x[i]) and abs(x[i]) < bound):
                return
        out[k + 1] = x

