"""The control core's compute, timed on the states of the in-process closed loop: the compiled
laws against the scipy reference, the KF, and the graph's law run cold as a node runs it.

Every figure is a median of per-step wall times over a replay of a closed-loop run (its
estimates, references and measurements), so the fast path's warm starts are as far off as in
the loop; the first, cold step is left out. Where two paths compete they are timed interleaved,
step by step on the same state, so their ratio holds under the machine's shifting load.
:func:`rows` gives the rows :mod:`soft_gripper_sdre.tools.benchmarks.bench` writes.

Beside the hand's, the controller of a finger with a 3-D tip and three inputs (d = 3, m = 3) on
the general path (:func:`bench_shaped`): the general kernels against the numpy general path, each
row the median of at least five repeats with their min–max.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import NamedTuple

import numpy as np

Row = tuple[str, str, str]


def _us(seconds: float) -> str:
    return f'{seconds * 1e6:.0f} µs'


class _Replay(NamedTuple):
    """A closed-loop run as :func:`bench_control` replays it to ``law``."""

    law: str
    #: per step, the law's arguments: position, velocity, reference position, velocity and
    #: acceleration (contiguous)
    steps: list[tuple[np.ndarray, ...]]
    #: per step, the kernel's z: the arguments stacked (``sdre``'s without the acceleration)
    z: list[np.ndarray]
    #: the steps the reference runs on too
    paired: set[int]
    #: the fingertip's rest position, the kernel's origin
    origin: np.ndarray

    @classmethod
    def of(cls, loop, law: str, ref_steps: int, model) -> _Replay:
        """``loop``'s states for ``law``, the reference paired on ``ref_steps`` steps spread over
        the run (never the first)."""
        T = len(loop.est)
        acc = np.gradient(loop.ref_vel, loop.t, axis=0)        # the moving reference's acceleration
        steps = [tuple(np.ascontiguousarray(a) for a in (loop.est[k, :, :2], loop.est[k, :, 2:],
                                                         loop.ref_pos[k], loop.ref_vel[k], acc[k]))
                 for k in range(T)]
        z = [np.concatenate(s[:4] if law == 'sdre' else s, axis=1) for s in steps]
        paired = set(np.linspace(1, T - 1, min(ref_steps, T - 1)).astype(int).tolist())
        return cls(law, steps, z, paired, np.array(model.rest_tip[:2], dtype=np.float64))


@dataclass
class _ReplayTimes:
    """What the replays of :func:`bench_control` gather: per-step wall times [s] of the fast law
    (``fast``; ``fast_paired`` on the steps the reference also ran), the reference and the bare
    kernel call; the fast path's Newton–Kleinman iterations; the largest difference of the
    unsaturated torques to the reference's (``worst``) and the largest of those (``scale``)."""

    t: dict[str, list[float]] = field(default_factory=lambda: {
        k: [] for k in ('fast', 'fast_paired', 'reference', 'kernel')})
    iterations: list[int] = field(default_factory=list)
    worst: float = 0.0
    scale: float = 0.0

    def summary(self) -> dict[str, float]:
        """The medians of the times, the mean iterations, the share of exact solves (none) and
        the difference relative to the scale."""
        result = {k: float(np.median(v)) for k, v in self.t.items()}
        result['iterations'] = float(np.mean(self.iterations))
        result['exact'] = float(np.mean(np.array(self.iterations) == 0))
        result['difference'] = self.worst / self.scale
        return result


