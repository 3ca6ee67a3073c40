"""Micro-benchmark of the compiled control kernels against the numpy fast path and the scipy reference.

    python -m soft_gripper_sdre.tools.bench_kernel [--seconds 2] [--noise 5e-5] [--no-compile-times]

Replays the estimates and references of an in-process closed loop (hand + cube, default weights,
``--noise`` measurement noise) through every controller, interleaved step by step so that each
sees the same load, and prints per-step wall times for four fingers back to back (median, mean,
99th percentile, first cold step left out), the iterations, the largest torque difference to the
reference, the KF step both ways, and numba's compile time from an empty cache and from a warm one.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault('OMP_NUM_THREADS', '1')      # before numpy loads BLAS: one thread, as the nodes
import numpy as np  # noqa: E402

from soft_gripper_sdre.control.compiled import (FeedforwardOutputs, SdcNetwork, SdreOutputs, SdreSettings,  # noqa: E402
                                                SdreState, feedforward_step, kf_step, sdre_step, tracking_step,
                                                tracking_torques, warm_up)
from soft_gripper_sdre.control.sdre import SdreController  # noqa: E402


class KernelLaw:
    """The compiled kernels wrapped the way a supervisor runs them: one kernel call per step, and
    for every finger it hands back (cold, or a check failed) SdreController's exact path (scipy's
    solve and the general checks, with the SDC form's stabilisability test), run by a cold
    one-finger controller, whose accepted solution goes into the kernels' state. The command's
    roll-off is left out (``lowpass_hz=0`` on the numpy side compares like with like).

    For this benchmark and the equivalence tests (test_compiled.py), which compare it with
    TrackingController (``law='sdre'``), SdreFeedforwardLaw (``'sdre_ff'``) and, through
    :meth:`step_sdc`, SdreController.
    """

    def __init__(self, model, weights, u_max: float, n_fingers: int = 4, law: str = 'sdre', ff_at: str = 'x') -> None:
        if law not in ('sdre', 'sdre_ff'):
            raise ValueError(f'law must be sdre or sdre_ff, got {law!r}')
        self.law, self.ff_at_reference, self.n = law, ff_at == 'ref', int(n_fingers)
        self.network = SdcNetwork.of(model)
        self.settings = SdreSettings.of(weights.Q, weights.R, u_max)
        self.origin = np.array(model.rest_tip[:2], dtype=np.float64)
        self.state, self.out = SdreState.cold(self.n), SdreOutputs.empty(self.n)
        self.ff = FeedforwardOutputs.empty(self.n)
        self.exact = SdreController(weights.Q, weights.R, u_max, n=1)
        self.exact_solves = 0

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> dict[str, np.ndarray]:
        """The law's step (TrackingController / SdreFeedforwardLaw.compute without the roll-off);
        returns copies of u, u_unsat, K, Ks, P, residual, nk_iterations, failed_checks, ok,
        fallback (as SdreStep and LawStep name them)."""
        rows = [np.ascontiguousarray(a, dtype=np.float64) for a in (pos, vel, ref_pos, ref_vel)]
        if self.law == 'sdre':
            tracking_step(*rows, self.origin, *self.network, *self.settings, *self.state, *self.out)
        else:
            acc = np.zeros((self.n, 2)) if ref_acc is None else np.ascontiguousarray(ref_acc, dtype=np.float64)
            feedforward_step(*rows, acc, self.origin, self.ff_at_reference, *self.network, *self.settings,
                             *self.state, *self.out, *self.ff)
        return self._result(lambda: self._feedback_states(*rows))

    def step_sdc(self, a2, g2, x, x_d) -> dict[str, np.ndarray]:
        """SdreController.step_sdc on the kernel (``law='sdre'``): the blocks are given."""
        x, x_d = (np.ascontiguousarray(a, dtype=np.float64) for a in (x, x_d))
        self.out.a2[:], self.out.g2[:] = a2, g2
        sdre_step(x, x_d, *self.settings, *self.state, *self.out)
        return self._result(lambda: (x, x_d))

    def _feedback_states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray]:
        """The (x, x_d) the kernel's SDRE step used: sdre_ff feeds back e = x − x_d with x_d = 0."""
        x = np.concatenate([pos - self.origin, vel], axis=1)
        x_d = np.concatenate([ref_pos - self.origin, ref_vel], axis=1)
        if self.law == 'sdre':
            return x, x_d
        x[~self.ff.state_finite] = x_d[~self.ff.state_finite] = 0.0
        return x - x_d, np.zeros_like(x)

    def _result(self, feedback_states) -> dict[str, np.ndarray]:
        s, out, ff = self.state, self.out, self.ff
        failed, iterations = out.failed.copy(), out.iterations.copy()
        if not s.warm.all():
            self._exact_path(*feedback_states(), failed, iterations)
        ok = s.warm.copy()
        fallback = ~ok
        if self.law == 'sdre_ff':
            ok &= ff.state_finite
            fallback |= ~ff.state_finite | ~ff.ff_usable
        return dict(u=out.u.copy(), u_unsat=out.u_unsat.copy(), K=s.K.copy(), Ks=s.Ks.copy(), P=s.P.copy(),
                    residual=out.residual.copy(), nk_iterations=iterations, failed_checks=failed, ok=ok,
                    fallback=fallback)

    def _exact_path(self, x, x_d, failed, iterations) -> None:
        """scipy and the general checks for the fingers the kernel handed back; torques again."""
        s, out = self.state, self.out
        for i in np.flatnonzero(~s.warm):
            self.exact.reset()                     # cold: no Newton–Kleinman, no gains of another finger
            step = self.exact.step_sdc(out.a2[i:i + 1], out.g2[i:i + 1], x[i:i + 1], x_d[i:i + 1])
            self.exact_solves += self.exact.exact_solves
            failed[i], iterations[i] = step.failed_checks[0], 0
            if step.ok[0]:
                s.P[i], s.K[i], s.Ks[i], s.warm[i] = step.P[0], step.K[0], step.Ks[0], True
                out.residual[i] = step.residual[0]
        finite = (np.isfinite(x).all(axis=1) & np.isfinite(x_d).all(axis=1)
                  & np.isfinite(out.a2).all(axis=(1, 2)) & np.isfinite(out.g2).all(axis=(1, 2)))
        tracking_torques(s.K, s.Ks, x, x_d, finite, self.settings.u_max, out.u, out.u_unsat)
        if self.law == 'sdre_ff':                  # u = u_ff + K e, as the kernel composes it
            v = self.ff.u_ff + out.u_unsat
            v[~(np.isfinite(v) & self.ff.state_finite[:, None])] = 0.0
            out.u_unsat[:] = v
            np.clip(v, -self.settings.u_max, self.settings.u_max, out=out.u)


