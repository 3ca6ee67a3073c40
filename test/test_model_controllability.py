"""Controllability-aware learning: the penalty on G2's smallest singular value
(learning/training.py)."""
from dataclasses import replace

import numpy as np
import torch

from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import train


def _data(n, seed):
    """A plant ẍ = −ω² x + G2 u driven with *equal* torques (like the paper's signals), so the data
    only pin down G2's row sums: nothing keeps the learned G2 invertible."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 1, (n, 4))
    u = np.repeat(rng.normal(0, 1, (n, 1)), 2, axis=1)
    G2 = np.array([[0.2, 1.0], [-1.0, 0.1]])
    acc = -4.0 * x[:, :2] - 0.5 * x[:, 2:] + u @ G2.T
    return x, u, acc


def _min_singular_value(net, box=3.0, n=2000):
    xs = (torch.rand(n, 4, generator=torch.Generator().manual_seed(9)) * 2 - 1) * box
    with torch.no_grad():
        return torch.linalg.svdvals(net(xs)[1])[:, -1].numpy()


def test_singular_value_penalty_keeps_g2_invertible_over_the_box():
    x, u, acc = _data(3000, 0)
    xv, uv, accv = _data(500, 1)
    base = replace(PRESETS['default'], epochs=15, patience=100)
    plain = train(x, u, acc, xv, uv, accv, base)
    aware = train(x, u, acc, xv, uv, accv, replace(base, sv_penalty=10.0, sv_floor=0.3))
    s_plain, s_aware = _min_singular_value(plain.net), _min_singular_value(aware.net)
    assert np.quantile(s_aware, 0.05) > 0.25  # the floor holds almost everywhere
    assert np.quantile(s_aware, 0.05) > 2 * np.quantile(s_plain, 0.05)
    # and the fit is not given up for it: the validation loss stays within 2× of the plain one
    assert aware.val_loss[aware.best_epoch] < 2 * plain.val_loss[plain.best_epoch] + 1e-3
