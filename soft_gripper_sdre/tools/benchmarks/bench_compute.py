"""The control core's compute, timed on the states of the in-process closed loop: the compiled
laws against the scipy reference, the KF, and the graph's law run cold as a node runs it.

Every figure is a median of per-step wall times over a replay of a closed-loop run (its
estimates, references and measurements), so the fast path's warm starts are as far off as in
the loop; the first, cold step is left out. Where two paths compete they are timed interleaved,
step by step on the same state, so their ratio holds under the machine's shifting load.
:func:`rows` gives the rows :mod:`soft_gripper_sdre.tools.benchmarks.bench` writes.
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
    torques to the reference's relative to the largest of those.
    """
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    n = loop.est.shape[1]
    replay, times = _Replay.of(loop, law, ref_steps, model), _ReplayTimes()
    for _ in range(repeats):
        fast = make_law(law, model, w, 0.0625, n_fingers=n, method='fast')
        ref = make_law(law, model, w, 0.0625, n_fingers=n, method='reference')
        _replay_once(fast, ref, replay, times)
    return times.summary()


def bench_kf(loop, repeats: int) -> float:
    """Median wall time of one ConstantVelocityKF step for every finger (compiled) [s], on the
    loop's measurements."""
    from soft_gripper_sdre.control.kf import ConstantVelocityKF
    meas = [np.ascontiguousarray(z) for z in loop.meas]
    samples = []
    clock = time.perf_counter
    for _ in range(repeats):
        kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=meas[0].shape[0])
        kf.reset(meas[0])
        for z in meas[1:]:
            t0 = clock()
            kf.step(z)
            samples.append(clock() - t0)
    return float(np.median(samples))


def bench_idle(loop, law: str = 'sdre_ff') -> dict[str, float]:
    """The graph's law on the closed loop's states, as a node runs it: median compute [s] right
    after 1 ms of sleep (``idle``: a node waiting for its next estimate), right after sweeping
    64 MB of memory (``flushed``: other processes ran on the core meanwhile, as in the graph), and
    back to back (``busy``: as the replays above).

    Three instances of the law step through the same states, one after the other at each step, so
    all see the same warm starts and the same load.
    """
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    laws = {k: make_law(law, model, w, 0.0625, n_fingers=4) for k in ('idle', 'flushed', 'busy')}
    before = {'idle': lambda: time.sleep(1e-3), 'flushed': np.ones(8_000_000).sum,
              'busy': lambda: None}
    acc = np.zeros((loop.est.shape[1], 2))
    clock, t = time.perf_counter, {k: [] for k in laws}
    for k in range(len(loop.est)):
        args = (loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k], loop.ref_vel[k])
        for name, ctl in laws.items():
            before[name]()
            t0 = clock()
            ctl.compute(*args, ref_acc=acc)
            if k:
                t[name].append(clock() - t0)
    return {k: float(np.median(v)) for k, v in t.items()}


def rows(loop, quick: bool, figures: dict[str, float] | None = None) -> list[Row]:
    """The compute rows of BENCHMARKS.md, on the states of ``loop`` (the noisy closed loop) and of
    a clean one: both laws compiled and as the reference, ``sdre`` on clean states, the KF, and
    ``sdre_ff`` cold. ``figures``, if given, gets what the floor rows compare: the KF step
    (``kf_s``) and ``sdre_ff``'s compiled compute (``control_s``) [s]."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    out: list[Row] = []
    for law in ('sdre', 'sdre_ff'):
        ctrl = bench_control(loop, law, 1 if quick else 2, 100 if quick else 300)
        out += [(f'controller compute, {law}, 4 fingers (compiled)', _us(ctrl['fast']),
                 f'{ctrl["reference"] / ctrl["fast_paired"]:.0f}× faster than the reference '
                 'on the same steps; states of the closed loop below (0.05 mm noise): '
                 f'{ctrl["iterations"]:.2f} Newton–Kleinman iterations per step, '
                 f'{100 * ctrl["exact"]:.1f} % exact solves; '
                 f'torques within {ctrl["difference"]:.1e} of '
                 "the largest of the reference's; the kernel call alone "
                 f'{_us(ctrl["kernel"])}'),
                (f'controller compute, {law}, 4 fingers (scipy reference)', _us(ctrl['reference']),
                 'scipy solve_continuous_are per finger, general checks')]
    clean = bench_control(default_grasp(1.0 if quick else 2.0, noise_std=0.0), 'sdre', 1,
                          50 if quick else 200)
    out.append(('controller compute, sdre, 4 fingers (compiled), clean states', _us(clean['fast']),
                f'{clean["reference"] / clean["fast_paired"]:.0f}× faster than the reference, '
                'same steps; the same loop without measurement noise: '
                f'{clean["iterations"]:.2f} iterations per step'))
    kf = bench_kf(loop, 1 if quick else 3)
    out.append(('KF step, 4 fingers (compiled)', _us(kf),
                'predict + Joseph-form update, the closed loop\'s measurements'))
    cold = bench_idle(loop)
    out.append(('controller compute, sdre_ff (the graph\'s law), cold',
                f'{_us(cold["idle"])} / {_us(cold["flushed"])}',
                'after 1 ms of sleep / after 64 MB of other memory traffic, '
                f'against {_us(cold["busy"])} back to back on the same states '
                f'({cold["idle"] / cold["busy"]:.1f}× / {cold["flushed"] / cold["busy"]:.1f}×): '
                'a node that waits for each estimate while other processes use its core '
                'runs it cold'))
    if figures is not None:
        figures.update(kf_s=kf, control_s=ctrl['fast'])
    return out
