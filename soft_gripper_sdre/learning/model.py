"""The learned task-space dynamics in state-dependent-coefficient form: the two networks, their
checkpoint, and the numpy model the controller evaluates (training:
:mod:`soft_gripper_sdre.learning.training`).

A finger of shape (d, m) (:class:`~soft_gripper_sdre.sim.shape.FingerShape`: a tip of d = 2 or 3
coordinates, m = 1 to 4 inputs) has the state x = [p − p₀, ṗ] ∈ R^2d (SI, translated so that the
settled rest pose p₀ is the origin and f(0) = 0) and the input u ∈ R^m (each in its actuator's SI
unit: N·m, N, Pa):

    ẋ = A(x) x + G(x) u,   A = [[0, I], [A21(x), A22(x)]],   G = [[0], [G2(x)]],
    vec([A21 A22]) = NN_θ1(x) ∈ R^2d²,   vec(G2) = NN_θ2(x) ∈ R^dm      (vec stacks columns)

each network three fully connected layers (2d → 32 → 32 → out) with ReLU between. The hand of
this package is d = 2, m = 2: x = [X − X₀, Y − Y₀, Ẋ, Ẏ], u = [u_ax0, u_ax1] [N·m], 8 + 4
outputs. The loss is eq. 18, mean ‖ẋ − A(x)x − G(x)u‖²; its first d rows are ṗ − ṗ ≡ 0, so only
the acceleration rows carry information and the loss is the mean squared acceleration residual.

With scaling (the default preset) the networks see x / s_x and predict scaled accelerations
p̈ / s_a from scaled inputs u / s_u; the physical matrices follow exactly,
A_ij = s_a,i Â_ij / s_x,j and G2_ij = s_a,i Ĝ_ij / s_u,j, so the model keeps the paper's form.

A checkpoint carries its shape (``'shape': {'d', 'm'}``) and the bounds of the inputs its data
were recorded under (``'input_bounds': {'lower', 'upper'}``, or None when not known); one without
the keys is the hand's (2, 2).

:class:`SDCModel` evaluates a checkpoint with plain numpy (no torch at control time): the two
networks as one fused network of three matmuls.
"""
from __future__ import annotations

import hashlib
import math
from pathlib import Path
import pickle
import re

import numpy as np
import torch
from torch import nn

from soft_gripper_sdre.learning.dataset import ZIP_MAGIC
from soft_gripper_sdre.sim.shape import (
    HAND_SHAPE,
    FingerShape,
    InputBounds,
    ShapeError,
    shape_from_record,
)

FORMAT_VERSION = 1
HIDDEN = 32
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


#: OpenBLAS's thread-count setters, as numpy's and scipy's wheels (64-bit and 32-bit integer
#: builds, symbols prefixed ``scipy_``) and a system OpenBLAS name them
_OPENBLAS_SETTERS = ('scipy_openblas_set_num_threads64_', 'scipy_openblas_set_num_threads',
                     'openblas_set_num_threads64_', 'openblas_set_num_threads')


def set_blas_threads(n: int) -> int:
    """Run every OpenBLAS loaded in this process (numpy's and scipy's; scipy.linalg is loaded
    first) on ``n`` threads; returns how many libraries were set (0 where none is found or the
    process's maps cannot be read).

    The training tools' closed-loop checks and labels do linear algebra on matrices of a few rows
    (a 4 × 4 Riccati equation per period): a second OpenBLAS thread cannot share such work, and on
    a loaded machine waking it makes each call wait for a core (a 4 × 4 triangular solve took
    4.3 ms with OpenBLAS's default threads beside other work, 0.09 ms on one). The results are
    the same bits: OpenBLAS splits a product over its output's blocks, not its sums.
    """
    import ctypes

    import scipy.linalg  # noqa: F401  (scipy's OpenBLAS is loaded with it)

    if int(n) < 1:
        raise ValueError(f'n must be >= 1, got {n!r}')
    try:
        with open('/proc/self/maps') as maps:
            paths = {line.split()[-1] for line in maps if 'openblas' in line.lower()}
    except OSError:
        return 0
    done = 0
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _OPENBLAS_SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter(ctypes.c_int(int(n)))
                done += 1
                break
    return done


# ----------------------------------------------------------------------------------------------
# networks
# ----------------------------------------------------------------------------------------------

def mlp(n_in: int, n_out: int, hidden: int = HIDDEN) -> nn.Sequential:
    """Three fully connected layers with ReLU between (none after the last)."""
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, n_out))


