"""Benchmarks: the control core's costs, the simulator, the closed loop in-process and as a graph.

    python -m soft_gripper_sdre.tools.benchmarks.bench [--write BENCHMARKS.md] [--quick]
        [--floor REPEATS]

Prints a table of (what, figure, note) rows; ``--write`` also renders it as Markdown with the
machine facts and the command. Every figure is a median over repeated timings; where two paths
compete (the compiled controller vs the scipy reference) they are timed interleaved in the same
run and their ratio is reported, since the machine is shared and absolute numbers drift. The
start-up rows time numba's compilation from an empty cache and the graph's start-up on a filled one.
The node-graph rows come from :mod:`soft_gripper_sdre.tools.benchmarks.bench_graph` when it is
installed (``rows(quick) -> [(what, figure, note)]``). ``--floor REPEATS`` measures only what the
floor rows compare (:func:`floor_table`): a few minutes instead of the whole table's hour.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
from pathlib import Path
import platform
import statistics
import subprocess
import sys
import tempfile
import time

os.environ.setdefault('OMP_NUM_THREADS', '1')  # before numpy loads BLAS: one thread, as the nodes
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


def bench_markers(repeats: int) -> float:
    """Median wall time of one update of the simulator's hand markers (its ground truth, the
    URDF's forward kinematics, the MarkerArray's CDR bytes: nodes/markers.py) [s]."""
    from soft_gripper_sdre import FINGER_NAMES
    from soft_gripper_sdre.nodes.markers import HandMarkers
    from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
    from soft_gripper_sdre.sim.hand_description import hand_urdf
    with GripperSim(SimConfig()) as sim:
        markers = HandMarkers(hand_urdf(), FINGER_NAMES, range(4))

        def update():
            truth = sim.truth()
            markers.encode(0, truth.q, truth.cube_pose)
        return _median_time(update, repeats, 50)


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
    from soft_gripper_sdre.control.compiled import (
        FeedforwardOutputs,
        SdreOutputs,
        SdreState,
        feedforward_step,
        tracking_step,
    )
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model, w = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    T, n = loop.est.shape[:2]
    acc = np.gradient(loop.ref_vel, loop.t, axis=0)            # the moving reference's acceleration
    rows = [tuple(np.ascontiguousarray(a) for a in (loop.est[k, :, :2], loop.est[k, :, 2:],
                                                    loop.ref_pos[k], loop.ref_vel[k], acc[k]))
            for k in range(T)]
    stacked = [np.concatenate(r[:4] if law == 'sdre' else r, axis=1)
               for r in rows]                               # the kernel's z
    paired = set(np.linspace(1, T - 1, min(ref_steps, T - 1)).astype(int).tolist())
    origin = np.array(model.rest_tip[:2], dtype=np.float64)
    t: dict[str, list[float]] = {k: [] for k in ('fast', 'fast_paired', 'reference', 'kernel')}
    iterations, worst, scale = [], 0.0, 0.0
    clock = time.perf_counter
    for _ in range(repeats):
        fast = make_law(law, model, w, 0.0625, n_fingers=n, method='fast')
        ref = make_law(law, model, w, 0.0625, n_fingers=n, method='reference')
        s = fast.sdre
        integral = getattr(fast, 'integral', None)
        state, out, ff = SdreState.cold(n), SdreOutputs.empty(n), FeedforwardOutputs.empty(n)
        for k, (pos, vel, ref_pos, ref_vel, ref_acc) in enumerate(rows):
            for src, dst in zip(s.state, state):
                dst[:] = src                              # the warm start the law starts from
            xi = None if integral is None else integral.xi.copy()
            t0 = clock()
            step = fast.compute(pos, vel, ref_pos, ref_vel, ref_acc=ref_acc)
            t1 = clock()
            if law == 'sdre':
                tracking_step(stacked[k], origin, *fast.network, *s.settings, *state, *out)
            else:
                feedforward_step(stacked[k], origin, False, *fast.network, *s.settings, *state,
                                 *out, *ff)
            t2 = clock()
            if k == 0:
                continue
            iterations.append(int(step.nk_iterations.max()))
            t['fast'].append(t1 - t0)
            t['kernel'].append(t2 - t1)
            if k in paired:
                if xi is not None:                        # the reference from the same integral
                    ref.integral.xi[:] = xi
                t0 = clock()
                reference = ref.compute(pos, vel, ref_pos, ref_vel, ref_acc=ref_acc)
                t['reference'].append(clock() - t0)
                t['fast_paired'].append(t['fast'][-1])
                worst = max(worst, float(np.abs(step.u_unsat - reference.u_unsat).max()))
                scale = max(scale, float(np.abs(reference.u_unsat).max()))
    result = {k: float(np.median(v)) for k, v in t.items()}
    result['iterations'] = float(np.mean(iterations))
    result['exact'] = float(np.mean(np.array(iterations) == 0))
    result['difference'] = worst / scale
    return result


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


def compile_seconds() -> dict[str, float]:
    """Seconds for ``import compiled`` and ``warm_up()`` in a fresh interpreter, with an empty numba
    cache (``cold``: compiling every kernel) and again with the cache that run left (``cached``)."""
    code = ('import time; t0 = time.perf_counter(); '
            'from soft_gripper_sdre.control import compiled; '
            't1 = time.perf_counter(); compiled.warm_up(); t2 = time.perf_counter(); '
            'print(t1 - t0, t2 - t1)')
    out = {}
    with tempfile.TemporaryDirectory(prefix='sgs_numba_cache_') as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for name in ('cold', 'cached'):
            res = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                                 text=True, check=True)
            out[f'{name} import'], out[f'{name} warm_up'] = map(float, res.stdout.split())
    return out


def graph_startup(timeout: float = 120.0) -> float:
    """Seconds from launching the four loop processes together (simulator, estimator, trajectory,
    controller, on the shipped configuration, numba's cache as it is) to the first torque command
    on ``torque_commands``, heard by a node of this process."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from soft_gripper_sdre.nodes.topics import LOOP_QOS, TORQUE_COMMANDS
    from soft_gripper_sdre.tools.graph.procs import Graph, ros_env
    env = ros_env()
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    first: list[float] = []
    context = Context()
    rclpy.init(context=context)
    node = Node('bench_startup', context=context)
    node.create_subscription(JointState, TORQUE_COMMANDS,
                             lambda _: first or first.append(time.monotonic()), LOOP_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        with (tempfile.TemporaryDirectory(prefix='sgs_startup_') as logs,
              Graph(env, Path(logs)) as graph):
            t0 = time.monotonic()
            for name in ('estimator', 'trajectory', 'controller'):
                graph.start(name)
            graph.start('simulator', {'duration': 0.5, 'min_tip_subscribers': 2})
            while (not first and time.monotonic() < t0 + timeout
                   and all(p.alive() for p in graph.procs.values())):
                executor.spin_once(timeout_sec=0.05)
            if not first:
                raise RuntimeError(f'no torque command within {timeout:g} s: '
                                   f'{ {n: p.log_tail(600) for n, p in graph.procs.items()} }')
            return first[0] - t0
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


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


def bench_collect(seconds: float) -> float:
    """Real-time factor of collecting one excitation signal (finger scene, settle included)."""
    from soft_gripper_sdre.tools.learning.collect import collect_signal
    t0 = time.perf_counter()
    collect_signal('u1', duration=seconds)
    return seconds / (time.perf_counter() - t0)


def graph_rows(quick: bool, figures: dict[str, float] | None = None) -> list[Row]:
    """The node-graph rows, if the graph benchmark module is installed (``figures``: see
    :func:`soft_gripper_sdre.tools.benchmarks.bench_graph.rows`)."""
    try:
        module = importlib.import_module('soft_gripper_sdre.tools.benchmarks.bench_graph')
    except ModuleNotFoundError as exc:
        if exc.name != 'soft_gripper_sdre.tools.benchmarks.bench_graph':
            raise
        return [('node graph', 'not measured',
                 '`soft_gripper_sdre.tools.benchmarks.bench_graph` is not installed')]
    return list(module.rows(quick, figures=figures))


def floor_rows(hand: float, hop_us: float, kf: float, control: float,
               figures: dict[str, float]) -> list[Row]:
    """Each mode of the graph against its floor, from figures of this run: the physics of a period
    ``hand`` [s], one DDS hop one way ``hop_us`` [µs], the KF and controller compute ``kf``,
    ``control`` [s], and the graph runs' ``figures``
    (:func:`soft_gripper_sdre.tools.benchmarks.bench_graph.mode_rows`).

    In strict lockstep nothing overlaps, so a period can be no shorter than the sum of the
    physics, the three hops and the compute. Pipelined, the physics of one period runs while the
    tips of the next travel the three hops and are computed on, so a period can be no shorter
    than the larger of the physics and the hops + compute (the hops and the compute follow one
    another); on ``os.cpu_count()`` cores it also needs every process's CPU of a period spread
    over them."""
    hops, compute = 3e-6 * hop_us, kf + control
    lockstep_floor = hand + hops + compute
    pipelined_floor = max(hand, hops + compute)
    cores = os.cpu_count() or 1
    us = lambda s: f'{s * 1e6:.0f} µs'          # noqa: E731

    def period(mode: str) -> float:
        rtf = figures.get(f'{mode}_rtf', float('nan'))
        return 1e-3 / rtf if rtf > 0 else float('nan')
    lock, pipe = period('lockstep'), period('pipelined')
    cpu = figures.get('pipelined_cpu_us', float('nan'))
    return [
        ('floor of a lockstep period: physics + three rclpy hops + compute',
         f'{us(lockstep_floor)} ({1e-3 / lockstep_floor:.2f}× real time)',
         f'physics alone {us(hand)} (the hand + cube row), three hops {3 * hop_us:.0f} µs (3 × the '
         f'raw-CDR hop\'s p50, each with its node\'s receive and send), compute {us(compute)} '
         '(KF + sdre_ff, back to back)'),
        ('lockstep graph period against its floor',
         f'{us(lock)} = {lock / lockstep_floor:.2f}× the floor',
         f'1 ms / {figures.get("lockstep_rtf", float("nan")):.2f}× real time (the lockstep row); '
         'the rest is what the three processes add beyond their hop: waking up, /diagnostics, '
         'cold caches, the machine\'s other load'),
        ('floor of a pipelined period: the larger of physics and three hops + compute',
         f'{us(pipelined_floor)} ({1e-3 / pipelined_floor:.2f}× real time)',
         f'physics {us(hand)} beside three hops + compute {us(hops + compute)}: '
         'the physics of t_k → t_(k+1) runs while the tips of t_k are answered; '
         f'and on {cores} cores every process\'s CPU of a period '
         f'({cpu:.0f} µs in the pipelined run) needs at least {cpu / cores:.0f} µs'),
        ('pipelined graph period against its floor',
         f'{us(pipe)} = {pipe / pipelined_floor:.2f}× the floor',
         f'1 ms / {figures.get("pipelined_rtf", float("nan")):.2f}× real time (the pipelined row); '
         f'the lockstep run\'s period is {lock / pipe:.2f}× this one'),
    ]


def floor_table(quick: bool, repeats: int) -> list[Row]:
    """The floor rows alone, measured together (``--floor``): the hand's physics, the KF and
    ``sdre_ff`` compute on the closed loop's states, the raw-CDR hop, and the graph in lockstep,
    in pipelined mode and pipelined with the estimator and the controller in one process, taking
    turns ``repeats`` times, each row with the load it ran under."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    from soft_gripper_sdre.tools.benchmarks.bench_graph import mode_rows, mode_runs
    from soft_gripper_sdre.tools.benchmarks.hop import hop
    us = lambda s: f'{s * 1e6:.0f} µs'          # noqa: E731
    load = lambda: f'load average {os.getloadavg()[0]:.1f}'    # noqa: E731
    hand = bench_sim('hand', 0.5 if quick else 2.0, 5)
    out: list[Row] = [('simulator step, hand + cube', f'{us(hand)} ({1e-3 / hand:.2f}× real time)',
                       load())]
    loop = default_grasp(1.0 if quick else 2.0, noise_std=5e-5)
    kf = bench_kf(loop, 1 if quick else 3)
    ctrl = bench_control(loop, 'sdre_ff', 1 if quick else 2, 20)
    out += [('KF step, 4 fingers (compiled)', us(kf), load()),
            ('controller compute, sdre_ff, 4 fingers (compiled)', us(ctrl['fast']),
             f'the kernel call alone {us(ctrl["kernel"])}; {load()}')]
    raw = hop('events', 1000 if quick else 3000, raw=True)
    out.append(('one DDS hop, tip_positions as raw CDR (nodes/cdr.py), EventsExecutor',
                f'{raw["p50"]:.0f} / {raw["p99"]:.0f} µs', f'p50 / p99 one way; {load()}'))
    seconds = 1.0 if quick else 3.0
    figures: dict[str, float] = {}
    out += mode_rows(mode_runs(seconds, repeats,
                               layouts=('lockstep', 'pipelined', 'pipelined_composed')),
                     seconds, figures)
    return out + floor_rows(hand, raw['p50'], kf, ctrl['fast'], figures)


def deploy_rows(quick: bool) -> list[Row]:
    """The deployment loop's rows (:mod:`soft_gripper_sdre.tools.benchmarks.bench_deploy`)."""
    from soft_gripper_sdre.tools.benchmarks.bench_deploy import rows as deploy
    return deploy(quick)


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
    marker = bench_markers(5)
    out.append(('simulator markers, hand (one update)', us(marker),
                'ground truth + forward kinematics + MarkerArray bytes, on a wall timer; at the '
                f'default marker_rate 10 Hz {100 * 10 * marker / (1000 * hand):.1f} % of the hand '
                "simulator's stepping at 1 kHz (publishing the 12 KB adds a DDS write)"))
    # the closed loop on the default settings (0.05 mm measurement noise), then its states replayed
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    loop = default_grasp(1.0 if quick else 3.0, noise_std=5e-5)
    T = len(loop.t)
    for law in ('sdre', 'sdre_ff'):
        ctrl = bench_control(loop, law, 1 if quick else 2, 100 if quick else 300)
        out += [(f'controller compute, {law}, 4 fingers (compiled)', us(ctrl['fast']),
                 f'{ctrl["reference"] / ctrl["fast_paired"]:.0f}× faster than the reference '
                 'on the same steps; states of the closed loop below (0.05 mm noise): '
                 f'{ctrl["iterations"]:.2f} Newton–Kleinman iterations per step, '
                 f'{100 * ctrl["exact"]:.1f} % exact solves; '
                 f'torques within {ctrl["difference"]:.1e} of '
                 "the largest of the reference's; the kernel call alone "
                 f'{us(ctrl["kernel"])}'),
                (f'controller compute, {law}, 4 fingers (scipy reference)', us(ctrl['reference']),
                 'scipy solve_continuous_are per finger, general checks')]
    clean = bench_control(default_grasp(1.0 if quick else 2.0, noise_std=0.0), 'sdre', 1,
                          50 if quick else 200)
    out.append(('controller compute, sdre, 4 fingers (compiled), clean states', us(clean['fast']),
                f'{clean["reference"] / clean["fast_paired"]:.0f}× faster than the reference, '
                'same steps; the same loop without measurement noise: '
                f'{clean["iterations"]:.2f} iterations per step'))
    kf = bench_kf(loop, 1 if quick else 3)
    out.append(('KF step, 4 fingers (compiled)', us(kf),
                'predict + Joseph-form update, the closed loop\'s measurements'))
    cold = bench_idle(loop)
    out.append(('controller compute, sdre_ff (the graph\'s law), cold',
                f'{us(cold["idle"])} / {us(cold["flushed"])}',
                'after 1 ms of sleep / after 64 MB of other memory traffic, '
                f'against {us(cold["busy"])} back to back on the same states '
                f'({cold["idle"] / cold["busy"]:.1f}× / {cold["flushed"] / cold["busy"]:.1f}×): '
                'a node that waits for each estimate while other processes use its core '
                'runs it cold'))
    period = float(np.median(loop.period_seconds))
    out.append(('closed loop in-process (sim + KF + controller)', f'{1e-3 / period:.2f}× real time',
                f'median period {us(period)}; over the whole {T * 1e-3:.0f} s run '
                f'{T * 1e-3 / loop.step_seconds:.2f}× (load bursts included); '
                'hand + cube, 0.05 mm noise, stepping only'))
    figures: dict[str, float] = {}
    out += graph_rows(quick, figures)
    if 'hop_p50_us' in figures:
        out += floor_rows(hand, figures['hop_p50_us'], kf, ctrl['fast'], figures)
    out += deploy_rows(quick)
    if not quick:                # compiling from an empty cache takes about a minute
        compiled = compile_seconds()
        out.append(('compiled kernels: import + warm_up(), empty cache / cached',
                    f'{compiled["cold import"] + compiled["cold warm_up"]:.1f} s / '
                    f'{compiled["cached import"] + compiled["cached warm_up"]:.1f} s',
                    'a fresh interpreter with NUMBA_CACHE_DIR empty, then again with what it left; '
                    f'of which importing numba and the kernels {compiled["cold import"]:.1f} s / '
                    f'{compiled["cached import"]:.1f} s'))
    out.append(('graph start-up (processes launched → first torque command)',
                f'{graph_startup():.1f} s',
                'simulator, estimator, trajectory, controller started together on the shipped '
                "configuration, numba's cache filled (make's kernels stamp)"))
    # training is timed by the train tool itself: a fresh `make model` run, else the shipped
    # model's record
    trained = Path('runs/train/metrics.json')
    source = (trained if trained.is_file()
              else Path(__file__).resolve().parents[1] / 'models' / 'default.json')
    if source.is_file():
        m = json.loads(source.read_text())
        out.append((f'training, {m["preset"]} preset ({m["epochs_run"]} epochs)',
                    f'{m["train_seconds"]:.0f} s',
                    'as measured by `make model` (runs/train/metrics.json)' if source == trained
                    else 'as recorded with the shipped model (models/default.json), '
                         'not re-run here'))
    collect = bench_collect(1.0 if quick else 3.0)
    out.append(('data collection, one finger', f'{collect:.2f}× real time',
                'one excitation signal with ground truth, 0.5 s settle included'))
    return out


def markdown(table: list[Row], quick: bool) -> str:
    load = os.getloadavg()[0]
    lines = ['# Benchmarks', '',
             'Reproduce: `make bench` '
             '(= `python -m soft_gripper_sdre.tools.benchmarks.bench --write BENCHMARKS.md`).',
             f'Measured {time.strftime("%Y-%m-%d")} on {platform.machine()}, {os.cpu_count()} '
             f'cores, Python {platform.python_version()}, a shared machine (other jobs running; '
             f'load average {load:.1f} at the end of the run)'
             + (', short runs (`--quick`)' if quick else '')
             + ': compare the ratios, which are measured in one run.', '',
             '| what | figure | note |', '| --- | ---: | --- |']
    lines += [f'| {n} | {v} | {note} |' for n, v, note in table]
    lines += ['', 'The controller and KF rows replay the estimates and references of the '
              'in-process closed loop (hand + cube, default weights and 40 Hz roll-off), so the '
              'fast path\'s warm starts are as far off as in the loop; the first, cold step is '
              'left out. The closed-loop row times the stepping only, not the simulator\'s '
              'construction and settle; its figure is 1 ms over the median period. '
              'Training is timed by the train tool itself; data collection includes the '
              'finger\'s 0.5 s settle.']
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.bench',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--write', type=Path, default=None,
                    help='also write the results as Markdown here')
    ap.add_argument('--quick', action='store_true', help='shorter runs (smoke test)')
    ap.add_argument('--floor', type=int, default=None, metavar='REPEATS',
                    help='only the floor rows: physics, compute, one hop, and the graph in '
                         'lockstep and pipelined mode alternating REPEATS times '
                         '(prints; --write is refused)')
    a = ap.parse_args(argv)
    if a.floor is not None and (a.floor < 1 or a.write):
        ap.error('--floor takes a number of repeats >= 1 and prints only (no --write)')
    from soft_gripper_sdre.learning.model import set_torch_threads
    set_torch_threads(1)
    table = floor_table(a.quick, a.floor) if a.floor is not None else rows(a.quick)
    width = max(len(r[0]) for r in table)
    for name, value, note in table:
        print(f'{name:<{width}}  {value:>28}  {note}')
    if a.write:
        a.write.write_text(markdown(table, a.quick))
        print(f'wrote {a.write}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
