"""Training the SDC networks (eq. 18) and writing their checkpoint.

Seeded and deterministic: the same data and settings give the same bits on the same machine kind
and torch build (:data:`TRAIN_THREADS` intra-op threads, torch's deterministic algorithms only).
The networks, the checkpoint's layout and reading it back are :mod:`soft_gripper_sdre.learning.model`.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
import hashlib
import math
from pathlib import Path
import time
from typing import Callable, Iterator

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

    def __post_init__(self) -> None:
        if self.patience is not None and not (isinstance(self.patience, int) and self.patience >= 1):
            raise ValueError(f'patience must be an int >= 1 or None (run every epoch), got {self.patience!r}')
        if not (np.isfinite(self.sv_penalty) and self.sv_penalty >= 0.0):
            raise ValueError(f'sv_penalty must be finite and >= 0 (0 = off), got {self.sv_penalty!r}')
        for name in ('sv_floor', 'sv_box'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v!r}')


PRESETS = {
    'default': TrainSettings(),
    'paper': TrainSettings(preset='paper', epochs=70, lr=1e-5, batch_size=64, cosine=False,
                           scale=False),
}


@dataclass
class TrainResult:
    net: SDCNet
    scales: dict[str, np.ndarray]
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0


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
          on_epoch: Callable[[int, float, float], None] | None = None) -> TrainResult:
    """Fit the SDC networks to accelerations (eq. 18).

    Seeded and deterministic: the same data and settings give the same bits on the same machine
    kind and torch build (:data:`TRAIN_THREADS` threads, deterministic algorithms only).

    Args:
        x, u, acc: training states (N, 4), inputs (N, 2), acceleration labels (N, 2), SI.
        x_val, u_val, acc_val: validation set; the weights of the best validation epoch are kept.
        settings: the preset.
        on_epoch: called with (epoch, train loss, validation loss) for progress display.
    """
    for name, a, w in (('x', x, 4), ('u', u, 2), ('acc', acc, 2), ('x_val', x_val, 4),
                       ('u_val', u_val, 2), ('acc_val', acc_val, 2)):
        if a.ndim != 2 or a.shape[1] != w:
            raise ValueError(f'{name} must have shape (N, {w}), got {a.shape}')
    with deterministic_torch():
        return _train_seeded(x, u, acc, x_val, u_val, acc_val, settings, on_epoch)


def _train_seeded(x, u, acc, x_val, u_val, acc_val, settings: TrainSettings, on_epoch) -> TrainResult:
    torch.manual_seed(settings.seed)
    gen = torch.Generator().manual_seed(settings.seed)
    s = _scales(x, u, acc, settings.scale)
    t = lambda a, k: torch.as_tensor(a / s[k], dtype=torch.float32)  # noqa: E731
    X, U, Y = t(x, 'x'), t(u, 'u'), t(acc, 'acc')
    Xv, Uv, Yv = t(x_val, 'x'), t(u_val, 'u'), t(acc_val, 'acc')
    net = SDCNet(settings.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    sched = (torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=settings.epochs)
             if settings.cosine else None)
    result = TrainResult(net, s)
    best, best_state, since_best = math.inf, None, 0
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
                smin = torch.linalg.svdvals(net.g_net(xs).reshape(-1, 2, 2).transpose(1, 2))[:, -1]   # G2 alone
                loss = loss + settings.sv_penalty * torch.relu(settings.sv_floor - smin).pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
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
        if val < best:
            best, since_best, result.best_epoch = val, 0, epoch
            best_state = {k: v.clone() for k, v in net.state_dict().items()}
        else:
            since_best += 1
            if settings.patience is not None and since_best >= settings.patience:
                break
    if best_state is not None:
        net.load_state_dict(best_state)
    result.seconds = time.perf_counter() - start
    return result


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
        'architecture': {'hidden': settings.hidden, 'a_out': 8, 'g_out': 4, 'n_state': 4, 'n_input': 2},
        'state_dict': {k: v.detach().clone() for k, v in result.net.state_dict().items()},
        'scales': {k: torch.as_tensor(v, dtype=torch.float64) for k, v in result.scales.items()},
        'rest_tip': torch.as_tensor(np.asarray(rest_tip, dtype=float)),
        'dt': float(dt),
        'settings': asdict(settings),
        'data': data,
        'metrics': metrics or {},
        'history': {'train_loss': list(map(float, result.train_loss)),
                    'val_loss': list(map(float, result.val_loss)), 'best_epoch': result.best_epoch},
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, path)
    return path
