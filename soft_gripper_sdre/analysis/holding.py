"""Where the learned model can be held still, and with what torque: the closed-loop check's move
(:mod:`~soft_gripper_sdre.analysis.loop_settings`) goes no farther than the model holds with
:data:`HOLD_SHARE` of the torque limit, the rest being the feedback's.

ẋ = A(x)x + G(x)u is affine in u, so at rest at a displacement p (x = [p, 0]) the torque that
holds the model still solves G₂(x) u = −(A(x)x)₂, with G₂'s columns read off the model's ẋ as
the change per unit of each input.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.analysis import model_fitness
from soft_gripper_sdre.analysis.data_facts import DataFacts

#: the check's move holds still with at most this share of the torque limit (the rest is the
#: feedback's)
HOLD_SHARE = 0.5
#: displacements tried for the holdable travel, as shares of the reach's travel
HOLD_GRID = 40


def hold_torques(model, points: np.ndarray) -> np.ndarray:
    """(N, 2) torques that hold the learned model still at the displacements ``points`` (N, 2)
    from its rest: u = −G₂(x)⁻¹ (A(x)x)₂, from ẋ = A(x)x + G(x)u being affine in u."""
    n = len(points)
    x = np.zeros((n, 4))
    x[:, :2] = points
    free = model_fitness.xdot(model, x, np.zeros((n, 2)))[:, 2:]
    G2 = np.stack([model_fitness.xdot(model, x, np.tile(e, (n, 1)))[:, 2:] - free
                   for e in np.eye(2)], axis=2)
    return -np.stack([np.linalg.lstsq(g, f, rcond=None)[0] for g, f in zip(G2, free)])


def holdable_travel(model, facts: DataFacts) -> float:
    """The largest displacement along ``facts.direction``, up to ``facts.travel``, that every
    smaller one included the model holds with :data:`HOLD_SHARE` of ``facts.torque_limit``."""
    lengths = facts.travel * np.arange(1, HOLD_GRID + 1) / HOLD_GRID
    need = np.abs(hold_torques(model, np.outer(lengths, facts.unit))).max(axis=1)
    over = np.flatnonzero(~(need <= HOLD_SHARE * facts.torque_limit))    # NaN counts as over
    if not over.size:
        return facts.travel
    return float(lengths[over[0] - 1]) if over[0] > 0 else 0.0
