"""The learned task-space dynamics in state-dependent-coefficient form (the only torch module).

State x = [X − X₀, Y − Y₀, Ẋ, Ẏ] (SI, translated so that the settled rest pose is the origin and
f(0) = 0), input u = [u_ax0, u_ax1] [N·m]:

    ẋ = A(x) x + G(x) u,   A = [[0, I], [A21(x), A22(x)]],   G = [[0], [G2(x)]],
    vec([A21 A22]) = NN_θ1(x) ∈ R⁸,   vec(G2) = NN_θ2(x) ∈ R⁴      (vec stacks columns)

each network three fully connected layers (4 → 32 → 32 → out) with ReLU between. The loss is
eq. 18, mean ‖ẋ − A(x)x − G(x)u‖²; its first two rows are Ẋ − Ẋ ≡ 0, so only the acceleration
rows carry information and the loss is the mean squared acceleration residual.

With scaling (the default preset) the networks see x / s_x and predict scaled accelerations
ẍ / s_a from scaled inputs u / s_u; the physical matrices follow exactly,
A_ij = s_a,i Â_ij / s_x,j and G2_ij = s_a,i Ĝ_ij / s_u,j, so the model keeps the paper's form.

:class:`SDCModel` evaluates a checkpoint with plain numpy (no torch at control time): the two
networks as one fused network of three matmuls.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
import hashlib
import math
from pathlib import Path
import pickle
import re
import time
from typing import Callable, Iterator

import numpy as np
import torch
from torch import nn

from soft_gripper_sdre.learning.dataset import ZIP_MAGIC

FORMAT_VERSION = 1
HIDDEN = 32
#: intra-op threads while training: the order of torch's reductions, and so every weight's bits,
#: depends on it
TRAIN_THREADS = 1
DEFAULT_MODEL = Path(__file__).resolve().parent.parent / 'models' / 'default.pt'
#: the same preset trained on the paper's signals alone (u1..u3, both torques equal): kept to show
#: what identifying excitation buys (without it G2's column directions come out wrong)
PAPER_DATA_MODEL = DEFAULT_MODEL.with_name('paper_data.pt')


class ModelFileError(ValueError):
    """A checkpoint cannot be used; the message names the file and the reason."""


def set_torch_threads(n: int) -> None:
    """Run torch's CPU work on ``n`` threads (the tools use one, as the nodes run numpy: on a
    shared machine more threads only contend for the same cores)."""
    if int(n) < 1:
        raise ValueError(f'n must be >= 1, got {n!r}')
    torch.set_num_threads(int(n))


# ----------------------------------------------------------------------------------------------
# networks
# ----------------------------------------------------------------------------------------------

def mlp(n_in: int, n_out: int, hidden: int = HIDDEN) -> nn.Sequential:
    """Three fully connected layers with ReLU between (none after the last)."""
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, n_out))


class SDCNet(nn.Module):
    """NN_θ1 (A21, A22) and NN_θ2 (G2), in scaled units."""

    def __init__(self, hidden: int = HIDDEN) -> None:
        super().__init__()
        self.a_net = mlp(4, 8, hidden)
        self.g_net = mlp(4, 4, hidden)

    def forward(self, xs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Scaled state (B, 4) → [A21 A22] (B, 2, 4) and G2 (B, 2, 2) (column-stacked vec⁻¹)."""
        a = self.a_net(xs).reshape(-1, 4, 2).transpose(1, 2)
        g = self.g_net(xs).reshape(-1, 2, 2).transpose(1, 2)
        return a, g

    def accel(self, xs: torch.Tensor, us: torch.Tensor) -> torch.Tensor:
        """Scaled ẍ = [A21 A22] x + G2 u."""
        a, g = self(xs)
        return (a @ xs.unsqueeze(-1) + g @ us.unsqueeze(-1)).squeeze(-1)


# ----------------------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------------------

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


# ----------------------------------------------------------------------------------------------
# checkpoint
# ----------------------------------------------------------------------------------------------

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