def replay(seconds: float, noise_std: float):
    """The in-process closed loop whose states the benchmark replays (tools.bench.closed_loop)."""
    from soft_gripper_sdre.tools.bench import closed_loop
    return closed_loop(seconds, noise_std)


def _stats(samples: list[float]) -> str:
    a = np.asarray(samples) * 1e6
    return f'median {np.median(a):6.1f} µs, mean {a.mean():6.1f}, p99 {np.percentile(a, 99):6.1f}'


def bench_laws(loop, law: str, repeats: int = 2) -> dict:
    """Per-step times of the numpy fast path, the compiled kernel (in KernelLaw, and the bare kernel
    call from the same warm starts) and the scipy reference, each run back to back over the loop's
    states, the runs alternating ``repeats`` times; iterations and torque differences."""
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    steps = [tuple(np.ascontiguousarray(a) for a in (loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k],
                                                     loop.ref_vel[k])) for k in range(len(loop.est))]
    kw = {'ref_acc': np.zeros((4, 2))} if law == 'sdre_ff' else {}
    clock = time.perf_counter
    t = {k: [] for k in ('numpy fast', 'compiled (KernelLaw)', 'compiled kernel call', 'scipy reference')}

    def run(name, compute, after=lambda: None):
        """compute(args) for every step, timed; then ``after()``, not timed."""
        out = []
        for k, args in enumerate(steps):
            t0 = clock()
            res = compute(args)
            if k:
                t[name].append(clock() - t0)
            out.append(res)
            after()
        return out

    for _ in range(repeats):
        fast = make_law(law, model, w, 0.0625, method='fast', lowpass_hz=0.0)
        ref = make_law(law, model, w, 0.0625, method='reference', lowpass_hz=0.0)
        compiled = KernelLaw(model, w, 0.0625, law=law)
        before = [tuple(a.copy() for a in compiled.state)]      # the state each step starts from
        out_c = run('compiled (KernelLaw)', lambda args: compiled.compute(*args, **kw),
                    after=lambda: before.append(tuple(a.copy() for a in compiled.state)))
        state, out, ff = SdreState.cold(4), SdreOutputs.empty(4), FeedforwardOutputs.empty(4)
        for k, args in enumerate(steps):            # the kernel alone, from the warm start KernelLaw had
            for src, dst in zip(before[k], state):
                dst[:] = src
            t0 = clock()
            if law == 'sdre':
                tracking_step(*args, compiled.origin, *compiled.network, *compiled.settings, *state, *out)
            else:
                feedforward_step(*args, kw['ref_acc'], compiled.origin, False, *compiled.network,
                                 *compiled.settings, *state, *out, *ff)
            if k:
                t['compiled kernel call'].append(clock() - t0)
        out_f = run('numpy fast', lambda args: fast.compute(*args, **kw))
        out_r = run('scipy reference', lambda args: ref.compute(*args, **kw))
    uc = np.array([o['u_unsat'] for o in out_c])
    uf, ur = (np.array([o.u_unsat for o in outs]) for outs in (out_f, out_r))
    it_fast = [o.nk_iterations.max() for o in out_f[1:]] if law == 'sdre' else None   # LawStep has none
    return dict(times=t, iterations=float(np.mean([o['nk_iterations'].max() for o in out_c[1:]])),
                iterations_numpy=None if it_fast is None else float(np.mean(it_fast)),
                compiled_vs_reference=float(np.abs(uc - ur).max()), fast_vs_reference=float(np.abs(uf - ur).max()),
                compiled_vs_fast=float(np.abs(uc - uf).max()), scale=float(np.abs(ur).max()),
                exact_solves=compiled.exact_solves, exact_solves_numpy=fast.sdre.exact_solves, steps=len(steps))


