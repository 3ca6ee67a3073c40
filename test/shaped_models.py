"""SDC models of any finger shape (d tip coordinates, m inputs), references such a model can
follow, and a closed loop on the model: the law tests of shapes other than the hand's (shared; no
test imports another). Generalises test/sdc_models.py's StiffeningModel and track_sine."""
import numpy as np

#: rest tip of the test models [m] (a 3-D tip uses all three coordinates, a planar one X, Y)
REST = np.array([0.01, -0.02, 0.3])

#: the input map at rest G₂(0) (d, m) [m/s² per input unit] of each test shape: every input
#: reaches the tip, no two alike; one input drives both axes of a planar tip, whose stiffnesses
#: differ (so the pair is controllable although G₂ is 2 × 1)
INPUT_MAPS = {
    (2, 1): [[600.0], [-350.0]],
    (2, 2): [[10.0, 600.0], [-600.0, 5.0]],
    (2, 3): [[500.0, -200.0, 150.0], [100.0, 450.0, -300.0]],
    (2, 4): [[500.0, -200.0, 150.0, 80.0], [100.0, 450.0, -300.0, 250.0]],
    (3, 2): [[600.0, 50.0], [-100.0, 500.0], [250.0, -300.0]],
    (3, 3): [[600.0, 50.0, -80.0], [-100.0, 500.0, 60.0], [70.0, -40.0, 550.0]],
}
#: per-axis stiffness at rest [1/s²] (X, Y, Z) and damping [1/s]
STIFFNESS = (300.0, 900.0, 600.0)
DAMPING = 2.0


class ShapedModel:
    """A state-dependent SDC model of shape (d, m) with AG only:

        p̈ = −k_i (1 + (p_i / 5 mm)²) p_i − c ṗ + (1 + 20 p_X) s(p) G₂(0) u,

    with p = the tip's displacement from :data:`REST`, G₂(0) from :data:`INPUT_MAPS` (or
    ``G2``), and s(p) = 0 where ``dead_beyond`` [m] is given and p_X exceeds it (a singular input
    map there), else 1.
    """

    rest_tip = REST

    def __init__(self, d, m, G2=None, dead_beyond=None):
        self.d, self.m = d, m
        self.G2 = np.array(INPUT_MAPS[(d, m)] if G2 is None else G2, dtype=float)
        self.dead_beyond = dead_beyond

    def AG(self, x):
        with np.errstate(invalid='ignore'):      # a non-finite state gives non-finite rows
            return self._AG(x)

    def _AG(self, x):
        d = self.d
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[1] != 2 * d:
            raise ValueError(f'x must be (n, {2 * d})')
        n = len(x)
        p = x[:, :d]
        A = np.zeros((n, 2 * d, 2 * d))
        A[:, :d, d:] = np.eye(d)
        k = np.array(STIFFNESS[:d]) * (1.0 + (p / 5e-3) ** 2)
        A[:, d:, :d] = -k[:, :, None] * np.eye(d)
        A[:, d:, d:] = -DAMPING * np.eye(d)
        scale = 1.0 + 20.0 * p[:, 0]
        if self.dead_beyond is not None:
            scale = np.where(p[:, 0] > self.dead_beyond, 0.0, scale)
        G = np.zeros((n, 2 * d, self.m))
        G[:, d:, :] = scale[:, None, None] * self.G2
        return A, G


def rk4(model, x, u, dt):
    """One RK4 step of the model's plant ẋ = A(x) x + G(x) u with u held."""
    def f(z):
        A, G = model.AG(z)
        return A[0] @ z + G[0] @ u
    k1 = f(x)
    k2 = f(x + dt / 2 * k1)
    k3 = f(x + dt / 2 * k2)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + dt * k3))


def input_signal(bounds, hz=2.0, level=0.6):
    """u(t) (m,) within ``bounds``: each input a sine of ``level`` of its half-span about the middle
    of its interval (a one-sided input: starting at its bound nearest 0 and rising), each input at
    its own phase."""
    lo, hi = bounds.lower, bounds.upper
    one = bounds.one_sided
    phase = np.arange(len(lo)) * 2.0

    def u(t):
        w = 2 * np.pi * hz * t
        sym = level * hi * np.sin(w + phase)                               # about 0
        start = np.where(np.abs(lo) < np.abs(hi), lo, hi)
        side = start + level * (hi - lo) * 0.5 * (1 - np.cos(w + phase * 0))  # from the rest bound
        return np.where(one, side, sym)
    return u


