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
and torch build (:data:`TRAIN_THREADS` intra-op threads, ATen's deterministic algorithms only).
The settings and their presets are :mod:`soft_gripper_sdre.learning.train_settings`; the model's
simulation of the records and L_sim, :mod:`soft_gripper_sdre.learning.rollout`; the label stage's
step without autograd (the same bits at about half the cost), :mod:`soft_gripper_sdre.learning.
label_step`; the simulation stage's loss and gradient compiled (forward and adjoint through the
RK4 steps, autograd's to rounding in float64 at about a quarter of its cost),
:mod:`soft_gripper_sdre.learning.compiled_rollout`; the networks, the checkpoint's layout and
reading it back,
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

from soft_gripper_sdre.learning import compiled_rollout, label_step
from soft_gripper_sdre.learning.model import FORMAT_VERSION, SDCNet
from soft_gripper_sdre.learning.rollout import (
    Run,
    Scales,
    val_sim_error,
    windows,
)
from soft_gripper_sdre.learning.train_settings import TrainSettings
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, InputBounds

#: intra-op threads while training: the order of torch's reductions, and so every weight's bits,
#: depends on it
TRAIN_THREADS = 1


@dataclass
class TrainResult:
    net: SDCNet
    scales: dict[str, np.ndarray]
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0
    #: the simulation stage (empty when off): its training loss per epoch, and the validation
    #: simulation error per epoch of both stages (a label epoch not scored,
    #: ``TrainSettings.score_every``, repeats the last score), with the epochs scored
    rollout_loss: list[float] = field(default_factory=list)
    val_sim_error: list[float] = field(default_factory=list)
    scored_epochs: list[int] = field(default_factory=list)
    #: wall time of each stage [s]: ``label_stage``, ``simulation_stage`` (0 when off)
    timings: dict[str, float] = field(default_factory=dict)


def _scales(x: np.ndarray, u: np.ndarray, acc: np.ndarray, scale: bool) -> dict[str, np.ndarray]:
    """Each column's standard deviation (1 where a column does not vary), or ones unscaled."""
    if not scale:
        return {'x': np.ones(x.shape[1]), 'u': np.ones(u.shape[1]), 'acc': np.ones(acc.shape[1])}
    std = lambda a: np.where(a.std(axis=0) > 0, a.std(axis=0), 1.0)  # noqa: E731
    return {'x': std(x), 'u': std(u), 'acc': std(acc)}


@contextmanager
def deterministic_torch(threads: int = TRAIN_THREADS) -> Iterator[None]:
    """Run the block with ``threads`` intra-op threads and ATen's deterministic algorithms only,
    then put both settings back."""
    old_threads = torch.get_num_threads()
    old_mode = torch.are_deterministic_algorithms_enabled()
    old_warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(threads)
    _set_deterministic_algorithms(True, warn_only=False)
    try:
        yield
    finally:
        _set_deterministic_algorithms(old_mode, warn_only=old_warn_only)
        torch.set_num_threads(old_threads)


def _set_deterministic_algorithms(mode: bool, warn_only: bool) -> None:
    """ATen's deterministic-algorithms flag, which is all training runs under.
    ``torch.use_deterministic_algorithms`` also sets the flag of torch's graph compiler, and
    importing that compiler's configuration costs seconds (1.5–3 s on two cores); training never
    compiles a graph, so where torch offers ATen's flag alone it is set alone. (``torch.optim``'s
    optimizers import the compiler as they are made; both stages step
    :class:`~soft_gripper_sdre.learning.label_step.Adam`, the same arithmetic.)"""
    set_aten_flag = getattr(torch._C, '_set_deterministic_algorithms', None)
    if set_aten_flag is None:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        set_aten_flag(mode, warn_only=warn_only)


def train(x: np.ndarray, u: np.ndarray, acc: np.ndarray, x_val: np.ndarray, u_val: np.ndarray,
          acc_val: np.ndarray, settings: TrainSettings,
          on_epoch: Callable[[int, float, float], None] | None = None,
          runs: list[Run] | None = None, val_runs: list[Run] | None = None,
          shape: FingerShape = HAND_SHAPE) -> TrainResult:
    """Fit the SDC networks to accelerations (eq. 18), then, when the settings say so, to their
    own simulation of the records (module doc).

    Seeded and deterministic: the same data and settings give the same bits on the same machine
    kind and torch build (:data:`TRAIN_THREADS` threads, deterministic algorithms only).

    Args:
        x, u, acc: training states (N, 2d), inputs (N, m), acceleration labels (N, d), SI, of a
            finger of shape (d, m) (the hand: (N, 4), (N, 2), (N, 2)).
        x_val, u_val, acc_val: validation set; the weights of the best validation epoch are kept.
        settings: the preset.
        on_epoch: called with (epoch, train loss, validation loss) for progress display; in the
            simulation stage the epochs count on and the losses are the simulation errors.
        runs, val_runs: the contiguous training and validation records, needed by the
            simulation stage (``settings.rollout_epochs`` > 0) and otherwise unused.
        shape: the finger's shape (d, m), which sizes the networks (default: the hand's).

    Raises:
        ValueError: an array whose width is not the shape's (naming it), or the simulation stage
            without records long enough.
    """
    ns, m, d = shape.n_state, shape.m, shape.d
    for name, a, w in (('x', x, ns), ('u', u, m), ('acc', acc, d), ('x_val', x_val, ns),
                       ('u_val', u_val, m), ('acc_val', acc_val, d)):
        if a.ndim != 2 or a.shape[1] != w:
            raise ValueError(f'{name} must have shape (N, {w}) for the shape {shape}, '
                             f'got {a.shape}')
    if settings.rollout_epochs > 0:
        for name, given, seconds in (('runs', runs, settings.rollout_seconds),
                                     ('val_runs', val_runs, settings.rollout_val_seconds)):
            if not any(len(r.x) > max(int(round(seconds / r.dt)), 1) for r in given or ()):
                raise ValueError(f'the simulation stage needs {name}: records longer than '
                                 f'{seconds:g} s')
    with deterministic_torch():
        return _train_seeded(x, u, acc, x_val, u_val, acc_val, settings, on_epoch, runs, val_runs,
                             shape)


class _Labelled(NamedTuple):
    """States, inputs and acceleration labels in the networks' scaled units."""

    x: torch.Tensor
    u: torch.Tensor
    acc: torch.Tensor


def _label_loss(net: SDCNet, data: _Labelled) -> torch.Tensor:
    """Eq. 18: the mean squared acceleration residual."""
    return ((net.accel(data.x, data.u) - data.acc) ** 2).sum(dim=1).mean()


def _rest_penalty(net: SDCNet, s: Scales, settings: TrainSettings) -> torch.Tensor | None:
    """L_rest (module doc), or None when every eigenvalue of A(0) is already left of the margin.

    A(0) comes from a_net alone (:func:`~soft_gripper_sdre.learning.label_step.mlp_forward`: the
    same bits as ``net(0)``'s, without g_net and the modules' dispatch: the check runs every
    batch)."""
    d = net.shape.d
    params = tuple(net.a_net.parameters())

    def real_parts():
        out, _, _ = label_step.mlp_forward(params, torch.zeros(1, 2 * d))
        a0 = out.reshape(2 * d, d).t() * s.acc[:, None] / s.x[None, :]          # [A21 A22], SI
        top = torch.cat([torch.zeros(d, d), torch.eye(d)], dim=1)
        return torch.linalg.eigvals(torch.cat([top, a0], dim=0)).real
    with torch.no_grad():
        if float(real_parts().max()) + settings.rest_margin <= 0:
            return None
    return settings.rest_weight * torch.relu(real_parts() + settings.rest_margin).pow(2).sum()


def _gradients(loss: torch.Tensor, net: SDCNet) -> list[torch.Tensor]:
    """``loss``'s gradient with respect to ``net.parameters()``, by autograd, in that order."""
    net.zero_grad(set_to_none=True)
    loss.backward()
    return [p.grad for p in net.parameters()]


def _clipped(grads: list[torch.Tensor], clip: float) -> list[torch.Tensor] | None:
    """``grads`` scaled so their total 2-norm is at most ``clip``, as
    ``torch.nn.utils.clip_grad_norm_`` scales a model's gradients (the same norm, coefficient and
    products); None when the norm is not finite."""
    norm = torch.nn.utils.get_total_norm(grads)
    if not torch.isfinite(norm):
        return None
    coef = torch.clamp(clip / (norm + 1e-6), max=1.0)
    return [g * coef for g in grads]


def _train_seeded(x, u, acc, x_val, u_val, acc_val, settings: TrainSettings, on_epoch, runs,
                  val_runs, shape: FingerShape) -> TrainResult:
    s = _scales(x, u, acc, settings.scale)
    t = lambda a, k: torch.as_tensor(a / s[k], dtype=torch.float32)  # noqa: E731
    train_set = _Labelled(t(x, 'x'), t(u, 'u'), t(acc, 'acc'))
    val_set = _Labelled(t(x_val, 'x'), t(u_val, 'u'), t(acc_val, 'acc'))
    simulating = settings.rollout_epochs > 0
    run = _Training(settings, s, on_epoch,
                    windows(val_runs, settings.rollout_val_seconds, 1) if simulating else [], shape)
    start = time.perf_counter()
    run.label_stage(train_set, val_set)
    labelled = time.perf_counter()
    if simulating:
        run.simulation_stage(runs)
    run.keep_best()
    end = time.perf_counter()
    run.result.seconds = end - start
    run.result.timings = {'label_stage': labelled - start, 'simulation_stage': end - labelled}
    return run.result


class _Training:
    """One seeded run of both stages on the same networks: the generator of the shuffles (and of
    the singular-value penalty's states), and the best-scoring epoch so far, whose weights are
    the result's; the patience rule counts across both stages."""

    def __init__(self, settings: TrainSettings, scales: dict[str, np.ndarray],
                 on_epoch: Callable[[int, float, float], None] | None, val_windows: list,
                 shape: FingerShape) -> None:
        self.settings, self.on_epoch, self.val_windows = settings, on_epoch, val_windows
        torch.manual_seed(settings.seed)                      # the networks' initial weights
        self.gen = torch.Generator().manual_seed(settings.seed)
        self.st = Scales(*(torch.as_tensor(scales[k], dtype=torch.float32)
                           for k in ('x', 'u', 'acc')))
        self.net = SDCNet(settings.hidden, shape)
        self.result = TrainResult(self.net, scales)
        self.best, self.best_state, self.since_best = math.inf, None, 0

    def keep_if_best(self, epoch: int, score: float) -> bool:
        """Keep the weights when ``score`` is the lowest yet; True when patience has run out."""
        if score < self.best:
            self.best, self.since_best, self.result.best_epoch = score, 0, epoch
            self.best_state = {k: v.clone() for k, v in self.net.state_dict().items()}
            return False
        self.since_best += 1
        return self.settings.patience is not None and self.since_best >= self.settings.patience

    def keep_best(self) -> None:
        """Load the kept weights into the networks."""
        if self.best_state is not None:
            self.net.load_state_dict(self.best_state)

    def label_stage(self, train_set: _Labelled, val_set: _Labelled) -> None:
        """The label epochs (eq. 18), each scored by its validation loss, or by its validation
        simulation error when the simulation stage follows."""
        settings, net, result = self.settings, self.net, self.result
        opt = label_step.Adam(list(net.parameters()), settings.lr,
                              weight_decay=settings.weight_decay)
        step = label_step.LabelStep(net)
        for epoch in range(settings.epochs):
            net.train()
            train_loss = self._label_epoch(opt, step, train_set)
            if settings.cosine:
                opt.lr = label_step.cosine_lr(opt.lr, epoch + 1, settings.epochs)
            net.eval()
            val = float(step.loss(*val_set))
            result.train_loss.append(train_loss)
            result.val_loss.append(val)
            if self.on_epoch is not None:
                self.on_epoch(epoch, train_loss, val)
            score = val
            if settings.rollout_epochs > 0:
                if epoch % settings.score_every and epoch != settings.epochs - 1:
                    result.val_sim_error.append(result.val_sim_error[-1])
                    continue
                score = val_sim_error(net, self.st, self.val_windows)
                result.val_sim_error.append(score)
                result.scored_epochs.append(epoch)
            if self.keep_if_best(epoch, score):
                break

    def _label_epoch(self, opt: label_step.Adam, step: label_step.LabelStep,
                     data: _Labelled) -> float:
        """One pass over the shuffled training set in batches; returns the mean loss.

        The set is shuffled once per epoch and the batches are its consecutive slices. A batch
        with only the label loss takes its gradient in closed form
        (:mod:`~soft_gripper_sdre.learning.label_step`); one with a penalty on, through autograd.
        Either way Adam's update is the same arithmetic, and a batch whose loss is not finite is
        skipped."""
        settings, net = self.settings, self.net
        n = data.x.shape[0]
        perm = torch.randperm(n, generator=self.gen)
        size = settings.batch_size
        total = 0.0
        for xs, us, acc in zip(data.x[perm].split(size), data.u[perm].split(size),
                               data.acc[perm].split(size)):
            batch = _Labelled(xs, us, acc)
            count = batch.x.shape[0]
            rest = _rest_penalty(net, self.st, settings) if settings.rest_margin > 0 else None
            if settings.sv_penalty == 0 and rest is None:
                loss, grads = step(*batch)
            else:
                loss = _label_loss(net, batch)
                if settings.sv_penalty > 0:
                    loss = loss + self._sv_penalty(count)
                if rest is not None:
                    loss = loss + rest
                grads = _gradients(loss, net)
            value = loss.item()
            if math.isfinite(value):
                opt.step(grads)
            total += value * count
        return total / n

    def _sv_penalty(self, count: int) -> torch.Tensor:
        """sv_penalty · mean(relu(σ_floor − σ_min(G2(x)))²) at ``count`` states drawn uniformly
        from the box of ±sv_box: G2 kept invertible over the whole box, not only where the data
        lie."""
        settings, shape = self.settings, self.net.shape
        xs = (torch.rand(count, shape.n_state, generator=self.gen) * 2 - 1) * settings.sv_box
        smin = torch.linalg.svdvals(
            self.net.g_net(xs).reshape(-1, shape.m, shape.d).transpose(1, 2))[:, -1]  # G2 alone
        return settings.sv_penalty * torch.relu(settings.sv_floor - smin).pow(2).mean()

    def simulation_stage(self, runs: list[Run]) -> None:
        """The rollout epochs (module doc), continuing from the label stage's last weights."""
        settings, net, result = self.settings, self.net, self.result
        batches = [(dt, *(a.double().numpy() for a in arrays))
                   for dt, *arrays in windows(runs, settings.rollout_seconds,
                                              settings.rollout_overlap)]
        opt = label_step.Adam(list(net.parameters()), settings.rollout_lr)
        first = len(result.train_loss)
        for epoch in range(settings.rollout_epochs):
            net.train()
            train_loss = self._rollout_epoch(opt, batches)
            opt.lr = label_step.cosine_lr(opt.lr, epoch + 1, settings.rollout_epochs)
            net.eval()
            val = val_sim_error(net, self.st, self.val_windows)
            result.rollout_loss.append(train_loss)
            result.val_sim_error.append(val)
            result.scored_epochs.append(first + epoch)
            if self.on_epoch is not None:
                self.on_epoch(first + epoch, train_loss, val)
            if self.keep_if_best(first + epoch, val):
                break

    def _rollout_epoch(self, opt: label_step.Adam, batches: list) -> float:
        """One pass over every window, shuffled within each grid spacing, in batches of
        ``rollout_batch_size`` windows; returns the mean L_sim of the batches that stepped.

        L_sim and its gradient come from the compiled forward and adjoint runs
        (:mod:`~soft_gripper_sdre.learning.compiled_rollout`); L_rest, when it is on and due,
        through autograd, added to both."""
        settings, net = self.settings, self.net
        size = settings.rollout_batch_size or settings.batch_size
        total, count = 0.0, 0
        for dt, x0, u, p in batches:
            perm = torch.randperm(x0.shape[0], generator=self.gen).numpy()
            for i in range(0, len(perm), size):
                idx = perm[i:i + size]
                loss, grads = compiled_rollout.loss_and_grads(net, self.st, dt, x0[idx], u[idx],
                                                              p[idx])
                rest = (_rest_penalty(net, self.st, settings) if settings.rest_margin > 0
                        else None)
                if rest is not None:
                    loss += rest.item()
                    grads = [g if r is None else g + r
                             for g, r in zip(grads, _gradients(rest, net))]
                grads = _clipped(grads, 1.0) if math.isfinite(loss) else None
                if grads is not None:                    # a non-finite batch is skipped
                    opt.step(grads)
                    total += loss * len(idx)
                    count += len(idx)
        return total / max(count, 1)


def fingerprint(*arrays: np.ndarray) -> str:
    """sha256 over the training arrays (shape, dtype and bytes)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_checkpoint(path: Path, result: TrainResult, *, rest_tip: np.ndarray, dt: float,
                    settings: TrainSettings, data: dict, metrics: dict | None = None,
                    input_bounds: InputBounds | None = None) -> Path:
    """Write a self-describing checkpoint that ``torch.load(weights_only=True)`` can read: the
    networks' shape (``result.net.shape``) and ``input_bounds``, the bounds the data were
    recorded under (None: not known), beside the weights, scales and provenance.

    Raises:
        ValueError: ``input_bounds`` of another number of inputs than the networks'.
    """
    shape = result.net.shape
    if input_bounds is not None and input_bounds.m != shape.m:
        raise ValueError(f'input_bounds name {input_bounds.m} input(s), the networks have '
                         f'{shape.m}')
    a_out, g_out = shape.network_outputs
    ckpt = {
        'format_version': FORMAT_VERSION,
        'architecture': {'hidden': settings.hidden, 'a_out': a_out, 'g_out': g_out,
                         'n_state': shape.n_state, 'n_input': shape.m},
        'shape': shape.to_record(),
        'input_bounds': None if input_bounds is None else input_bounds.to_record(),
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