class SDCNet(nn.Module):
    """NN_θ1 (A21, A22) and NN_θ2 (G2) of a finger of ``shape``, in scaled units: a_net maps the
    state (2d) to vec([A21 A22]) (2d²), g_net to vec(G2) (dm), both vecs column-stacked."""

    def __init__(self, hidden: int = HIDDEN, shape: FingerShape = HAND_SHAPE) -> None:
        super().__init__()
        self.shape = shape
        a_out, g_out = shape.network_outputs
        self.a_net = mlp(shape.n_state, a_out, hidden)
        self.g_net = mlp(shape.n_state, g_out, hidden)

    def forward(self, xs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Scaled state (B, 2d) → [A21 A22] (B, d, 2d) and G2 (B, d, m) (column-stacked
        vec⁻¹)."""
        d, m = self.shape.d, self.shape.m
        a = self.a_net(xs).reshape(-1, 2 * d, d).transpose(1, 2)
        g = self.g_net(xs).reshape(-1, m, d).transpose(1, 2)
        return a, g

    def accel(self, xs: torch.Tensor, us: torch.Tensor) -> torch.Tensor:
        """Scaled p̈ = [A21 A22] x + G2 u: (B, d) from states (B, 2d) and inputs (B, m)."""
        a, g = self(xs)
        return (a @ xs.unsqueeze(-1) + g @ us.unsqueeze(-1)).squeeze(-1)


# ----------------------------------------------------------------------------------------------
# checkpoint
# ----------------------------------------------------------------------------------------------

def read_checkpoint(path: Path) -> dict:
    """Load and check a checkpoint; no code in the file is ever executed.

    Raises:
        ModelFileError: missing, unreadable or truncated, carrying pickled objects, another format
            version, a shape or input bounds that cannot be used or do not agree, or network sizes
            or scales other than the shape's.

    Returns:
        The checkpoint's plain data with ``'net'`` (the :class:`SDCNet` loaded), ``'shape'`` (its
        :class:`~soft_gripper_sdre.sim.shape.FingerShape`) and ``'input_bounds'`` (its
        :class:`~soft_gripper_sdre.sim.shape.InputBounds`, or None).
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
        raise ModelFileError(f'model file {path} is not a checkpoint: a torch.save file is a zip '
                             f'archive and this one starts with {head!r} '
                             f'(corrupt, or another kind of file)')
    try:
        ckpt = torch.load(path, map_location='cpu', weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r'Unsupported global: GLOBAL ([\w.]+)', str(exc))
        what = f' (it needs {found.group(1)})' if found else ''
        raise ModelFileError(f'model file {path} holds objects other than tensors and plain '
                             f'data{what}; refused without running them') from None
    except Exception as exc:  # torch reports a non-zip file through whatever its legacy reader hits
        raise ModelFileError(f'model file {path} is unreadable or truncated: {exc}'[:400]) from None
    if not isinstance(ckpt, dict) or 'format_version' not in ckpt:
        raise ModelFileError(f'model file {path} is not a soft_gripper_sdre checkpoint')
    if ckpt['format_version'] != FORMAT_VERSION:
        raise ModelFileError(f'model file {path} has format version {ckpt["format_version"]}, '
                             f'this package reads version {FORMAT_VERSION}')
    shape, bounds = _checkpoint_shape(path, ckpt)
    try:
        hidden = int(ckpt['architecture']['hidden'])
        _check_architecture(ckpt['architecture'], shape)
        net = SDCNet(hidden, shape)
        net.load_state_dict(ckpt['state_dict'])
        for key, n in (('x', shape.n_state), ('u', shape.m), ('acc', shape.d)):
            if tuple(ckpt['scales'][key].shape) != (n,):
                raise ValueError(f'scale {key} has shape {tuple(ckpt["scales"][key].shape)}, '
                                 f'the shape ({shape}) needs ({n},)')
        if tuple(ckpt['rest_tip'].shape) != (3,):
            raise ValueError(f'rest_tip has shape {tuple(ckpt["rest_tip"].shape)}')
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        raise ModelFileError(
            f'model file {path} does not match the network layout: {exc}'[:400]) from None
    _check_record(path, ckpt)
    ckpt['net'] = net
    ckpt['shape'], ckpt['input_bounds'] = shape, bounds
    return ckpt


def _check_record(path: Path, ckpt: dict) -> None:
    """The checkpoint's numbers a model is built from are finite (``rest_tip``, every scale,
    every weight), its period ``dt`` a positive number, and the records the model carries
    (``settings``, ``data``, ``metrics``: mappings; ``history``: a mapping or a list) present.

    Raises:
        ModelFileError: naming the key and what it holds.
    """
    def bad(key: str, why: str) -> ModelFileError:
        return ModelFileError(f'model file {path}: {key} {why}'[:400])
    tensors = {'rest_tip': ckpt['rest_tip'],
               **{f'scale {k}': v for k, v in ckpt['scales'].items()},
               **{f'weight {k}': v for k, v in ckpt['state_dict'].items()}}
    for key, value in tensors.items():
        if not bool(torch.isfinite(value).all()):
            raise bad(key, 'holds a NaN or an infinity')
    dt = ckpt.get('dt')
    if isinstance(dt, torch.Tensor) and dt.numel() == 1:
        dt = dt.item()
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt)
                                                                         and dt > 0):
        raise bad('dt', f'must be a period > 0 s, got {dt!r}')
    for key, kinds in (('settings', dict), ('data', dict), ('metrics', dict),
                       ('history', (dict, list))):
        if key not in ckpt:
            raise bad(key, 'is missing (a checkpoint tools.learning.train writes has it)')
        if not isinstance(ckpt[key], kinds):
            raise bad(key, f'must be a mapping, got {type(ckpt[key]).__name__}')


