"""Training the SDC networks (eq. 18) and writing their checkpoint.

Two stages. The first fits the networks to acceleration labels (eq. 18), the paper's method.
The second, on when ``rollout_epochs`` > 0 (the ``gripper`` preset), fits the model's own
simulation: from each estimated state of a record, the model is integrated (RK4, the recorded
input held over each period) for ``rollout_seconds`` and its positions are compared with the
estimated ones,

    L_sim = mean over windows and steps of ‖(p̂_k − p_k) / s_p‖²,   k = 1 … H,

so errors that compound over a few periods, which one-step labels hide, are paid for. On a finger
whose accelerations are barely above the noise (small, slow or sticky motions) the labels alone
leave a model whose rest is unstable though its R² looks fine; positions carry the same
information at a far better signal-to-noise ratio. With ``rest_margin`` > 0 both stages add

    L_rest = rest_weight · Σᵢ relu(Re λᵢ(A(0)) + rest_margin)²,

which keeps the learned rest stable (every eigenvalue of A(0) left of −rest_margin), as the
finger's is. When the rollout stage is on, the kept weights are those of the epoch, in either
stage, whose free runs of ``rollout_val_seconds`` on the validation records miss least.

Seeded and deterministic: the same data and settings give the same bits on the same machine kind
and torch build (:data:`TRAIN_THREADS` intra-op threads, torch's deterministic algorithms only).
The networks, the checkpoint's layout and reading it back are
:mod:`soft_gripper_sdre.learning.model`.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
import hashlib
import math
from pathlib import Path
import time
from typing import Callable, Iterator, NamedTuple

import numpy as np
import torch

from soft_gripper_sdre.learning.model import FORMAT_VERSION, HIDDEN, SDCNet

#: intra-op threads while training: the order of torch's reductions, and so every weight's bits,
#: depends on it
TRAIN_THREADS = 1


@dataclass(frozen=True)
class TrainSettings:
    """A training preset. ``paper``: Adam 1e-5, 70 epochs, unscaled, as published.

    ``patience``: stop after this many epochs without a new best validation loss; None runs the
    whole budget. The default preset runs it: its cosine schedule anneals the learning rate to zero
    over the budget, while a stop decided by the noisy mid-schedule validation curve can fall
    tens of epochs earlier or later when the data change at rounding level, and so give another
    model. Either way the weights of the best validation epoch are kept.
    """

    preset: str = 'default'
    epochs: int = 300
    lr: float = 1e-3
    batch_size: int = 256
    cosine: bool = True
    scale: bool = True
    weight_decay: float = 0.0
    patience: int | None = None
    seed: int = 0
    hidden: int = HIDDEN
    #: controllability-aware learning (README "Beyond the paper"): weight of the penalty
    #: mean(relu(σ_floor − σ_min(G2(x)))²) on G2's smallest singular value at states drawn uniformly
    #: from a box of ±sv_box (scaled units: data standard deviations) each batch; 0 = off
    sv_penalty: float = 0.0
    sv_floor: float = 0.3
    sv_box: float = 3.0
    #: simulation-error stage (module doc): epochs (0 = off), window length [s], learning rate,
    #: and how many windows cover each sample (their starts are H / overlap samples apart, so
    #: the cost per epoch does not grow with the rate)
    rollout_epochs: int = 0
    rollout_seconds: float = 0.1
    rollout_lr: float = 3e-4
    rollout_overlap: int = 5
    #: the epochs are scored by free runs of this length [s] on the validation records, as long
    #: as the verdict's (analysis/model_fitness.py): 0.1 s runs of a slow signal cannot tell a
    #: quasi-static model from the finger
    rollout_val_seconds: float = 1.0
    #: stable learned rest (module doc): A(0)'s eigenvalues kept left of −rest_margin [1/s]
    #: (0 = off) by a penalty of this weight
    rest_margin: float = 0.0
    rest_weight: float = 10.0

    def __post_init__(self) -> None:
        if self.patience is not None and not (isinstance(self.patience, int)
                                              and self.patience >= 1):
            raise ValueError(f'patience must be an int >= 1 or None (run every epoch), '
                             f'got {self.patience!r}')
        if not (np.isfinite(self.sv_penalty) and self.sv_penalty >= 0.0):
            raise ValueError(f'sv_penalty must be finite and >= 0 (0 = off), '
                             f'got {self.sv_penalty!r}')
        for name in ('sv_floor', 'sv_box', 'rollout_seconds', 'rollout_lr', 'rest_weight',
                     'rollout_val_seconds'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v!r}')
        for name in ('rollout_epochs', 'rollout_overlap'):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= (0 if name == 'rollout_epochs' else 1)):
                raise ValueError(f'{name} must be an int >= '
                                 f'{0 if name == "rollout_epochs" else 1}, got {v!r}')
        if not (np.isfinite(self.rest_margin) and self.rest_margin >= 0.0):
            raise ValueError(f'rest_margin must be finite and >= 0 (0 = off), '
                             f'got {self.rest_margin!r}')


PRESETS = {
    'default': TrainSettings(),
    'paper': TrainSettings(preset='paper', epochs=70, lr=1e-5, batch_size=64, cosine=False,
                           scale=False),
    # a gripper of your own (docs/own_gripper.md): labels, then the simulation error, rest kept
    # stable
    'gripper': TrainSettings(preset='gripper', rollout_epochs=40, rest_margin=1.0),
}


class Run(NamedTuple):
    """A contiguous record on a uniform grid for the simulation stage: estimated states x (N, 4)
    (translated, SI), the held inputs u (N, 2) [N·m] and the grid spacing dt [s]."""

    x: np.ndarray
    u: np.ndarray
    dt: float


@dataclass
class TrainResult:
    net: SDCNet
    scales: dict[str, np.ndarray]
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0
    #: the simulation stage (empty when off): its training loss per epoch, and the validation
    #: simulation error per epoch of both stages
    rollout_loss: list[float] = field(default_factory=list)
    val_sim_error: list[float] = field(default_factory=list)


def _scales(x: np.ndarray, u: np.ndarray, acc: np.ndarray, scale: bool) -> dict[str, np.ndarray]:
    if not scale:
        return {'x': np.ones(4), 'u': np.ones(2), 'acc': np.ones(2)}
    std = lambda a: np.where(a.std(axis=0) > 0, a.std(axis=0), 1.0)  # noqa: E731
    return {'x': std(x), 'u': std(u), 'acc': std(acc)}


@contextmanager
def deterministic_torch(threads: int = TRAIN_THREADS) -> Iterator[None]:
    """Run the block with ``threads`` intra-op threads and torch's deterministic algorithms only,
    then put both settings back."""
    old_threads = torch.get_num_threads()
    old_mode = torch.are_deterministic_algorithms_enabled()
    old_warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(old_mode, warn_only=old_warn_only)
        torch.set_num_threads(old_threads)


def train(x: np.ndarray, u: np.ndarray, acc: np.ndarray, x_val: np.ndarray, u_val: np.ndarray,
          acc_val: np.ndarray, settings: TrainSettings,
          on_epoch: Callable[[int, float, float], None] | None = None,
          runs: list[Run] | None = None, val_runs: list[Run] | None = None) -> TrainResult:
    """Fit the SDC networks to accelerations (eq. 18), then, when the settings say so, to their
    own simulation of the records (module doc).

    Seeded and deterministic: the same data and settings give the same bits on the same machine
    kind and torch build (:data:`TRAIN_THREADS` threads, deterministic algorithms only).

    Args:
        x, u, acc: training states (N, 4), inputs (N, 2), acceleration labels (N, 2), SI.
        x_val, u_val, acc_val: validation set; the weights of the best validation epoch are kept.
        settings: the preset.
        on_epoch: called with (epoch, train loss, validation loss) for progress display; in the
            simulation stage the epochs count on and the losses are the simulation errors.
        runs, val_runs: the contiguous training and validation records, needed by the
            simulation stage (``settings.rollout_epochs`` > 0) and otherwise unused.
    """
    for name, a, w in (('x', x, 4), ('u', u, 2), ('acc', acc, 2), ('x_val', x_val, 4),
                       ('u_val', u_val, 2), ('acc_val', acc_val, 2)):
        if a.ndim != 2 or a.shape[1] != w:
            raise ValueError(f'{name} must have shape (N, {w}), got {a.shape}')
    if settings.rollout_epochs > 0:
        for name, given, seconds in (('runs', runs, settings.rollout_seconds),
                                     ('val_runs', val_runs, settings.rollout_val_seconds)):
            if not any(len(r.x) > max(int(round(seconds / r.dt)), 1) for r in given or ()):
                raise ValueError(f'the simulation stage needs {name}: records longer than '
                                 f'{seconds:g} s')
    with deterministic_torch():
        return _train_seeded(x, u, acc, x_val, u_val, acc_val, settings, on_epoch, runs, val_runs)


class _Scales(NamedTuple):
    x: torch.Tensor
    u: torch.Tensor
    acc: torch.Tensor


def _windows(runs: list[Run], seconds: float,
             overlap: int) -> list[tuple[float, torch.Tensor, ...]]:
    """Windows of ``seconds`` (H samples) starting every H / ``overlap`` samples into each run,
    grouped by grid spacing: [(dt, starts (B, 4), inputs (B, H, 2), positions (B, H, 2))]."""
    groups: dict[float, list[list[np.ndarray]]] = {}
    for run in runs:
        h = max(int(round(seconds / run.dt)), 1)
        starts = range(0, len(run.x) - h, max(h // overlap, 1))
        if not starts:
            continue
        got = groups.setdefault(float(run.dt), [[], [], []])
        got[0] += [run.x[i] for i in starts]
        got[1] += [run.u[i:i + h] for i in starts]
        got[2] += [run.x[i + 1:i + h + 1, :2] for i in starts]
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return [(dt, f32(x0), f32(u), f32(p)) for dt, (x0, u, p) in sorted(groups.items())]


#: a simulated state is held within this many data standard deviations, so a diverging run
#: stays finite (its window then counts at most :data:`SIM_ERROR_CAP`, and passes no gradient)
SIM_BOUND = 100.0
#: a window's simulation error counts at most this (scaled units: a run off by ten standard
#: deviations of the data), so one diverged window does not hide how the others do
SIM_ERROR_CAP = 100.0


def _simulate(net: SDCNet, s: _Scales, x0: torch.Tensor, u: torch.Tensor,
              dt: float) -> torch.Tensor:
    """Positions (B, H, 2) of the model's RK4 runs from x0 (B, 4), inputs u (B, H, 2) held."""
    def f(x, uk):
        return torch.cat([x[:, 2:], net.accel(x / s.x, uk / s.u) * s.acc], dim=1)
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
        out.append(x[:, :2])
    return torch.stack(out, dim=1)