def read_checkpoint(path: Path) -> dict:
    """Load and check a checkpoint; no code in the file is ever executed.

    Raises:
        ModelFileError: missing, unreadable or truncated, carrying pickled objects, another format
            version, or other network sizes.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f'model file {path} does not exist')
    try:
        with path.open('rb') as f:
            head = f.read(len(ZIP_MAGIC))
    except OSError as exc:
        raise ModelFileError(f'model file {path} cannot be read: {exc}') from None
    if head != ZIP_MAGIC:
        raise ModelFileError(f'model file {path} is not a checkpoint: a torch.save file is a zip archive '
                             f'and this one starts with {head!r} (corrupt, or another kind of file)')
    try:
        ckpt = torch.load(path, map_location='cpu', weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r'Unsupported global: GLOBAL ([\w.]+)', str(exc))
        what = f' (it needs {found.group(1)})' if found else ''
        raise ModelFileError(f'model file {path} holds objects other than tensors and plain data{what}; '
                             'refused without running them') from None
    except Exception as exc:  # torch reports a non-zip file through whatever its legacy reader hits
        raise ModelFileError(f'model file {path} is unreadable or truncated: {exc}'[:400]) from None
    if not isinstance(ckpt, dict) or 'format_version' not in ckpt:
        raise ModelFileError(f'model file {path} is not a soft_gripper_sdre checkpoint')
    if ckpt['format_version'] != FORMAT_VERSION:
        raise ModelFileError(f'model file {path} has format version {ckpt["format_version"]}, '
                             f'this package reads version {FORMAT_VERSION}')
    try:
        hidden = int(ckpt['architecture']['hidden'])
        net = SDCNet(hidden)
        net.load_state_dict(ckpt['state_dict'])
        for key, n in (('x', 4), ('u', 2), ('acc', 2)):
            if tuple(ckpt['scales'][key].shape) != (n,):
                raise ValueError(f'scale {key} has shape {tuple(ckpt["scales"][key].shape)}')
        if tuple(ckpt['rest_tip'].shape) != (3,):
            raise ValueError(f'rest_tip has shape {tuple(ckpt["rest_tip"].shape)}')
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        raise ModelFileError(f'model file {path} does not match the network layout: {exc}'[:400]) from None
    ckpt['net'] = net
    return ckpt


def _fused_layers(sd: dict[str, np.ndarray], s: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """NN_θ1 and NN_θ2 as one network in physical units, for evaluation with three matmuls.

    The two networks take the same input, so they run side by side: layer 1 stacks their weights
    (4 → 2·32), layers 2 and 3 are block-diagonal. The scalings fold into the weights: the input
    x / s_x into layer 1's rows, and the output factors (A_ij = s_a,i Â_ij / s_x,j,
    G2_ij = s_a,i Ĝ_ij / s_u,j) into layer 3's columns, which are also reordered from the networks'
    column-stacked vec to row-major [A21 A22] (8) then G2 (4).

    Returns:
        [(w1, b1), (w2, b2), (w3, b3)] with h ↦ relu(h w1 + b1) ↦ relu(· w2 + b2) ↦ · w3 + b3.
    """
    layer = lambda net, i: (sd[f'{net}.{i}.weight'].T, sd[f'{net}.{i}.bias'])  # noqa: E731
    (a1, c1), (a2, c2), (a3, c3) = (layer('a_net', i) for i in (0, 2, 4))
    (g1, d1), (g2, d2), (g3, d3) = (layer('g_net', i) for i in (0, 2, 4))
    ha, hg = a1.shape[1], g1.shape[1]
    w1 = np.hstack([a1, g1]) / s['x'][:, None]
    b1 = np.concatenate([c1, d1])
    w2 = np.zeros((ha + hg, ha + hg))
    w2[:ha, :ha], w2[ha:, ha:] = a2, g2
    b2 = np.concatenate([c2, d2])
    w3 = np.zeros((ha + hg, 12))
    b3 = np.zeros(12)
    # output k of NN_θ1 is [A21 A22][k % 2, k // 2] (column-stacked vec), of NN_θ2 is G2[k % 2, k // 2]
    for k in range(8):
        r, c = k % 2, k // 2
        f = s['acc'][r] / s['x'][c]
        w3[:ha, 4 * r + c] = f * a3[:, k]
        b3[4 * r + c] = f * c3[k]
    for k in range(4):
        r, c = k % 2, k // 2
        f = s['acc'][r] / s['u'][c]
        w3[ha:, 8 + 2 * r + c] = f * g3[:, k]
        b3[8 + 2 * r + c] = f * d3[k]
    return [(np.ascontiguousarray(w1), b1), (w2, b2), (w3, b3)]


def _homogeneous(layers: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, ...]:
    """The fused network with layers 2 and 3's biases carried by a constant hidden unit.

    Layer 1 gets one more output unit, 0·x + 1 = 1, which the ReLU keeps at 1; layer 2 gets the
    same unit and both later layers take their bias from that unit's weight row:

        h₁ = relu(x w₁' + b₁'),  h₂ = relu(h₁ W₂),  out = h₂ W₃,
        W₂ = [[w₂, 0], [b₂, 1]],  W₃ = [[w₃], [b₃]]

    (h₁ W₂ = h w₂ + 1·b₂ for h₁ = [h, 1]), so the network costs three matmuls, one bias add and
    two in-place ReLUs. Returns (w₁', b₁', W₂, W₃).
    """
    (w1, b1), (w2, b2), (w3, b3) = layers
    h = w1.shape[1]
    w1e = np.hstack([w1, np.zeros((w1.shape[0], 1))])
    b1e = np.append(b1, 1.0)
    W2 = np.zeros((h + 1, h + 1))
    W2[:h, :h], W2[h, :h], W2[h, h] = w2, b2, 1.0
    W3 = np.vstack([w3, b3])
    return np.ascontiguousarray(w1e), b1e, W2, W3


class SDCModel:
    """A trained SDC model evaluated with numpy: A(x), G(x) for one state or a batch (SI).

    Args:
        path: checkpoint file; None loads the default model shipped with the package.
    """

    def __init__(self, path: Path | str | None = None) -> None:
        self.path = Path(path) if path is not None else DEFAULT_MODEL
        ckpt = read_checkpoint(self.path)
        sd = {k: v.detach().double().numpy() for k, v in ckpt['state_dict'].items()}
        s = {k: v.numpy() for k, v in ckpt['scales'].items()}
        self._layers = _fused_layers(sd, s)
        self._net = _homogeneous(self._layers)
        self._b1 = {}        # layer 1's bias repeated for small batches of n states (no broadcasting)
        self.rest_tip = ckpt['rest_tip'].numpy().astype(float)
        self.dt = float(ckpt['dt'])
        self.settings = ckpt['settings']
        self.data = ckpt['data']
        self.metrics = ckpt['metrics']
        self.history = ckpt['history']

    def sdc_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The learned blocks for states x (4,) or (n, 4): [A21 A22] (n, 2, 4) and G2 (n, 2, 2).

        Both networks run as one: three matmuls with ReLU between (see :func:`_fused_layers`; the
        biases of layers 2 and 3 ride on a constant hidden unit, :func:`_homogeneous`).
        """
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            x = x[None]
        n, width = x.shape if x.ndim == 2 else (0, 0)
        if width != 4:
            raise ValueError(f'x must have shape (4,) or (n, 4), got {x.shape}')
        w1, b1, W2, W3 = self._net
        if n <= 16:
            b1 = self._b1.get(n)
            if b1 is None:
                b1 = self._b1[n] = np.tile(self._net[1], (n, 1))
        h = x @ w1
        h += b1                                  # [x w₁ + b₁, 1]
        np.maximum(h, 0.0, out=h)
        h = h @ W2                               # [h w₂ + b₂, 1]
        np.maximum(h, 0.0, out=h)
        out = h @ W3                             # h w₃ + b₃
        return out[:, :8].reshape(n, 2, 4), out[:, 8:].reshape(n, 2, 2)

    @property
    def fused_network(self) -> tuple[np.ndarray, ...]:
        """Copies of the fused network's arrays (w1, b1, w2, b2, w3, b3), float64 and C-contiguous.

        h ↦ relu(x w1 + b1) ↦ relu(· w2 + b2) ↦ · w3 + b3 maps states x (n, 4) to (n, 12): row-major
        [A21 A22] (8) then G2 (4), in SI (:func:`_fused_layers`). For evaluators outside this
        package's numpy path, such as the compiled control kernels, which take the arrays as inputs.
        """
        return tuple(np.array(a, dtype=np.float64, order='C') for layer in self._layers for a in layer)

    def AG(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A(x) (n, 4, 4) and G(x) (n, 4, 2) for states x (4,) or (n, 4)."""
        a, g = self.sdc_blocks(x)
        n = a.shape[0]
        A = np.zeros((n, 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0          # Ẋ, Ẏ rows: [0 I]
        A[:, 2:, :] = a
        G = np.zeros((n, 4, 2))
        G[:, 2:, :] = g
        return A, G

    def A(self, x: np.ndarray) -> np.ndarray:
        return self.AG(x)[0]

    def G(self, x: np.ndarray) -> np.ndarray:
        return self.AG(x)[1]

    def xdot(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """ẋ = A(x) x + G(x) u for (n, 4) states and (n, 2) inputs."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        A, G = self.AG(x)
        return np.einsum('nij,nj->ni', A, x) + np.einsum('nij,nj->ni', G, u)