def _replay_once(fast, ref, replay: _Replay, times: _ReplayTimes) -> None:
    """One pass over ``replay`` into ``times``: the fast law every step and right after it the
    bare kernel call from the same warm start; on the paired steps the reference, from the same
    integral, right after the fast law."""
    from soft_gripper_sdre.control.kernels import (
        FeedforwardOutputs,
        SdreOutputs,
        SdreState,
        feedforward_step,
        tracking_step,
    )
    t, n = times.t, replay.steps[0][0].shape[0]
    s = fast.sdre
    integral = getattr(fast, 'integral', None)
    state, out, ff = SdreState(n), SdreOutputs(n), FeedforwardOutputs(n)
    clock = time.perf_counter
    for k, (pos, vel, ref_pos, ref_vel, ref_acc) in enumerate(replay.steps):
        state.records[:] = s.state.records            # the warm start the law starts from
        xi = None if integral is None else integral.xi.copy()
        t0 = clock()
        step = fast.compute(pos, vel, ref_pos, ref_vel, ref_acc=ref_acc)
        t1 = clock()
        if replay.law == 'sdre':
            tracking_step(replay.z[k], replay.origin, *fast.network, s.settings.records,
                          state.records, out.records)
        else:
            feedforward_step(replay.z[k], replay.origin, False, *fast.network, s.settings.records,
                             state.records, out.records, ff.records)
        t2 = clock()
        if k == 0:
            continue
        times.iterations.append(int(step.nk_iterations.max()))
        t['fast'].append(t1 - t0)
        t['kernel'].append(t2 - t1)
        if k in replay.paired:
            if xi is not None:                        # the reference from the same integral
                ref.integral.xi[:] = xi
            t0 = clock()
            reference = ref.compute(pos, vel, ref_pos, ref_vel, ref_acc=ref_acc)
            t['reference'].append(clock() - t0)
            t['fast_paired'].append(t['fast'][-1])
            times.worst = max(times.worst, float(np.abs(step.u_unsat - reference.u_unsat).max()))
            times.scale = max(times.scale, float(np.abs(reference.u_unsat).max()))


def bench_control(loop, law: str, repeats: int, ref_steps: int) -> dict[str, float]:
    """``law``'s compute, compiled (the fast path) against the scipy reference, on the states of a
    closed-loop run (replayed).

    The fast law (which warm-starts from the step before) runs every step, and right after it the
    bare kernel call (``tracking_step`` / ``feedforward_step``) from the same warm start; the
    reference runs on ``ref_steps`` steps spread over the run, each timed right after the fast one
    on the same state, so the ratio compares the two under the same load. Returns medians of
    per-step wall times [s] (the first, cold step left out), the fast path's mean Newton–Kleinman
    iterations per step, its share of exact solves, and the largest difference of the unsaturated
    torques to the reference's relative to the largest of those; and ``runs``: per repeat (a
    replay with fresh laws) the medians of ``fast``, ``kernel`` and ``reference`` and the ratio
    ``reference / fast_paired``.
    """
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    n = loop.est.shape[1]
    replay, times = _Replay.of(loop, law, ref_steps, model), _ReplayTimes()
    runs: dict[str, list[float]] = {'fast': [], 'kernel': [], 'reference': [], 'ratio': []}
    for _ in range(repeats):
        fast = make_law(law, model, w, 0.0625, n_fingers=n, method='fast')
        ref = make_law(law, model, w, 0.0625, n_fingers=n, method='reference')
        once = _ReplayTimes()
        _replay_once(fast, ref, replay, once)
        for key, v in once.t.items():
            times.t[key] += v
        times.iterations += once.iterations
        times.worst, times.scale = max(times.worst, once.worst), max(times.scale, once.scale)
        run = once.summary()
        for key in ('fast', 'kernel', 'reference'):
            runs[key].append(run[key])
        runs['ratio'].append(run['reference'] / run['fast_paired'])
    return {**times.summary(), 'runs': runs}


def bench_kf(loop, repeats: int, runs: list[float] | None = None) -> float:
    """Median wall time of one ConstantVelocityKF step for every finger (compiled) [s], on the
    loop's measurements; ``runs``, if given, gets each repeat's median."""
    from soft_gripper_sdre.control.kf import ConstantVelocityKF
    meas = [np.ascontiguousarray(z) for z in loop.meas]
    samples = []
    clock = time.perf_counter
    for _ in range(repeats):
        kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=meas[0].shape[0])
        kf.reset(meas[0])
        once = []
        for z in meas[1:]:
            t0 = clock()
            kf.step(z)
            once.append(clock() - t0)
        samples += once
        if runs is not None:
            runs.append(float(np.median(once)))
    return float(np.median(samples))


