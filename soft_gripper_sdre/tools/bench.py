"""Benchmarks: the control core's costs, the simulator, the closed loop in-process and as a graph.

    python -m soft_gripper_sdre.tools.bench [--write BENCHMARKS.md] [--quick]

Prints a table of (what, figure, note) rows; ``--write`` also renders it as Markdown with the
machine facts and the command. Every figure is a median over repeated timings; where two paths
compete (fast vs reference controller, fast vs scipy Riccati solve) they are timed interleaved in
the same run and their ratio is reported, since the machine is shared and absolute numbers drift.
The node-graph rows come from :mod:`soft_gripper_sdre.tools.bench_graph` when it is installed
(``rows(quick) -> [(what, figure, note)]``).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')      # before numpy loads BLAS: one thread, as the nodes
import numpy as np  # noqa: E402

Row = tuple[str, str, str]


def _median_time(fn, repeats: int, inner: int) -> float:
    """Median over ``repeats`` of the mean wall time of ``inner`` calls [s]."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) / inner)
    return statistics.median(samples)


def bench_sim(scene: str, seconds: float, repeats: int) -> float:
    """Median wall time of one control period of the simulator alone (step + measure), u = 0 [s]."""
    from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
    with GripperSim(SimConfig(scene=scene)) as sim:
        u = np.zeros((sim.n_fingers, 2))
        steps = int(seconds / sim.config.control_period / repeats)

        def period():
            sim.step(u)
            sim.measure()
        return _median_time(period, repeats, steps)


def closed_loop(seconds: float, noise_std: float):
    """The grasp closed in-process on the default settings (hand, KF, fast SDRE, roll-off)."""
    from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    from soft_gripper_sdre.sim.hand import SimConfig
    from soft_gripper_sdre.control.trajectory import GraspProfile
    return run_closed_loop(SDCModel(), duration=seconds, weights=Weights(**DEFAULT_WEIGHTS),
                           u_max=0.0625, profile=GraspProfile(others='open'),
                           sim_config=SimConfig(scene='hand', noise_std=noise_std))


def bench_control(loop, repeats: int, ref_steps: int) -> dict[str, float]:
    """Controller, model, Riccati and KF costs on the states of a closed-loop run (replayed).

    The fast controller (which warm-starts from the step before) runs every step; the reference
    runs on ``ref_steps`` steps spread over the run, each timed right after the fast one on the
    same state, so the ratio compares the two under the same load. Returns medians of per-step
    wall times [s] (the first, cold step left out), the fast path's mean Newton–Kleinman iterations
    per step and its share of exact solves.
    """
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.control.kernel import full_sdc_matrices, structured_gains, upper_triangle
    from soft_gripper_sdre.control.kf import ConstantVelocityKF
    from soft_gripper_sdre.control.laws import SdreLaw
    from soft_gripper_sdre.learning.model import SDCModel
    from soft_gripper_sdre.control.riccati import care
    from soft_gripper_sdre.control.sdre import SdreController
    model = SDCModel()
    w = Weights(**DEFAULT_WEIGHTS)
    est, ref_pos, ref_vel = loop.est, loop.ref_pos, loop.ref_vel
    T = len(est)
    paired = set(np.linspace(1, T - 1, min(ref_steps, T - 1)).astype(int).tolist())
    x = np.concatenate([est[:, :, :2] - model.rest_tip[:2], est[:, :, 2:]], axis=2)
    blocks = [model.sdc_blocks(x[k]) for k in range(T)]
    full = [full_sdc_matrices(*b) for b in blocks]
    t: dict[str, list[float]] = {k: [] for k in ('fast', 'fast_paired', 'reference', 'nk', 'nk_paired',
                                                 'care', 'model', 'kf')}
    iterations = []
    clock = time.perf_counter
    for _ in range(repeats):
        fast = SdreLaw(model, w, 0.0625, method='fast')
        ref = SdreLaw(model, w, 0.0625, method='reference')
        s = SdreController(w.Q, w.R, 0.0625)
        p = upper_triangle(s.step_sdc(*blocks[0], x[0], x[0]).P)        # the kernel's warm start
        kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
        kf.reset(loop.meas[0])
        for k in range(T):
            args = (est[k, :, :2], est[k, :, 2:], ref_pos[k], ref_vel[k])
            t0 = clock()
            out = fast.compute(*args)
            t1 = clock()
            gains = structured_gains(*blocks[k], p, s.kernel_constants)   # the Riccati solve and checks alone
            t2 = clock()
            p = gains.p
            model.sdc_blocks(x[k])
            t3 = clock()
            kf.step(loop.meas[k])
            t4 = clock()
            if k == 0:
                continue
            iterations.append(int(out.nk_iterations.max()))
            t['fast'].append(t1 - t0)
            t['nk'].append(t2 - t1)
            t['model'].append(t3 - t2)
            t['kf'].append(t4 - t3)
            if k in paired:
                t0 = clock()
                ref.compute(*args)
                t1 = clock()
                [care(full[k][0][i], full[k][1][i], w.Q, w.R) for i in range(4)]
                t2 = clock()
                t['reference'].append(t1 - t0)
                t['care'].append(t2 - t1)
                t['fast_paired'].append(t['fast'][-1])
                t['nk_paired'].append(t['nk'][-1])
    out = {k: float(np.median(v)) for k, v in t.items()}
    out['iterations'] = float(np.mean(iterations))
    out['exact'] = float(np.mean(np.array(iterations) == 0))
    return out