def model_reference(model, u_of_t, seconds=0.4, dt=2e-4):
    """A reference the model can follow exactly: its own response from rest to the input
    ``u_of_t``, on the grid k·dt. Returns (pos, vel, acc), each (K + 1, d), in the base frame."""
    d = model.d
    x = np.zeros(2 * d)
    steps = int(round(seconds / dt))
    pos, vel, acc = [], [], []
    for k in range(steps + 1):
        u = u_of_t(k * dt)
        A, G = model.AG(x)
        acc.append((A[0] @ x + G[0] @ u)[d:])
        pos.append(x[:d] + REST[:d])
        vel.append(x[d:].copy())
        x = rk4(model, x, u, dt)
    return np.array(pos), np.array(vel), np.array(acc)


def track(law, model, reference, dt=2e-4, x0=None, noise=0.0, seed=0):
    """Integrate the model's plant under ``law`` (RK4, u held over dt) along ``reference`` (pos,
    vel, acc) from ``x0`` (None: the reference's start). Returns (the tip error [m] after each
    step (K,), the commands (K, m), the law's steps). ``noise``: the estimate's standard
    deviation [m]."""
    d = model.d
    pos, vel, acc = reference
    x = (np.concatenate([pos[0] - REST[:d], vel[0]]) if x0 is None
         else np.asarray(x0, dtype=float))
    rng = np.random.default_rng(seed)
    errors, commands, steps = [], [], []
    for k in range(len(pos) - 1):
        est = x[:d] + REST[:d] + noise * rng.standard_normal(d)
        step = law.compute(est[None], x[None, d:], pos[k][None], vel[k][None], ref_acc=acc[k][None])
        u = step.u[0].copy()
        x = rk4(model, x, u, dt)
        errors.append(np.linalg.norm(x[:d] + REST[:d] - pos[k + 1]))
        commands.append(u)
        steps.append(step)
    return np.array(errors), np.array(commands), steps


#: known systems p̈ = −k p − c ṗ + G₂ u a model is really trained on, by shape (d, m): G₂ [m/s² per
#: input unit] and the inputs' bounds (a one-chamber planar finger, pressure 0..2e5 Pa; a
#: three-tendon 3-D segment, pull-only tendons 0..2 N)
KNOWN_SYSTEMS = {
    (2, 1): (np.array([[5e-6], [-2e-6]]), ([0.0], [2e5])),
    (3, 3): (np.array([[0.6, -0.3, -0.3], [0.0, 0.52, -0.52], [0.2, 0.2, 0.2]]),
             ([0.0] * 3, [2.0] * 3)),
}
KNOWN_STIFFNESS, KNOWN_DAMPING = 400.0, 20.0       # k [1/s²], c [1/s]


def known_system_data(d: int, m: int, n: int, seed: int):
    """``n`` seeded samples (x, u, ẍ) of the known system of shape (d, m), inputs uniform over
    their bounds."""
    from soft_gripper_sdre.sim.shape import InputBounds
    G2, (lower, upper) = KNOWN_SYSTEMS[(d, m)]
    bounds = InputBounds(lower, upper)
    rng = np.random.default_rng(seed)
    u = bounds.lower + (bounds.upper - bounds.lower) * rng.random((n, m))
    scale = np.abs(G2 @ bounds.half_span).max() / KNOWN_STIFFNESS
    p = scale * rng.standard_normal((n, d))
    v = 10 * scale * rng.standard_normal((n, d))
    return np.hstack([p, v]), u, -KNOWN_STIFFNESS * p - KNOWN_DAMPING * v + u @ G2.T


def trained_known_system(d: int, m: int, directory):
    """A checkpoint really trained (20 epochs, seeded) on the known system of shape (d, m), with
    its inputs' bounds: (FingerShape, InputBounds, path of model.pt in ``directory``)."""
    from dataclasses import replace

    import torch

    from soft_gripper_sdre.learning.train_settings import PRESETS
    from soft_gripper_sdre.learning.training import save_checkpoint, train
    from soft_gripper_sdre.sim.shape import FingerShape, InputBounds
    torch.set_num_threads(1)
    settings = replace(PRESETS['default'], epochs=20)
    result = train(*known_system_data(d, m, 2000, 0), *known_system_data(d, m, 400, 1), settings,
                   shape=FingerShape(d, m))
    bounds = InputBounds(*KNOWN_SYSTEMS[(d, m)][1])
    path = directory / 'model.pt'
    save_checkpoint(path, result, rest_tip=np.zeros(3), dt=1e-3, settings=settings,
                    data={'source': 'test'}, input_bounds=bounds)
    return FingerShape(d, m), bounds, path