def _window_errors(net: SDCNet, s: _Scales, dt: float, x0, u, p) -> torch.Tensor:
    """Each window's L_sim (module doc), positions in units of their scale, capped at
    :data:`SIM_ERROR_CAP`."""
    err = (((_simulate(net, s, x0, u, dt) - p) / s.x[:2]) ** 2).sum(dim=-1).mean(dim=1)
    return err.clamp(max=SIM_ERROR_CAP)


def _sim_error(net: SDCNet, s: _Scales, dt: float, x0, u, p) -> torch.Tensor:
    """L_sim of a batch of windows."""
    return _window_errors(net, s, dt, x0, u, p).mean()


def _val_sim_error(net: SDCNet, s: _Scales, windows) -> float:
    """L_sim over every validation window, each window's error capped at
    :data:`SIM_ERROR_CAP` (a diverged run counts as the cap)."""
    total, count = 0.0, 0
    with torch.no_grad():
        for dt, x0, u, p in windows:
            err = _window_errors(net, s, dt, x0, u, p)
            err = torch.where(torch.isfinite(err), err, torch.full_like(err, SIM_ERROR_CAP))
            total += float(err.sum())
            count += err.numel()
    return total / count


def _with_rest_penalty(loss: torch.Tensor, net: SDCNet, s: _Scales,
                       settings: TrainSettings) -> torch.Tensor:
    """``loss`` + L_rest (module doc) when the penalty is on and some eigenvalue of A(0) is right
    of −rest_margin (eigenvalues' gradients are only taken where they are needed)."""
    if settings.rest_margin <= 0:
        return loss
    rest = _rest_penalty(net, s, settings)
    return loss if rest is None else loss + rest