def bench_idle(loop, law: str = 'sdre_ff') -> dict[str, float]:
    """The graph's law on the closed loop's states, as a node runs it: median compute [s] right
    after 1 ms of sleep (``idle``: a node waiting for its next estimate), right after sweeping
    64 MB of memory (``flushed``: other processes ran on the core meanwhile, as in the graph), and
    back to back (``busy``: as the replays above).

    Three instances of the law step through the same states, one after the other at each step, so
    all see the same warm starts and the same load.
    """
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    laws = {k: make_law(law, model, w, 0.0625, n_fingers=4) for k in ('idle', 'flushed', 'busy')}
    before = {'idle': lambda: time.sleep(1e-3), 'flushed': np.ones(8_000_000).sum, 'busy': lambda: None}
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


def bench_collect(seconds: float) -> float:
    """Real-time factor of collecting one excitation signal (finger scene, settle included)."""
    from soft_gripper_sdre.tools.collect import collect_signal
    t0 = time.perf_counter()
    collect_signal('u1', duration=seconds)
    return seconds / (time.perf_counter() - t0)


def graph_rows(quick: bool) -> list[Row]:
    """The node-graph rows, if the graph benchmark module is installed."""
    try:
        module = importlib.import_module('soft_gripper_sdre.tools.bench_graph')
    except ModuleNotFoundError as exc:
        if exc.name != 'soft_gripper_sdre.tools.bench_graph':
            raise
        return [('node graph', 'not measured', '`soft_gripper_sdre.tools.bench_graph` is not installed')]
    return list(module.rows(quick))


