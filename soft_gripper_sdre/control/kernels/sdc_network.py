"""The fused SDC network compiled with numba: x ↦ [A21 A22](x), G2(x) for one finger
(:func:`finger_blocks`) and for n (:func:`sdc_forward`), on the network packed in one array
(:class:`~soft_gripper_sdre.control.kernels.SdcNetwork`).
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels.cache import kernel


@kernel
def network_arrays(network, hidden):
    """(layers, scratch) of the packed network: the layers w1 (4, h), b1 (h,), w2 (h, h), b2 (h,),
    w3 (h, 12), b3 (12,) as views of ``network``, which holds them one after the other
    (h = ``hidden``); the activations h1 (h,), h2 (h,), out (12,) that :func:`finger_blocks` works
    in, three arrays so that the compiler knows a store to one leaves the others unchanged."""
    h = hidden
    e1 = 4 * h
    e2 = e1 + h
    e3 = e2 + h * h
    e4 = e3 + h
    e5 = e4 + 12 * h
    layers = (network[:e1].reshape((4, h)), network[e1:e2], network[e2:e3].reshape((h, h)),
              network[e3:e4], network[e4:e5].reshape((h, 12)), network[e5:e5 + 12])
    return layers, (np.empty(h), np.empty(h), np.empty(12))


@kernel
def finger_blocks(x, layers, scratch, a2, g2):
    """a2 (2, 4) = [A21 A22](x) and g2 (2, 2) = G2(x) for one state x (4,): the fused network
    (``layers`` and ``scratch`` from :func:`network_arrays`).

    A negative hidden unit (ReLU: 0) is skipped; NaN is not, so a non-finite state gives
    non-finite blocks.
    """
    w1, b1, w2, b2, w3, b3 = layers
    h1, h2, out = scratch
    hidden = b1.shape[0]
    h1[:] = b1
    for k in range(4):
        for j in range(hidden):
            h1[j] += x[k] * w1[k, j]
    h2[:] = b2
    for k in range(hidden):
        if h1[k] < 0.0:
            continue                                   # relu(h) = 0
        for j in range(hidden):
            h2[j] += h1[k] * w2[k, j]
    out[:] = b3
    for k in range(hidden):
        if h2[k] < 0.0:
            continue
        for j in range(12):
            out[j] += h2[k] * w3[k, j]
    for r in range(2):
        for c in range(4):
            a2[r, c] = out[4 * r + c]
        for c in range(2):
            g2[r, c] = out[8 + 2 * r + c]


@kernel
def sdc_forward(x, network, hidden, a2, g2):
    """a2 (n, 2, 4) = [A21 A22](x) and g2 (n, 2, 2) = G2(x) for states x (n, 4): the fused network,
    packed (:func:`network_arrays`)."""
    layers, scratch = network_arrays(network, hidden)
    for i in range(x.shape[0]):
        finger_blocks(x[i], layers, scratch, a2[i], g2[i])

