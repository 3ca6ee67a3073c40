"""Benchmarks: the control core's costs, the simulator, the closed loop in-process and as a graph.

    python -m soft_gripper_sdre.tools.benchmarks.bench [--write BENCHMARKS.md] [--quick]
        [--floor REPEATS]

Prints a table of (what, figure, note) rows; ``--write`` also renders it as Markdown with the
machine facts and the command. Every figure is a median over repeated timings; where two paths
compete (the compiled controller vs the scipy reference:
:mod:`soft_gripper_sdre.tools.benchmarks.bench_compute`) they are timed interleaved in the same
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

from soft_gripper_sdre.tools.benchmarks.bench_compute import (  # noqa: E402
    Row,
    bench_control,
    bench_kf,
)
from soft_gripper_sdre.tools.benchmarks.bench_compute import rows as compute_rows  # noqa: E402


def _us(seconds: float) -> str:
    return f'{seconds * 1e6:.0f} µs'


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


def compile_seconds() -> dict[str, float]:
    """Seconds for ``import control.kernels`` and ``warm_up()`` in a fresh interpreter, with an
    empty numba cache (``cold``: compiling every kernel) and again with the cache that run left
    (``cached``)."""
    code = ('import time; t0 = time.perf_counter(); '
            'from soft_gripper_sdre.control import kernels as compiled; '
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

    def period(mode: str) -> float:
        rtf = figures.get(f'{mode}_rtf', float('nan'))
        return 1e-3 / rtf if rtf > 0 else float('nan')
    lock, pipe = period('lockstep'), period('pipelined')
    cpu = figures.get('pipelined_cpu_us', float('nan'))
    return [
        ('floor of a lockstep period: physics + three rclpy hops + compute',
         f'{_us(lockstep_floor)} ({1e-3 / lockstep_floor:.2f}× real time)',
         f'physics alone {_us(hand)} (the hand + cube row), three hops {3 * hop_us:.0f} µs '
         '(3 × the raw-CDR hop\'s p50, each with its node\'s receive and send), compute '
         f'{_us(compute)} (KF + sdre_ff, back to back)'),
        ('lockstep graph period against its floor',
         f'{_us(lock)} = {lock / lockstep_floor:.2f}× the floor',
         f'1 ms / {figures.get("lockstep_rtf", float("nan")):.2f}× real time (the lockstep row); '
         'the rest is what the three processes add beyond their hop: waking up, /diagnostics, '
         'cold caches, the machine\'s other load'),
        ('floor of a pipelined period: the larger of physics and three hops + compute',
         f'{_us(pipelined_floor)} ({1e-3 / pipelined_floor:.2f}× real time)',
         f'physics {_us(hand)} beside three hops + compute {_us(hops + compute)}: '
         'the physics of t_k → t_(k+1) runs while the tips of t_k are answered; '
         f'and on {cores} cores every process\'s CPU of a period '
         f'({cpu:.0f} µs in the pipelined run) needs at least {cpu / cores:.0f} µs'),
        ('pipelined graph period against its floor',
         f'{_us(pipe)} = {pipe / pipelined_floor:.2f}× the floor',
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
    load = lambda: f'load average {os.getloadavg()[0]:.1f}'    # noqa: E731
    hand = bench_sim('hand', 0.5 if quick else 2.0, 5)
    out: list[Row] = [('simulator step, hand + cube', f'{_us(hand)} ({1e-3 / hand:.2f}× real time)',
                       load())]
    loop = default_grasp(1.0 if quick else 2.0, noise_std=5e-5)
    kf = bench_kf(loop, 1 if quick else 3)
    ctrl = bench_control(loop, 'sdre_ff', 1 if quick else 2, 20)
    out += [('KF step, 4 fingers (compiled)', _us(kf), load()),
            ('controller compute, sdre_ff, 4 fingers (compiled)', _us(ctrl['fast']),
             f'the kernel call alone {_us(ctrl["kernel"])}; {load()}')]
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


def simulator_rows(quick: bool) -> tuple[list[Row], float]:
    """The simulator's rows: one finger, the hand + cube and the hand's markers; and the hand's
    period [s], which the floor rows compare."""
    finger = bench_sim('finger', 1.0 if quick else 4.0, 5)
    hand = bench_sim('hand', 0.5 if quick else 2.0, 5)
    marker = bench_markers(5)
    return [('simulator step, one finger', f'{_us(finger)} ({1e-3 / finger:.2f}× real time)',
             '1 ms period, 2 physics substeps; SoMo reports 6–8× for one finger'),
            ('simulator step, hand + cube', f'{_us(hand)} ({1e-3 / hand:.2f}× real time)',
             f'{hand / finger:.1f}× one finger'),
            ('simulator markers, hand (one update)', _us(marker),
             'ground truth + forward kinematics + MarkerArray bytes, on a wall timer; at the '
             f'default marker_rate 10 Hz {100 * 10 * marker / (1000 * hand):.1f} % of the hand '
             "simulator's stepping at 1 kHz (publishing the 12 KB adds a DDS write)")], hand


def closed_loop_row(loop) -> Row:
    """The in-process closed loop's speed: 1 ms over its median period, and over the whole run."""
    T = len(loop.t)
    period = float(np.median(loop.period_seconds))
    return ('closed loop in-process (sim + KF + controller)', f'{1e-3 / period:.2f}× real time',
            f'median period {_us(period)}; over the whole {T * 1e-3:.0f} s run '
            f'{T * 1e-3 / loop.step_seconds:.2f}× (load bursts included); '
            'hand + cube, 0.05 mm noise, stepping only')


def startup_rows(quick: bool) -> list[Row]:
    """The start-up rows: numba's compilation from an empty cache and from the one it left (not
    with ``quick``: it takes about a minute), and the graph's start-up to its first torque."""
    out: list[Row] = []
    if not quick:
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
    return out


def training_rows() -> list[Row]:
    """Training's duration, as the train tool itself timed it: the runs of `make bench-train`
    (runs/bench_train.json, :mod:`~soft_gripper_sdre.tools.benchmarks.bench_train`), else a fresh
    `make model` run's (runs/train/metrics.json), else the shipped model's record."""
    from soft_gripper_sdre.learning.model import DEFAULT_MODEL
    from soft_gripper_sdre.tools.benchmarks import bench_train
    if bench_train.rows():
        return bench_train.rows()
    trained = Path('runs/train/metrics.json')
    source = trained if trained.is_file() else DEFAULT_MODEL.with_suffix('.json')
    if not source.is_file():
        return []
    m = json.loads(source.read_text())
    return [(f'training, {m["preset"]} preset ({m["epochs_run"]} epochs)',
             f'{m["train_seconds"]:.0f} s',
             'as measured by `make model` (runs/train/metrics.json)' if source == trained
             else 'as recorded with the shipped model (models/default.json), not re-run here')]


def rows(quick: bool) -> list[Row]:
    """Every row of the table, measured now: the simulator; the compute and the closed loop on
    the default settings (0.05 mm measurement noise), its states replayed; the node graph, each
    of its modes against its floor, the deployment loop; start-up, training, data collection."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    out, hand = simulator_rows(quick)
    loop = default_grasp(1.0 if quick else 3.0, noise_std=5e-5)
    figures: dict[str, float] = {}
    out += compute_rows(loop, quick, figures)
    out.append(closed_loop_row(loop))
    out += graph_rows(quick, figures)
    if 'hop_p50_us' in figures:
        out += floor_rows(hand, figures['hop_p50_us'], figures['kf_s'], figures['control_s'],
                          figures)
    out += deploy_rows(quick)
    out += startup_rows(quick)
    out += training_rows()
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
