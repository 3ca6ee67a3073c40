"""Benchmarks: simulator real-time factors, control-core costs, the closed loop in-process and as a graph.

    python -m soft_gripper_sdre.tools.bench [--write BENCHMARKS.md] [--quick]

Prints a table of figures and ratios measured in this run; ``--write`` also renders it as Markdown
with the machine facts and the command. Figures are medians of repeated timings; the machine is
shared, so compare ratios measured in the same run rather than absolute numbers across runs.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_time(fn, repeats: int, inner: int) -> float:
    """Median over ``repeats`` of the mean wall time of ``inner`` calls [s]."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) / inner)
    return statistics.median(samples)


def bench_sim(scene: str, seconds: float) -> float:
    """Real-time factor of the simulator alone (sim seconds per wall second), u = 0."""
    from soft_gripper_sdre.sim import GripperSim, SimConfig
    with GripperSim(SimConfig(scene=scene)) as sim:
        u = np.zeros((sim.n_fingers, 2))
        steps = int(seconds / sim.config.control_period)
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.step(u)
            sim.measure()
        return seconds / (time.perf_counter() - t0)


def bench_control(repeats: int) -> dict[str, float]:
    """µs per call: model A(x), G(x) for 4 fingers; the SDRE step fast and reference; the KF step."""
    from soft_gripper_sdre.control import DEFAULT_WEIGHTS, TrackingController, Weights
    from soft_gripper_sdre.kf import ConstantVelocityKF
    from soft_gripper_sdre.model import SDCModel
    model = SDCModel()
    rng = np.random.default_rng(0)
    pos = model.rest_tip[:2] + 2e-3 * rng.standard_normal((4, 2))
    vel = 1e-2 * rng.standard_normal((4, 2))
    ref = np.repeat(model.rest_tip[None, :2], 4, 0)
    x = np.concatenate([pos - model.rest_tip[:2], vel], axis=1)
    out = {'model A(x), G(x), 4 fingers': _median_time(lambda: model.AG(x), repeats, 200) * 1e6}
    for method in ('fast', 'reference'):
        ctrl = TrackingController(model, Weights(**DEFAULT_WEIGHTS), 0.0625, method=method)
        k = [0]

        def step():
            k[0] += 1
            ctrl.compute(pos + 1e-7 * (k[0] % 50), vel, ref, vel * 0.0)
        step()
        out[f'SDRE step, 4 fingers ({method})'] = _median_time(step, repeats, 100) * 1e6
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4)
    kf.reset(pos)
    out['KF step, 4 fingers'] = _median_time(lambda: kf.step(pos), repeats, 500) * 1e6
    return out


def bench_loop(seconds: float) -> float:
    """Real-time factor of the in-process closed loop (hand, SDRE, KF, no ROS)."""
    from soft_gripper_sdre.closed_loop import run_closed_loop
    from soft_gripper_sdre.control import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.model import SDCModel
    from soft_gripper_sdre.trajectory import GraspProfile
    t0 = time.perf_counter()
    run_closed_loop(SDCModel(), duration=seconds, weights=Weights(**DEFAULT_WEIGHTS), u_max=0.0625,
                    profile=GraspProfile(others='open'))
    return seconds / (time.perf_counter() - t0)


def bench_graph(seconds: float) -> float:
    """Real-time factor of the five-process graph in lockstep (from the demo's own timing)."""
    from soft_gripper_sdre.tools.demo import run_demo
    with tempfile.TemporaryDirectory() as tmp:
        return run_demo(Path(tmp), seconds, progress=False)['run']['real_time_factor']


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.bench', description=__doc__.split('\n')[0])
    ap.add_argument('--write', type=Path, default=None, help='also write the results as Markdown here')
    ap.add_argument('--quick', action='store_true', help='shorter runs (smoke test)')
    a = ap.parse_args(argv)
    os.environ.setdefault('OMP_NUM_THREADS', '1')
    import torch
    torch.set_num_threads(1)
    q = a.quick
    rows: list[tuple[str, str, str]] = []
    finger = bench_sim('finger', 1.0 if q else 5.0)
    hand = bench_sim('hand', 0.5 if q else 3.0)
    rows += [('simulator, one finger', f'{finger:.2f}× real time', 'SoMo reports 6–8× for one finger'),
             ('simulator, hand + cube', f'{hand:.2f}× real time', f'{finger / hand:.1f}× slower than one finger')]
    ctrl = bench_control(3 if q else 7)
    fast, ref = ctrl['SDRE step, 4 fingers (fast)'], ctrl['SDRE step, 4 fingers (reference)']
    for name, us in ctrl.items():
        note = ''
        if name.endswith('(fast)'):
            note = f'{ref / fast:.1f}× faster than scipy per step'
        rows.append((name, f'{us:.0f} µs', note))
    loop = bench_loop(0.5 if q else 2.0)
    rows.append(('closed loop in-process (sim + KF + SDRE)', f'{loop:.2f}× real time', '1 ms control period'))
    graph = bench_graph(0.5 if q else 2.0)
    rows.append(('node graph, 5 processes, lockstep', f'{graph:.2f}× real time',
                 f'{loop / graph:.1f}× slower than in-process (DDS, 4 hops per period)'))

    trained = Path('runs/train/metrics.json')
    if trained.is_file():          # training is timed by the train tool itself (`make model`)
        import json
        m = json.loads(trained.read_text())
        rows.append((f'training, {m["preset"]} preset ({m["epochs_run"]} epochs)',
                     f'{m["train_seconds"]:.0f} s', 'as measured by `make model` (runs/train/metrics.json)'))
    width = max(len(r[0]) for r in rows)
    for name, value, note in rows:
        print(f'{name:<{width}}  {value:>16}  {note}')
    if a.write:
        lines = ['# Benchmarks', '',
                 'Reproduce: `make bench` (= `python -m soft_gripper_sdre.tools.bench --write BENCHMARKS.md`).',
                 f'Measured {time.strftime("%Y-%m-%d")} on {platform.machine()}, {os.cpu_count()} cores, '
                 f'Python {platform.python_version()}, a shared machine (other jobs running): '
                 'compare the ratios, which are measured in one run.', '',
                 '| what | figure | note |', '| --- | ---: | --- |']
        lines += [f'| {n} | {v} | {note} |' for n, v, note in rows]
        a.write.write_text('\n'.join(lines) + '\n')
        print(f'wrote {a.write}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