def bench_kf(loop) -> dict:
    """ConstantVelocityKF.step against kf_step on the loop's measurements (both from the first)."""
    from soft_gripper_sdre.control.kf import ConstantVelocityKF
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
    kf.reset(loop.meas[0])
    x, P = kf.x.copy(), kf.P.copy()
    valid = np.ones(4, dtype=np.bool_)
    F, Q, R = kf.F, kf.Q, kf.R
    t = {'numpy': [], 'compiled': []}
    clock = time.perf_counter
    worst = 0.0
    for k in range(1, len(loop.meas)):
        z = np.ascontiguousarray(loop.meas[k])
        t0 = clock()
        kf_step(x, P, z, valid, F, Q, R)
        t1 = clock()
        xn = kf.step(z)
        t2 = clock()
        t['compiled'].append(t1 - t0)
        t['numpy'].append(t2 - t1)
        worst = max(worst, float(np.abs(x - xn).max() / np.abs(xn).max()))
    return dict(times=t, worst_relative=worst)


def compile_seconds() -> dict[str, float]:
    """Seconds for ``import compiled; warm_up()`` in a fresh interpreter: with an empty numba cache
    (compiling everything) and again with the cache that run left."""
    code = ('import time; t0 = time.perf_counter(); from soft_gripper_sdre.control import compiled; '
            't1 = time.perf_counter(); compiled.warm_up(); t2 = time.perf_counter(); print(t1 - t0, t2 - t1)')
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for name in ('cold', 'cached'):
            res = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, check=True)
            imported, warmed = map(float, res.stdout.split())
            out[f'{name} import'], out[f'{name} warm_up'] = imported, warmed
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.bench_kernel',
                                 description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=2.0, help='length of the replayed closed loop [s]')
    ap.add_argument('--noise', type=float, default=5e-5, help='measurement noise of the closed loop [m]')
    ap.add_argument('--no-compile-times', action='store_true', help='skip the cold / cached compile timings')
    a = ap.parse_args(argv)
    if not a.no_compile_times:
        for name, sec in compile_seconds().items():
            print(f'{name:<20} {sec:7.2f} s')
    warm_up()
    loop = replay(a.seconds, a.noise)
    for law in ('sdre', 'sdre_ff'):
        res = bench_laws(loop, law)
        numpy_its = '' if res['iterations_numpy'] is None else f' (numpy fast path {res["iterations_numpy"]:.2f})'
        print(f'\n{law}: {res["steps"]} steps, {res["iterations"]:.2f} Newton–Kleinman iterations per step'
              f'{numpy_its}, exact solves: {res["exact_solves"]} compiled, {res["exact_solves_numpy"]} numpy')
        for name, samples in res['times'].items():
            print(f'  {name:<20} {_stats(samples)}')
        print(f'  largest |u − u_reference|: compiled {res["compiled_vs_reference"]:.2e} N·m, numpy fast '
              f'{res["fast_vs_reference"]:.2e} N·m (largest |u| {res["scale"]:.2e} N·m); '
              f'|u_compiled − u_numpy fast| ≤ {res["compiled_vs_fast"]:.1e} N·m')
    kf = bench_kf(loop)
    print('\nKF step, 4 fingers')
    for name, samples in kf['times'].items():
        print(f'  {name:<20} {_stats(samples)}')
    print(f'  largest relative difference of x̂: {kf["worst_relative"]:.1e}')
    print(f'\nload average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} '
          f'on {os.cpu_count()} cores')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