def _checkpoint_shape(path: Path, ckpt: dict) -> tuple[FingerShape, InputBounds | None]:
    """The checkpoint's shape (the hand's without a ``'shape'`` key) and input bounds (None
    without an ``'input_bounds'`` key, or with None there), checked against each other."""
    try:
        shape = shape_from_record(ckpt.get('shape'), 'shape')
        record = ckpt.get('input_bounds')
        bounds = None if record is None else InputBounds.from_record(record, 'input_bounds')
    except ShapeError as exc:
        raise ModelFileError(f'model file {path}: {exc}'[:400]) from None
    if bounds is not None and bounds.m != shape.m:
        raise ModelFileError(f'model file {path}: input_bounds name {bounds.m} input(s), the '
                             f'shape ({shape}) has {shape.m}')
    return shape, bounds


def _check_architecture(arch: dict, shape: FingerShape) -> None:
    """ValueError when the sizes the checkpoint declares (``n_state``, ``n_input``, ``a_out``,
    ``g_out``, those present) are not those of ``shape``."""
    a_out, g_out = shape.network_outputs
    for key, want in (('n_state', shape.n_state), ('n_input', shape.m), ('a_out', a_out),
                      ('g_out', g_out)):
        if key in arch and arch[key] != want:
            raise ValueError(f'architecture {key} = {arch[key]!r}, the shape ({shape}) '
                             f'needs {want}')


