"""The model's own simulation of the records, and its error: what the simulation stage of training
(:mod:`soft_gripper_sdre.learning.training`) fits and how it scores the epochs.

From each window start, an estimated state of a record, the networks are integrated (RK4, the
recorded input held over each period) for H samples, and their positions are compared with the
estimated ones,

    L_sim = mean over windows and steps of ‖(p̂_k − p_k) / s_p‖²,   k = 1 … H.

A diverging run must not turn the mean into inf or NaN: the simulated state is held within
:data:`SIM_BOUND` data standard deviations, and a window counts at most :data:`SIM_ERROR_CAP`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from soft_gripper_sdre.learning.model import SDCNet

#: a simulated state is held within this many data standard deviations, so a diverging run
#: stays finite (its window then counts at most :data:`SIM_ERROR_CAP`, and passes no gradient)
SIM_BOUND = 100.0
#: a window's simulation error counts at most this (scaled units: a run off by ten standard
#: deviations of the data), so one diverged window does not hide how the others do
SIM_ERROR_CAP = 100.0


class Run(NamedTuple):
    """A contiguous record on a uniform grid for the simulation stage: estimated states x (N, 2d)
    (translated, SI), the held inputs u (N, m) (SI) and the grid spacing dt [s]."""

    x: np.ndarray
    u: np.ndarray
    dt: float


class Scales(NamedTuple):
    """The data's standard deviations (SI) that make the networks' units: state (2d,), input
    (m,), acceleration (d,)."""

    x: torch.Tensor
    u: torch.Tensor
    acc: torch.Tensor


def windows(runs: list[Run], seconds: float,
            overlap: int) -> list[tuple[float, torch.Tensor, ...]]:
    """Windows of ``seconds`` (H samples) starting every H / ``overlap`` samples into each run,
    grouped by grid spacing: [(dt, starts (B, 2d), inputs (B, H, m), positions (B, H, d))]."""
    groups: dict[float, list[list[np.ndarray]]] = {}
    for run in runs:
        h = max(int(round(seconds / run.dt)), 1)
        starts = range(0, len(run.x) - h, max(h // overlap, 1))
        if not starts:
            continue
        got = groups.setdefault(float(run.dt), [[], [], []])
        got[0] += [run.x[i] for i in starts]
        got[1] += [run.u[i:i + h] for i in starts]
        d = run.x.shape[1] // 2
        got[2] += [run.x[i + 1:i + h + 1, :d] for i in starts]
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return [(dt, f32(x0), f32(u), f32(p)) for dt, (x0, u, p) in sorted(groups.items())]


def simulate(net: SDCNet, s: Scales, x0: torch.Tensor, u: torch.Tensor,
             dt: float) -> torch.Tensor:
    """Positions (B, H, d) of the model's RK4 runs from x0 (B, 2d), inputs u (B, H, m) held."""
    d = net.shape.d

    def f(x, uk):
        return torch.cat([x[:, d:], net.accel(x / s.x, uk / s.u) * s.acc], dim=1)
    bound = SIM_BOUND * s.x
    x, out = x0, []
    for k in range(u.shape[1]):
        uk = u[:, k]
        k1 = f(x, uk)
        k2 = f(x + 0.5 * dt * k1, uk)
        k3 = f(x + 0.5 * dt * k2, uk)
        k4 = f(x + dt * k3, uk)
        x = torch.maximum(torch.minimum(x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4), bound),
                          -bound)
        out.append(x[:, :d])
    return torch.stack(out, dim=1)


def window_errors(net: SDCNet, s: Scales, dt: float, x0, u, p) -> torch.Tensor:
    """Each window's L_sim (module doc), positions in units of their scale, capped at
    :data:`SIM_ERROR_CAP`."""
    d = net.shape.d
    err = (((simulate(net, s, x0, u, dt) - p) / s.x[:d]) ** 2).sum(dim=-1).mean(dim=1)
    return err.clamp(max=SIM_ERROR_CAP)


def sim_error(net: SDCNet, s: Scales, dt: float, x0, u, p) -> torch.Tensor:
    """L_sim of a batch of windows."""
    return window_errors(net, s, dt, x0, u, p).mean()


def val_sim_error(net: SDCNet, s: Scales, val_windows) -> float:
    """L_sim over every validation window (:func:`windows`), each window's error capped at
    :data:`SIM_ERROR_CAP` (a diverged run counts as the cap)."""
    total, count = 0.0, 0
    with torch.no_grad():
        for dt, x0, u, p in val_windows:
            err = window_errors(net, s, dt, x0, u, p)
            err = torch.where(torch.isfinite(err), err, torch.full_like(err, SIM_ERROR_CAP))
            total += float(err.sum())
            count += err.numel()
    return total / count