def bench_idle(loop, law: str = 'sdre_ff', repeats: int = 1) -> dict[str, list[float]]:
    """The graph's law on the closed loop's states, as a node runs it: median compute [s] right
    after 1 ms of sleep (``idle``: a node waiting for its next estimate), right after sweeping
    64 MB of memory (``flushed``: other processes ran on the core meanwhile, as in the graph), and
    back to back (``busy``: as the replays above); each a list of ``repeats`` runs, each run over
    its own consecutive share of the loop's steps with fresh laws (the first, cold step left out).

    Three instances of the law step through the same states, one after the other at each step, so
    all see the same warm starts and the same load.
    """
    T = len(loop.est)
    bounds = np.linspace(0, T, repeats + 1).astype(int)
    runs = [_idle_once(loop, law, range(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]
    return {k: [r[k] for r in runs] for k in runs[0]}


def _idle_once(loop, law: str, steps: range) -> dict[str, float]:
    """One run of :func:`bench_idle` over the loop's ``steps``."""
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    laws = {k: make_law(law, model, w, 0.0625, n_fingers=4) for k in ('idle', 'flushed', 'busy')}
    before = {'idle': lambda: time.sleep(1e-3), 'flushed': np.ones(8_000_000).sum,
              'busy': lambda: None}
    acc = np.zeros((loop.est.shape[1], 2))
    clock, t = time.perf_counter, {k: [] for k in laws}
    for k in steps:
        args = (loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k], loop.ref_vel[k])
        for name, ctl in laws.items():
            before[name]()
            t0 = clock()
            ctl.compute(*args, ref_acc=acc)
            if k != steps[0]:
                t[name].append(clock() - t0)
    return {k: float(np.median(v)) for k, v in t.items()}


#: the hidden units per network of the (d, m) bench model, as the package's SDC networks have
SHAPED_HIDDEN = 32
#: the (d, m) bench: control period [s], reference amplitude [m] and frequency [Hz], estimate
#: noise [m], input limit (each input ±, in the input's unit)
SHAPED_DT, SHAPED_AMPLITUDE, SHAPED_HZ, SHAPED_NOISE, SHAPED_U_MAX = 1e-3, 2e-3, 1.0, 5e-5, 0.05


class ShapedBenchModel:
    """An SDC model of shape (d, m) built as the package's are: two networks of
    :data:`SHAPED_HIDDEN` units fused into one (``fused_network``, the layout of
    :attr:`SDCModel.fused_network <soft_gripper_sdre.learning.model.SDCModel.fused_network>`),
    evaluated in numpy by :meth:`sdc_blocks`. Its weights are random but fixed (``seed``), about a
    stiff, damped finger: the blocks at rest are A21 = −diag(300, 900, 600)[:d] [1/s²],
    A22 = −2 I [1/s], a G2 of rank min(d, m) (some 500 m/s² per input unit), and the hidden units
    vary them by some ten percent over millimetres. The per-step cost of a law on it is that of a
    trained model of the shape; it stands in for one (no (3, 3) model is shipped)."""

    def __init__(self, d: int, m: int, seed: int = 0) -> None:
        from soft_gripper_sdre.sim.shape import FingerShape
        self.shape = FingerShape(d, m)
        self.d, self.m = d, m
        self.rest_tip = np.array([0.01, -0.02, 0.3])
        rng = np.random.default_rng(seed)
        k, h = 2 * d, 2 * SHAPED_HIDDEN
        n_out = 2 * d * d + d * m
        a21 = -np.diag([300.0, 900.0, 600.0][:d])
        g2 = 500.0 * (np.eye(d, m) + 0.2 * rng.uniform(-1, 1, (d, m)))
        rest = np.concatenate([np.hstack([a21, -2.0 * np.eye(d)]).ravel(), g2.ravel()])
        w1 = rng.normal(0, 1.0, (k, h)) * np.r_[np.full(d, 300.0), np.full(d, 3.0)][:, None]
        w2 = rng.normal(0, 0.3, (h, h))
        w3 = rng.normal(0, 0.05 / np.sqrt(h), (h, n_out)) * np.abs(rest)[None, :]
        self._layers = [w1, rng.normal(0, 0.5, h), w2, rng.normal(0, 0.3, h), w3,
                        np.zeros(n_out)]
        self._layers[5] = rest - self._out(np.zeros((1, k)))[0]         # the rest blocks at 0

    def _out(self, x: np.ndarray) -> np.ndarray:
        w1, b1, w2, b2, w3, b3 = self._layers
        return np.maximum(np.maximum(x @ w1 + b1, 0.0) @ w2 + b2, 0.0) @ w3 + b3

    @property
    def fused_network(self) -> tuple[np.ndarray, ...]:
        return tuple(np.array(a, dtype=np.float64) for a in self._layers)

    def sdc_blocks(self, x) -> tuple[np.ndarray, np.ndarray]:
        d, m = self.d, self.m
        out = self._out(np.atleast_2d(np.asarray(x, dtype=float)))
        return out[:, :2 * d * d].reshape(-1, d, 2 * d), out[:, 2 * d * d:].reshape(-1, d, m)

    def AG(self, x) -> tuple[np.ndarray, np.ndarray]:
        d = self.d
        a2, g2 = self.sdc_blocks(x)
        A = np.zeros((len(a2), 2 * d, 2 * d))
        A[:, :d, d:] = np.eye(d)
        A[:, d:, :] = a2
        G = np.zeros((len(a2), 2 * d, self.m))
        G[:, d:, :] = g2
        return A, G


def shaped_loop(model: ShapedBenchModel, n: int, steps: int, seed: int = 0) -> list[tuple]:
    """The law's arguments at each step of a closed loop of ``n`` fingers on ``model`` (the plant
    is the model, 5 semi-implicit Euler substeps a period) under the compiled sdre_ff law: each
    finger tracks its own 3-D circle-and-bob of :data:`SHAPED_AMPLITUDE`, its estimate carrying
    :data:`SHAPED_NOISE` of white noise. Returns (pos, vel, ref_pos, ref_vel, ref_acc) per step,
    each (n, d), contiguous."""
    from soft_gripper_sdre.control.laws import SdreFeedforwardLaw
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.sim.shape import InputBounds
    d, m = model.d, model.m
    law = SdreFeedforwardLaw(model, Weights(**DEFAULT_WEIGHTS), SHAPED_U_MAX, n_fingers=n,
                             dt=SHAPED_DT, bounds=InputBounds.symmetric(SHAPED_U_MAX, m))
    rng = np.random.default_rng(seed)
    w = 2 * np.pi * SHAPED_HZ
    phase = np.linspace(0.0, np.pi, n)[:, None] + np.arange(d)[None, :] * (np.pi / 2)
    x = np.zeros((n, 2 * d))
    origin = model.rest_tip[:d]
    out = []
    for k in range(steps):
        t = k * SHAPED_DT
        ref = origin + SHAPED_AMPLITUDE * np.sin(w * t + phase)
        ref_v = SHAPED_AMPLITUDE * w * np.cos(w * t + phase)
        ref_a = -SHAPED_AMPLITUDE * w * w * np.sin(w * t + phase)
        est = x[:, :d] + origin + SHAPED_NOISE * rng.standard_normal((n, d))
        args = tuple(np.ascontiguousarray(a) for a in (est, x[:, d:].copy(), ref, ref_v, ref_a))
        u = law.compute(*args[:4], ref_acc=args[4]).u
        for _ in range(5):
            a2, g2 = model.sdc_blocks(x)
            acc = np.einsum('nij,nj->ni', a2, x) + np.einsum('nij,nj->ni', g2, u)
            x[:, d:] += SHAPED_DT / 5 * acc
            x[:, :d] += SHAPED_DT / 5 * x[:, d:]
        out.append(args)
    return out


def bench_shaped(n: int, repeats: int, steps: int, numpy_every: int, d: int = 3,
                 m: int = 3) -> dict[str, object]:
    """sdre_ff for ``n`` fingers of shape (d, m) on the general path: the general kernels
    (``compiled``) against the numpy general path (``numpy``), replaying :func:`shaped_loop`'s
    states, ``repeats`` times with fresh laws.

    The compiled law runs every step; on every ``numpy_every``-th step the numpy law runs right
    after it on the same state and from the same integral, so their ratio holds under the same
    load; on the other steps the numpy law takes the compiled law's warm starts, so that each
    timed step of both starts from the same P. Returns per path the median per-step wall time [s]
    of each repeat (the first, cold step left out), the compiled path's on the paired steps, its
    mean Newton–Kleinman iterations per finger, and the largest difference of the unsaturated
    torques relative to the largest of the numpy path's."""
    from soft_gripper_sdre.control.laws import SdreFeedforwardLaw
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.sim.shape import InputBounds
    model = ShapedBenchModel(d, m)
    replay = shaped_loop(model, n, steps)
    w, bounds = Weights(**DEFAULT_WEIGHTS), InputBounds.symmetric(SHAPED_U_MAX, m)
    result = {'compiled': [], 'compiled_paired': [], 'numpy': [], 'iterations': []}
    worst = scale = 0.0
    clock = time.perf_counter
    for _ in range(repeats):
        laws = [SdreFeedforwardLaw(model, w, SHAPED_U_MAX, n_fingers=n, dt=SHAPED_DT,
                                   bounds=bounds, compiled=c) for c in (True, False)]
        t = {'compiled': [], 'compiled_paired': [], 'numpy': []}
        iterations = []
        for k, (pos, vel, ref, ref_v, ref_a) in enumerate(replay):
            xi = laws[0].integral.xi.copy()
            t0 = clock()
            fast = laws[0].compute(pos, vel, ref, ref_v, ref_acc=ref_a)
            t1 = clock()
            laws[1].integral.xi[:] = xi
            if k % numpy_every == 0 or k == 0:
                t2 = clock()
                slow = laws[1].compute(pos, vel, ref, ref_v, ref_acc=ref_a)
                t3 = clock()
                if k:
                    t['numpy'].append(t3 - t2)
                    t['compiled_paired'].append(t1 - t0)
                    worst = max(worst, float(np.abs(fast.u_unsat - slow.u_unsat).max()))
                    scale = max(scale, float(np.abs(slow.u_unsat).max()))
            else:
                laws[1].sdre.warm_start(laws[0].sdre.state.P)    # numpy warm as the kernels
                laws[1].sdre.state.warm[:] = laws[0].sdre.state.warm
            if k:
                t['compiled'].append(t1 - t0)
                iterations.append(float(fast.nk_iterations.mean()))
        for key, v in t.items():
            result[key].append(float(np.median(v)))
        result['iterations'].append(float(np.mean(iterations)))
    result['difference'] = worst / max(scale, 1e-300)
    return result


def _spread_us(samples: list[float]) -> str:
    """The median of the repeats' figures and their min–max [µs]."""
    lo, mid, hi = (float(np.min(samples)), float(np.median(samples)), float(np.max(samples)))
    return f'{mid * 1e6:.0f} µs ({lo * 1e6:.0f}–{hi * 1e6:.0f})'


def shaped_rows(quick: bool) -> list[Row]:
    """The (d = 3, m = 3) controller rows: sdre_ff for 2 and 4 fingers on the general path,
    compiled and numpy, each the median (min–max) of at least 5 repeats."""
    out: list[Row] = []
    repeats, steps = (5, 300) if quick else (7, 1000)
    for n in (2, 4):
        r = bench_shaped(n, repeats, steps, numpy_every=4 if quick else 5)
        ratios = [a / b for a, b in zip(r['numpy'], r['compiled_paired'])]
        out += [(f'controller compute, sdre_ff, (d = 3, m = 3), {n} fingers (compiled)',
                 _spread_us(r['compiled']),
                 f'median (min–max) of {repeats} repeats; the general kernels, '
                 f'{np.median(ratios):.0f}× ({min(ratios):.0f}–{max(ratios):.0f}×) faster than '
                 'the numpy general path on the same steps; a closed loop of a synthetic 3-D, '
                 'three-input model (0.05 mm noise): '
                 f'{np.median(r["iterations"]):.2f} Newton–Kleinman iterations per finger and '
                 f"step; torques within {r['difference']:.1e} of the largest of the numpy path's"),
                (f'controller compute, sdre_ff, (d = 3, m = 3), {n} fingers (numpy general path)',
                 _spread_us(r['numpy']),
                 f'median (min–max) of {repeats} repeats; Newton–Kleinman in numpy/scipy, '
                 'general checks, pseudo-inverse feedforward')]
    return out


def rows(loop, quick: bool, figures: dict[str, float] | None = None) -> list[Row]:
    """The compute rows of BENCHMARKS.md, on the states of ``loop`` (the noisy closed loop) and of
    a clean one: both laws compiled and as the reference, ``sdre`` on clean states, the KF, and
    ``sdre_ff`` cold; each figure the median (min–max) of :data:`REPEATS` replays (two with
    ``quick``), with the load before and after. ``figures``, if given, gets what the floor rows
    compare: the KF step (``kf_s``) and ``sdre_ff``'s compiled compute (``control_s``) [s],
    medians."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    from soft_gripper_sdre.tools.benchmarks.spread import REPEATS, LoadWatch, figure, median
    repeats = 2 if quick else REPEATS
    out: list[Row] = []
    load = LoadWatch()
    load.note()
    for law in ('sdre', 'sdre_ff'):
        ctrl = bench_control(loop, law, repeats, 100 if quick else 300)
        runs = ctrl['runs']
        out += [(f'controller compute, {law}, 4 fingers (compiled)', figure(runs['fast']),
                 f'{median(runs["ratio"]):.0f}× ({min(runs["ratio"]):.0f}–'
                 f'{max(runs["ratio"]):.0f}×) faster than the reference '
                 'on the same steps; states of the closed loop below (0.05 mm noise): '
                 f'{ctrl["iterations"]:.2f} Newton–Kleinman iterations per step, '
                 f'{100 * ctrl["exact"]:.1f} % exact solves; '
                 f'torques within {ctrl["difference"]:.1e} of '
                 "the largest of the reference's; the kernel call alone "
                 f'{figure(runs["kernel"])}'),
                (f'controller compute, {law}, 4 fingers (scipy reference)',
                 figure(runs['reference']),
                 'scipy solve_continuous_are per finger, general checks')]
    clean = bench_control(default_grasp(1.0 if quick else 2.0, noise_std=0.0), 'sdre', repeats,
                          50 if quick else 200)
    out.append(('controller compute, sdre, 4 fingers (compiled), clean states',
                figure(clean['runs']['fast']),
                f'{median(clean["runs"]["ratio"]):.0f}× faster than the reference, '
                'same steps; the same loop without measurement noise: '
                f'{clean["iterations"]:.2f} iterations per step'))
    out += shaped_rows(quick)
    kf_runs: list[float] = []
    bench_kf(loop, repeats, kf_runs)
    out.append(('KF step, 4 fingers (compiled)', figure(kf_runs, digits=1),
                'predict + Joseph-form update, the closed loop\'s measurements'))
    cold = bench_idle(loop, repeats=repeats)
    ratio = lambda k: median([a / b for a, b in zip(cold[k], cold['busy'])])  # noqa: E731
    load.note()
    out.append(('controller compute, sdre_ff (the graph\'s law), cold',
                f'{figure(cold["idle"])} / {figure(cold["flushed"])}',
                'after 1 ms of sleep / after 64 MB of other memory traffic, '
                f'against {figure(cold["busy"])} back to back on the same states '
                f'({ratio("idle"):.1f}× / {ratio("flushed"):.1f}×), each run over its share of the '
                'loop: a node that waits for each estimate while other processes use its core '
                f'runs it cold; the compute rows ran at {load.text()}'))
    if figures is not None:
        figures.update(kf_s=median(kf_runs), control_s=median(ctrl['runs']['fast']))
    return out
