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

from soft_gripper_sdre.learning.model import SDCNet, fused_layers

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
    :data:`SIM_ERROR_CAP` (a diverged run counts as the cap).

    Scored as the deployed model evaluates the networks (:class:`~soft_gripper_sdre.learning.model.
    SDCModel`: both networks fused into three float64 layers in SI units), the runs compiled
    (:func:`~soft_gripper_sdre.learning.compiled_rollout.free_runs`): they are
    sequential and a few windows wide, so any array library's cost per operation, not the
    arithmetic, would set their time (at 500 Hz one scoring took 1.2 s in torch, 0.19 s in numpy).
    The same runs as :func:`simulate_numpy` to rounding, and as :func:`window_errors` to float32
    rounding."""
    layers = fused_network(net, s)
    total, count = 0.0, 0
    for dt, x0, u, p in val_windows:
        err = window_errors_numpy(layers, net.shape.d, s, dt, x0, u, p, compiled=True)
        total += float(err.sum())
        count += err.size
    return total / count


def fused_network(net: SDCNet, s: Scales) -> list[tuple[np.ndarray, np.ndarray]]:
    """The networks' current weights as the deployed model's three float64 layers in SI units
    (:func:`~soft_gripper_sdre.learning.model.fused_layers`)."""
    sd = {k: v.detach().double().numpy() for k, v in net.state_dict().items()}
    scales = {k: getattr(s, k).detach().double().numpy() for k in ('x', 'u', 'acc')}
    return fused_layers(sd, scales, net.shape)


def simulate_numpy(layers: list[tuple[np.ndarray, np.ndarray]], d: int, s: Scales, x0, u,
                   dt: float) -> np.ndarray:
    """:func:`simulate` with the fused float64 network (:func:`fused_network`): positions
    (B, H, d) of the RK4 runs from x0 (B, 2d), inputs u (B, H, m) held (SI, arrays or tensors)."""
    (w1, b1), (w2, b2), (w3, b3) = layers
    x = np.asarray(x0, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    n, m = x.shape[0], u.shape[2]
    a_out = 2 * d * d

    def f(x, uk):
        h = x @ w1
        h += b1
        np.maximum(h, 0.0, out=h)
        h = h @ w2
        h += b2
        np.maximum(h, 0.0, out=h)
        out = h @ w3
        out += b3
        acc = (np.einsum('bij,bj->bi', out[:, :a_out].reshape(n, d, 2 * d), x)
               + np.einsum('bij,bj->bi', out[:, a_out:].reshape(n, d, m), uk))
        return np.concatenate([x[:, d:], acc], axis=1)

    bound = SIM_BOUND * s.x.detach().double().numpy()
    out = np.empty((n, u.shape[1], d))
    with np.errstate(all='ignore'):
        for k in range(u.shape[1]):
            uk = u[:, k]
            k1 = f(x, uk)
            k2 = f(x + 0.5 * dt * k1, uk)
            k3 = f(x + 0.5 * dt * k2, uk)
            k4 = f(x + dt * k3, uk)
            x = np.maximum(np.minimum(x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4), bound),
                           -bound)
            out[:, k] = x[:, :d]
    return out


def simulate_compiled(layers: list[tuple[np.ndarray, np.ndarray]], d: int, s: Scales, x0, u,
                      dt: float) -> np.ndarray:
    """:func:`simulate_numpy` compiled (:func:`~soft_gripper_sdre.learning.compiled_rollout.
    free_runs`): the same runs to rounding."""
    from soft_gripper_sdre.learning.compiled_rollout import free_runs  # it imports this module
    x0 = np.ascontiguousarray(np.asarray(x0, dtype=np.float64))
    u = np.ascontiguousarray(np.asarray(u, dtype=np.float64))
    bound = SIM_BOUND * s.x.detach().double().numpy()
    out = np.empty((x0.shape[0], u.shape[1], d))
    free_runs(*(np.ascontiguousarray(a) for layer in layers for a in layer), d, x0, u, float(dt),
              bound, out)
    return out


def window_errors_numpy(layers, d: int, s: Scales, dt: float, x0, u, p,
                        compiled: bool = False) -> np.ndarray:
    """:func:`window_errors` with :func:`simulate_numpy` (``compiled``: :func:`simulate_compiled`):
    each window's L_sim, capped at :data:`SIM_ERROR_CAP`, a run that is not finite counted as the
    cap."""
    scale = s.x[:d].detach().double().numpy()
    run = simulate_compiled if compiled else simulate_numpy
    with np.errstate(all='ignore'):
        err = (((run(layers, d, s, x0, u, dt) - np.asarray(p, dtype=np.float64))
                / scale) ** 2).sum(axis=-1).mean(axis=1)
        err = np.minimum(err, SIM_ERROR_CAP)
    return np.where(np.isfinite(err), err, SIM_ERROR_CAP)