def weights_sha256(path: Path) -> str:
    """sha256 over the checkpoint's network weights (every tensor of the state dict, by name): two
    checkpoints with the same value are the same model bit for bit, whatever else they record."""
    state = read_checkpoint(path)['state_dict']
    h = hashlib.sha256()
    for key in sorted(state):
        a = state[key].detach().cpu().numpy()
        h.update(key.encode())
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def fused_layers(sd: dict[str, np.ndarray], s: dict[str, np.ndarray],
                  shape: FingerShape = HAND_SHAPE) -> list[tuple[np.ndarray, np.ndarray]]:
    """NN_θ1 and NN_θ2 as one network in physical units, for evaluation with three matmuls.

    The two networks take the same input, so they run side by side: layer 1 stacks their weights
    (2d → 2·32), layers 2 and 3 are block-diagonal. The scalings fold into the weights: the input
    x / s_x into layer 1's rows, and the output factors (A_ij = s_a,i Â_ij / s_x,j,
    G2_ij = s_a,i Ĝ_ij / s_u,j) into layer 3's columns, which are also reordered from the networks'
    column-stacked vec to row-major [A21 A22] (d × 2d) then G2 (d × m); the hand's 8 then 4.

    Returns:
        [(w1, b1), (w2, b2), (w3, b3)] with h ↦ relu(h w1 + b1) ↦ relu(· w2 + b2) ↦ · w3 + b3.
    """
    layer = lambda net, i: (sd[f'{net}.{i}.weight'].T, sd[f'{net}.{i}.bias'])  # noqa: E731
    (a1, c1), (a2, c2), (a3, c3) = (layer('a_net', i) for i in (0, 2, 4))
    (g1, d1), (g2, d2), (g3, d3) = (layer('g_net', i) for i in (0, 2, 4))
    ha, hg = a1.shape[1], g1.shape[1]
    d, m = shape.d, shape.m
    a_out, g_out = shape.network_outputs
    w1 = np.hstack([a1, g1]) / s['x'][:, None]
    b1 = np.concatenate([c1, d1])
    w2 = np.zeros((ha + hg, ha + hg))
    w2[:ha, :ha], w2[ha:, ha:] = a2, g2
    b2 = np.concatenate([c2, d2])
    w3 = np.zeros((ha + hg, a_out + g_out))
    b3 = np.zeros(a_out + g_out)
    # output k of NN_θ1 is [A21 A22][k % d, k // d] (column-stacked vec), of NN_θ2 is
    # G2[k % d, k // d]
    for k in range(a_out):
        r, c = k % d, k // d
        f = s['acc'][r] / s['x'][c]
        w3[:ha, 2 * d * r + c] = f * a3[:, k]
        b3[2 * d * r + c] = f * c3[k]
    for k in range(g_out):
        r, c = k % d, k // d
        f = s['acc'][r] / s['u'][c]
        w3[ha:, a_out + m * r + c] = f * g3[:, k]
        b3[a_out + m * r + c] = f * d3[k]
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

    Attributes:
        shape: the finger's :class:`~soft_gripper_sdre.sim.shape.FingerShape` (d, m).
        input_bounds: the :class:`~soft_gripper_sdre.sim.shape.InputBounds` the training data
            were recorded under, or None when the checkpoint does not say (the hand's).
        rest_tip: (3,) the settled rest tip [m]; the model's origin is ``rest_tip[:d]``.
    """

    def __init__(self, path: Path | str | None = None) -> None:
        self.path = Path(path) if path is not None else DEFAULT_MODEL
        ckpt = read_checkpoint(self.path)
        self.shape: FingerShape = ckpt['shape']
        self.input_bounds: InputBounds | None = ckpt['input_bounds']
        sd = {k: v.detach().double().numpy() for k, v in ckpt['state_dict'].items()}
        s = {k: v.numpy() for k, v in ckpt['scales'].items()}
        self._layers = fused_layers(sd, s, self.shape)
        self._net = _homogeneous(self._layers)
        self._b1 = {}  # layer 1's bias repeated for small batches of n states (no broadcasting)
        self.rest_tip = ckpt['rest_tip'].numpy().astype(float)
        self.dt = float(ckpt['dt'])
        self.settings = ckpt['settings']
        self.data = ckpt['data']
        self.metrics = ckpt['metrics']
        self.history = ckpt['history']

    @property
    def finger_rests(self) -> dict[str, np.ndarray]:
        """Each finger's own settled rest tip (3,) [m] by name, for a model learned from bags of
        several fingers (each translated by its own rest in training: the mean over the bags of
        its settle phases); {} for a model of one finger's records, whose rest is ``rest_tip``."""
        rests: dict[str, list] = {}
        for bag in self.data.get('bags', []) if isinstance(self.data, dict) else []:
            for name, info in bag.get('fingers', {}).items():
                rests.setdefault(name, []).append(info['rest_tip'])
        return {name: np.mean(np.asarray(v, dtype=float), axis=0) for name, v in rests.items()}

    def sdc_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The learned blocks for states x (2d,) or (n, 2d): [A21 A22] (n, d, 2d) and G2
        (n, d, m); the hand's (n, 2, 4) and (n, 2, 2).

        Both networks run as one: three matmuls with ReLU between (see :func:`fused_layers`; the
        biases of layers 2 and 3 ride on a constant hidden unit, :func:`_homogeneous`).
        """
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            x = x[None]
        n, width = x.shape if x.ndim == 2 else (0, 0)
        d, m, ns = self.shape.d, self.shape.m, self.shape.n_state
        if width != ns:
            raise ValueError(f'x must have shape ({ns},) or (n, {ns}), got {x.shape}')
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
        a_out = 2 * d * d
        return out[:, :a_out].reshape(n, d, ns), out[:, a_out:].reshape(n, d, m)

    @property
    def fused_network(self) -> tuple[np.ndarray, ...]:
        """Copies of the fused network's arrays (w1, b1, w2, b2, w3, b3), float64 and C-contiguous.

        h ↦ relu(x w1 + b1) ↦ relu(· w2 + b2) ↦ · w3 + b3 maps states x (n, 2d) to
        (n, 2d² + dm): row-major [A21 A22] then G2, in SI (:func:`fused_layers`); the hand's
        (n, 4) to (n, 12), 8 then 4. For evaluators outside this package's numpy path, such as
        the compiled control kernels, which take the arrays as inputs.
        """
        return tuple(np.array(a, dtype=np.float64, order='C')
                     for layer in self._layers for a in layer)

    def AG(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A(x) (n, 2d, 2d) and G(x) (n, 2d, m) for states x (2d,) or (n, 2d)."""
        a, g = self.sdc_blocks(x)
        n = a.shape[0]
        d, ns = self.shape.d, self.shape.n_state
        A = np.zeros((n, ns, ns))
        for i in range(d):
            A[:, i, d + i] = 1.0               # ṗ rows: [0 I]
        A[:, d:, :] = a
        G = np.zeros((n, ns, self.shape.m))
        G[:, d:, :] = g
        return A, G

    def A(self, x: np.ndarray) -> np.ndarray:
        return self.AG(x)[0]

    def G(self, x: np.ndarray) -> np.ndarray:
        return self.AG(x)[1]

    def xdot(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """ẋ = A(x) x + G(x) u for (n, 2d) states and (n, m) inputs."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        A, G = self.AG(x)
        return np.einsum('nij,nj->ni', A, x) + np.einsum('nij,nj->ni', G, u)