def _rest_penalty(net: SDCNet, s: _Scales, settings: TrainSettings) -> torch.Tensor | None:
    """L_rest (module doc), or None when every eigenvalue of A(0) is already left of the margin."""
    def real_parts():
        a0 = net(torch.zeros(1, 4))[0][0] * s.acc[:, None] / s.x[None, :]   # [A21 A22] at rest, SI
        top = torch.cat([torch.zeros(2, 2), torch.eye(2)], dim=1)
        return torch.linalg.eigvals(torch.cat([top, a0], dim=0)).real
    with torch.no_grad():
        if float(real_parts().max()) + settings.rest_margin <= 0:
            return None
    return settings.rest_weight * torch.relu(real_parts() + settings.rest_margin).pow(2).sum()


def _step(opt: torch.optim.Optimizer, loss: torch.Tensor, net: SDCNet,
          clip: float | None = None) -> bool:
    """One optimiser step; a batch whose loss or gradient is not finite is skipped."""
    if not torch.isfinite(loss):
        return False
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if clip is not None:
        norm = torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        if not torch.isfinite(norm):
            opt.zero_grad(set_to_none=True)
            return False
    opt.step()
    return True


def _train_seeded(x, u, acc, x_val, u_val, acc_val, settings: TrainSettings, on_epoch, runs,
                  val_runs) -> TrainResult:
    torch.manual_seed(settings.seed)
    gen = torch.Generator().manual_seed(settings.seed)
    s = _scales(x, u, acc, settings.scale)
    st = _Scales(*(torch.as_tensor(s[k], dtype=torch.float32) for k in ('x', 'u', 'acc')))
    t = lambda a, k: torch.as_tensor(a / s[k], dtype=torch.float32)  # noqa: E731
    X, U, Y = t(x, 'x'), t(u, 'u'), t(acc, 'acc')
    Xv, Uv, Yv = t(x_val, 'x'), t(u_val, 'u'), t(acc_val, 'acc')
    net = SDCNet(settings.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    sched = (torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=settings.epochs)
             if settings.cosine else None)
    result = TrainResult(net, s)
    simulating = settings.rollout_epochs > 0
    val_windows = _windows(val_runs, settings.rollout_val_seconds, 1) if simulating else []
    best, best_state, since_best = math.inf, None, 0

    def keep_if_best(epoch: int, score: float) -> bool:
        nonlocal best, best_state, since_best
        if score < best:
            best, since_best, result.best_epoch = score, 0, epoch
            best_state = {k: v.clone() for k, v in net.state_dict().items()}
            return False
        since_best += 1
        return settings.patience is not None and since_best >= settings.patience

    start = time.perf_counter()
    n = X.shape[0]
    for epoch in range(settings.epochs):
        net.train()
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(0, n, settings.batch_size):
            idx = perm[i:i + settings.batch_size]
            loss = ((net.accel(X[idx], U[idx]) - Y[idx]) ** 2).sum(dim=1).mean()   # eq. 18
            if settings.sv_penalty > 0:
                # keep G2 invertible over the whole box, not only where the data lie
                xs = (torch.rand(idx.numel(), 4, generator=gen) * 2 - 1) * settings.sv_box
                smin = torch.linalg.svdvals(
                    net.g_net(xs).reshape(-1, 2, 2).transpose(1, 2))[:, -1]  # G2 alone
                loss = loss + (settings.sv_penalty
                               * torch.relu(settings.sv_floor - smin).pow(2).mean())
            loss = _with_rest_penalty(loss, net, st, settings)
            _step(opt, loss, net)
            total += loss.item() * idx.numel()
        if sched is not None:
            sched.step()
        net.eval()
        with torch.no_grad():
            val = float(((net.accel(Xv, Uv) - Yv) ** 2).sum(dim=1).mean())
        result.train_loss.append(total / n)
        result.val_loss.append(val)
        if on_epoch is not None:
            on_epoch(epoch, total / n, val)
        score = val
        if simulating:
            score = _val_sim_error(net, st, val_windows)
            result.val_sim_error.append(score)
        if keep_if_best(epoch, score):
            break
    if simulating:
        _simulation_stage(net, st, runs, val_windows, settings, gen, result, on_epoch, keep_if_best)
    if best_state is not None:
        net.load_state_dict(best_state)
    result.seconds = time.perf_counter() - start
    return result


