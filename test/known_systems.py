"""Known SDC systems of the shapes (2, 1), (3, 3) and (2, 3) and a short real training run on
each, shared by the tests of the learned model and of the checks' compiled plant."""
from dataclasses import replace

import numpy as np
import torch

from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import train
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

#: G2 of each shape [m/s² per unit input]: the directions training must find
SYSTEMS = {
    # one pneumatic chamber (0..2e5 Pa) bending a planar tip toward +X, a little −Y
    (2, 1): (np.array([[5e-6], [-2e-6]]), InputBounds([0.0], [2e5])),
    # three pull-only tendons (0..2 N) of a 3-D segment, 120° apart, each also lifting the tip
    (3, 3): (np.array([[0.6, -0.3, -0.3], [0.0, 0.52, -0.52], [0.2, 0.2, 0.2]]),
             InputBounds([0.0] * 3, [2.0] * 3)),
    # three bidirectional motors on a planar tip (more inputs than coordinates)
    (2, 3): (np.array([[0.5, 0.0, 0.35], [0.0, 0.5, -0.35]]), InputBounds.symmetric(0.5, 3)),
}
STIFFNESS, DAMPING = 400.0, 20.0       # p̈ = −k p − c ṗ + G2 u


def system_data(d: int, m: int, n: int, seed: int):
    """States (n, 2d), inputs (n, m) drawn within the bounds, and exact accelerations (n, d) of
    the system of shape (d, m): positions about the rest the inputs' mid level holds."""
    G2, bounds = SYSTEMS[(d, m)]
    rng = np.random.default_rng(seed)
    u = bounds.lower + (bounds.upper - bounds.lower) * rng.random((n, m))
    mid = (G2 @ bounds.mid) / STIFFNESS                  # where the mid level settles
    p = mid + 0.5 * np.abs(mid).max() * rng.standard_normal((n, d))
    v = 10 * np.abs(mid).max() * rng.standard_normal((n, d))
    acc = -STIFFNESS * p - DAMPING * v + u @ G2.T
    return np.hstack([p, v]), u, acc


def fit(d: int, m: int, epochs: int = 60, **changes):
    """A short real training run on the known system of shape (d, m)."""
    torch.set_num_threads(1)
    data = system_data(d, m, 3000, 0) + system_data(d, m, 600, 1)
    settings = replace(PRESETS['default'], epochs=epochs, **changes)
    return train(*data, settings, shape=FingerShape(d, m)), settings, data