def rows(quick: bool) -> list[Row]:
    """Every row of the table, measured now."""
    out: list[Row] = []
    us = lambda s: f'{s * 1e6:.0f} µs'          # noqa: E731
    # simulator alone
    finger = bench_sim('finger', 1.0 if quick else 4.0, 5)
    hand = bench_sim('hand', 0.5 if quick else 2.0, 5)
    out += [('simulator step, one finger', f'{us(finger)} ({1e-3 / finger:.2f}× real time)',
             '1 ms period, 2 physics substeps; SoMo reports 6–8× for one finger'),
            ('simulator step, hand + cube', f'{us(hand)} ({1e-3 / hand:.2f}× real time)',
             f'{hand / finger:.1f}× one finger')]
    # the closed loop on the default settings (0.05 mm measurement noise), then its states replayed
    loop = closed_loop(1.0 if quick else 3.0, noise_std=5e-5)
    T = len(loop.t)
    ctrl = bench_control(loop, 1 if quick else 2, 100 if quick else 300)
    ratio = ctrl['reference'] / ctrl['fast_paired']
    out += [('controller compute, 4 fingers (fast)', us(ctrl['fast']),
             f'{ratio:.0f}× faster than the reference on the same steps; states of the closed loop below '
             f'(0.05 mm noise): {ctrl["iterations"]:.2f} Newton–Kleinman iterations per step, '
             f'{100 * ctrl["exact"]:.1f} % exact solves'),
            ('controller compute, 4 fingers (reference)', us(ctrl['reference']),
             'scipy solve_continuous_are per finger, general checks'),
            ('model A(x), G(x), 4 fingers', us(ctrl['model']), 'fused numpy network, three matmuls'),
            ('Riccati solve + checks, 4 fingers (fast)', us(ctrl['nk']),
             f'{ctrl["care"] / ctrl["nk_paired"]:.0f}× faster than scipy ×4 ({us(ctrl["care"])}), same steps'),
            ('KF step, 4 fingers', us(ctrl['kf']), 'covariance recursion remembered once settled')]
    clean = bench_control(closed_loop(1.0 if quick else 2.0, noise_std=0.0), 1, 50 if quick else 200)
    out.append(('controller compute, 4 fingers (fast), clean states', us(clean['fast']),
                f'{clean["reference"] / clean["fast_paired"]:.0f}× faster than the reference, same steps; the same '
                f'loop without measurement noise: {clean["iterations"]:.2f} iterations per step'))
    cold = bench_idle(loop)
    out.append(('controller compute, sdre_ff (the graph\'s law), cold', f'{us(cold["idle"])} / {us(cold["flushed"])}',
                f'after 1 ms of sleep / after 64 MB of other memory traffic, against {us(cold["busy"])} back '
                f'to back on the same states ({cold["idle"] / cold["busy"]:.1f}× / {cold["flushed"] / cold["busy"]:.1f}×): '
                'a node that waits for each estimate while other processes use its core runs it cold'))
    period = float(np.median(loop.period_seconds))
    out.append(('closed loop in-process (sim + KF + controller)', f'{1e-3 / period:.2f}× real time',
                f'median period {us(period)}; over the whole {T * 1e-3:.0f} s run '
                f'{T * 1e-3 / loop.step_seconds:.2f}× (load bursts included); hand + cube, 0.05 mm noise, '
                'stepping only'))
    out += graph_rows(quick)
    # training is timed by the train tool itself: a fresh `make model` run, else the shipped model's record
    trained = Path('runs/train/metrics.json')
    source = trained if trained.is_file() else Path(__file__).resolve().parents[1] / 'models' / 'default.json'
    if source.is_file():
        m = json.loads(source.read_text())
        out.append((f'training, {m["preset"]} preset ({m["epochs_run"]} epochs)',
                    f'{m["train_seconds"]:.0f} s',
                    'as measured by `make model` (runs/train/metrics.json)' if source == trained else
                    'as recorded with the shipped model (models/default.json), not re-run here'))
    collect = bench_collect(1.0 if quick else 3.0)
    out.append(('data collection, one finger', f'{collect:.2f}× real time',
                'one excitation signal with ground truth, 0.5 s settle included'))
    return out


def markdown(table: list[Row], quick: bool) -> str:
    load = os.getloadavg()[0]
    lines = ['# Benchmarks', '',
             'Reproduce: `make bench` (= `python -m soft_gripper_sdre.tools.bench --write BENCHMARKS.md`).',
             f'Measured {time.strftime("%Y-%m-%d")} on {platform.machine()}, {os.cpu_count()} cores, '
             f'Python {platform.python_version()}, a shared machine (other jobs running; load average '
             f'{load:.1f} at the end of the run)'
             + (', short runs (`--quick`)' if quick else '')
             + ': compare the ratios, which are measured in one run.', '',
             '| what | figure | note |', '| --- | ---: | --- |']
    lines += [f'| {n} | {v} | {note} |' for n, v, note in table]
    lines += ['', 'The controller, model, Riccati and KF rows replay the estimates and references of the '
              'in-process closed loop (hand + cube, default weights and 40 Hz roll-off), so the fast '
              "path's warm starts are as far off as in the loop; the first, cold step is left out. "
              'The closed-loop row times the stepping only, not the simulator\'s construction and '
              'settle; its figure is 1 ms over the median period. Training is timed by the train tool itself; data collection includes the '
              'finger\'s 0.5 s settle.']
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.bench', description=__doc__.split('\n')[0])
    ap.add_argument('--write', type=Path, default=None, help='also write the results as Markdown here')
    ap.add_argument('--quick', action='store_true', help='shorter runs (smoke test)')
    a = ap.parse_args(argv)
    from soft_gripper_sdre.learning.model import set_torch_threads
    set_torch_threads(1)
    table = rows(a.quick)
    width = max(len(r[0]) for r in table)
    for name, value, note in table:
        print(f'{name:<{width}}  {value:>28}  {note}')
    if a.write:
        a.write.write_text(markdown(table, a.quick))
        print(f'wrote {a.write}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