def _simulation_stage(net, st: _Scales, runs, val_windows, settings: TrainSettings, gen, result,
                      on_epoch, keep_if_best) -> None:
    """The rollout epochs (module doc), continuing from the label stage's last weights."""
    windows = _windows(runs, settings.rollout_seconds, settings.rollout_overlap)
    opt = torch.optim.Adam(net.parameters(), lr=settings.rollout_lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=settings.rollout_epochs)
    first = len(result.train_loss)
    for epoch in range(settings.rollout_epochs):
        net.train()
        total, count = 0.0, 0
        for dt, x0, u, p in windows:
            perm = torch.randperm(x0.shape[0], generator=gen)
            for i in range(0, len(perm), settings.batch_size):
                idx = perm[i:i + settings.batch_size]
                loss = _with_rest_penalty(_sim_error(net, st, dt, x0[idx], u[idx], p[idx]), net, st,
                                          settings)
                if _step(opt, loss, net, clip=1.0):
                    total += loss.item() * idx.numel()
                    count += idx.numel()
        sched.step()
        net.eval()
        val = _val_sim_error(net, st, val_windows)
        result.rollout_loss.append(total / max(count, 1))
        result.val_sim_error.append(val)
        if on_epoch is not None:
            on_epoch(first + epoch, total / max(count, 1), val)
        if keep_if_best(first + epoch, val):
            break


def fingerprint(*arrays: np.ndarray) -> str:
    """sha256 over the training arrays (shape, dtype and bytes)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_checkpoint(path: Path, result: TrainResult, *, rest_tip: np.ndarray, dt: float,
                    settings: TrainSettings, data: dict, metrics: dict | None = None) -> Path:
    """Write a self-describing checkpoint that ``torch.load(weights_only=True)`` can read."""
    ckpt = {
        'format_version': FORMAT_VERSION,
        'architecture': {'hidden': settings.hidden, 'a_out': 8, 'g_out': 4, 'n_state': 4,
                         'n_input': 2},
        'state_dict': {k: v.detach().clone() for k, v in result.net.state_dict().items()},
        'scales': {k: torch.as_tensor(v, dtype=torch.float64) for k, v in result.scales.items()},
        'rest_tip': torch.as_tensor(np.asarray(rest_tip, dtype=float)),
        'dt': float(dt),
        'settings': asdict(settings),
        'data': data,
        'metrics': metrics or {},
        'history': {'train_loss': list(map(float, result.train_loss)),
                    'val_loss': list(map(float, result.val_loss)), 'best_epoch': result.best_epoch,
                    'rollout_loss': list(map(float, result.rollout_loss)),
                    'val_sim_error': list(map(float, result.val_sim_error))},
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, path)
    return path
