"""Benchmarks: the control core's costs, the simulator, the closed loop in-process and as a graph.

    python -m soft_gripper_sdre.tools.benchmarks.bench [--write BENCHMARKS.md] [--quick]
        [--floor REPEATS]

Prints a table of (what, figure, note) rows; ``--write`` also renders it as Markdown with the
machine facts, the load before and after, and the command. Every timing row is the median and the
min–max of at least :data:`~soft_gripper_sdre.tools.benchmarks.spread.REPEATS` runs
(:mod:`~soft_gripper_sdre.tools.benchmarks.spread`), never the best of them; where two paths
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
import subprocess
import sys
import tempfile
import time
from typing import Sequence

os.environ.setdefault('OMP_NUM_THREADS', '1')  # before numpy loads BLAS: one thread, as the nodes
import numpy as np  # noqa: E402

from soft_gripper_sdre.tools.benchmarks.bench_compute import (  # noqa: E402
    Row,
    bench_control,
    bench_kf,
)
from soft_gripper_sdre.tools.benchmarks.bench_compute import rows as compute_rows  # noqa: E402
from soft_gripper_sdre.tools.benchmarks.spread import (  # noqa: E402
    REPEATS,
    LoadWatch,
    figure,
    median,
)
from soft_gripper_sdre.tools.benchmarks.wake import wake_rows  # noqa: E402


def _us(seconds: float) -> str:
    return f'{seconds * 1e6:.0f} µs'


def _times(fn, repeats: int, inner: int) -> list[float]:
    """Per repeat, the mean wall time of ``inner`` calls [s]."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) / inner)
    return samples


def bench_sim(scene: str, seconds: float, repeats: int) -> list[float]:
    """Per repeat (``seconds`` / ``repeats`` of sim time each), the mean wall time of one control
    period of the simulator alone (step + measure), u = 0 [s]."""
    from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
    with GripperSim(SimConfig(scene=scene)) as sim:
        u = np.zeros((sim.n_fingers, 2))
        steps = int(seconds / sim.config.control_period / repeats)

        def period():
            sim.step(u)
            sim.measure()
        return _times(period, repeats, steps)


def bench_grasp_physics(u: np.ndarray, repeats: int) -> list[float]:
    """Per repeat, the mean wall time of one control period of the hand simulator (step +
    measure) driven by ``u`` (steps, n, 2), the torques of a grasp closed in-process, from the
    settled scene: the physics of the periods the graph runs, the fingers moving and the cube
    touched (more work than the scene at rest, :func:`bench_sim`) [s]."""
    from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
    samples = []
    for _ in range(repeats):
        with GripperSim(SimConfig(scene='hand')) as sim:
            t0 = time.perf_counter()
            for u_k in u:
                sim.step(u_k)
                sim.measure()
            samples.append((time.perf_counter() - t0) / len(u))
    return samples


def bench_markers(repeats: int) -> list[float]:
    """Per repeat, the mean wall time (of 50) of one update of the simulator's hand markers (its
    ground truth, the URDF's forward kinematics, the MarkerArray's CDR bytes: nodes/markers.py)
    [s]."""
    from soft_gripper_sdre import FINGER_NAMES
    from soft_gripper_sdre.nodes.markers import HandMarkers
    from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
    from soft_gripper_sdre.sim.hand_description import hand_urdf
    with GripperSim(SimConfig()) as sim:
        markers = HandMarkers(hand_urdf(), FINGER_NAMES, range(4))

        def update():
            truth = sim.truth()
            markers.encode(0, truth.q, truth.cube_pose)
        return _times(update, repeats, 50)


def compile_seconds() -> dict[str, float]:
    """Seconds for ``import control.kernels`` and ``warm_up()`` in a fresh interpreter, with an
    empty numba cache (``cold``: compiling every kernel) and again with the cache that run left
    (``cached``): one run of each (:func:`startup_rows` repeats it)."""
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


def floor_rows(physics: float, hop_us: float, kf: float, control: float,
               figures: dict[str, float], rest: float,
               scheduled: Sequence[tuple[str, float, str]] = ()) -> list[Row]:
    """Each mode of the graph against its floor, from figures of this run: the physics of a period
    of the grasp ``physics`` [s] (:func:`bench_grasp_physics`; ``rest``: the scene at rest's),
    one DDS hop one way ``hop_us`` [µs], the KF and controller compute ``kf``, ``control`` [s],
    and the graph runs' ``figures``
    (:func:`soft_gripper_sdre.tools.benchmarks.bench_graph.mode_rows`). ``scheduled``: lockstep
    run otherwise (real-time priority, pinned), each (its words, the hop measured that way [µs],
    its layout in ``figures``), against its own floor: every part measured as it runs there.

    In strict lockstep nothing overlaps, so a period can be no shorter than the sum of the
    physics, the three hops and the compute. Pipelined, the physics of one period runs while the
    tips of the next travel the three hops and are computed on, so a period can be no shorter
    than the larger of the physics and the hops + compute (the hops and the compute follow one
    another); on ``os.cpu_count()`` cores it also needs every process's CPU of a period spread
    over them."""
    hops, compute = 3e-6 * hop_us, kf + control
    lockstep_floor = physics + hops + compute
    pipelined_floor = max(physics, hops + compute)
    cores = os.cpu_count() or 1

    def period(mode: str) -> float:
        """The run's mean period [s] from its first command on (the loop's pace, the start-up
        wait left out), or 1 ms over its real-time factor where that is not reported."""
        step_us = figures.get(f'{mode}_period_us', float('nan'))
        if step_us > 0:
            return 1e-6 * step_us
        rtf = figures.get(f'{mode}_rtf', float('nan'))
        return 1e-3 / rtf if rtf > 0 else float('nan')
    lock, pipe = period('lockstep'), period('pipelined')
    cpu = figures.get('pipelined_cpu_us', float('nan'))
    return [
        ('floor of a lockstep period: physics + three rclpy hops + compute',
         f'{_us(lockstep_floor)} ({1e-3 / lockstep_floor:.2f}× real time)',
         f'physics {_us(physics)} (the grasp\'s torques replayed; {_us(rest)} at rest), three '
         f'hops {3 * hop_us:.0f} µs '
         '(3 × the raw-CDR hop\'s p50, each with its node\'s receive and send), compute '
         f'{_us(compute)} (KF + sdre_ff, back to back)'),
        ('lockstep graph period against its floor',
         f'{_us(lock)} = {lock / lockstep_floor:.2f}× the floor',
         'the lockstep row\'s mean period from its first command on (its real-time factor, '
         f'{figures.get("lockstep_rtf", float("nan")):.2f}×, also counts the wait for that '
         'command); the rest is what the three processes add beyond their hop: waking up, '
         '/diagnostics, cold caches, the machine\'s other load'),
        ('floor of a pipelined period: the larger of physics and three hops + compute',
         f'{_us(pipelined_floor)} ({1e-3 / pipelined_floor:.2f}× real time)',
         f'physics {_us(physics)} beside three hops + compute {_us(hops + compute)}: '
         'the physics of t_k → t_(k+1) runs while the tips of t_k are answered; '
         f'and on {cores} cores every process\'s CPU of a period '
         f'({cpu:.0f} µs in the pipelined run) needs at least {cpu / cores:.0f} µs'),
        ('pipelined graph period against its floor',
         f'{_us(pipe)} = {pipe / pipelined_floor:.2f}× the floor',
         'the pipelined row\'s mean period from its first command on '
         f'({figures.get("pipelined_rtf", float("nan")):.2f}× real time over the whole run); '
         f'the lockstep run\'s period is {lock / pipe:.2f}× this one'),
    ] + [row for words, hop, layout in scheduled
         for row in _scheduled_floor_rows(words, physics + compute, hop, period(layout), lock)]


def _scheduled_floor_rows(words: str, physics_and_compute: float, hop_us: float, lock_at: float,
                          lock: float) -> list[Row]:
    """:func:`floor_rows`' two rows of lockstep run ``words`` (none without its run): the floor
    with the hop as it runs there, and the graph's period ``lock_at`` against it."""
    if not lock_at > 0:
        return []
    floor = physics_and_compute + 3e-6 * hop_us
    return [(f'floor of a lockstep period, {words}',
             f'{_us(floor)} ({1e-3 / floor:.2f}× real time)',
             f'the same physics and compute; three hops {3 * hop_us:.0f} µs (3 × the raw-CDR '
             'hop\'s p50 measured so)'),
            (f'lockstep graph period, {words}, against its floor',
             f'{_us(lock_at)} = {lock_at / floor:.2f}× the floor',
             'its lockstep row\'s mean period from its first command on; '
             f'{lock / lock_at:.2f}× as fast as lockstep at ordinary priority')]


def grasp_physics_row(loop, seconds: float, note: str = '') -> tuple[Row, float]:
    """The physics of the grasp's periods (:func:`bench_grasp_physics` on ``loop``'s torques,
    :data:`REPEATS` times), and its median [s]."""
    runs = bench_grasp_physics(loop.u, REPEATS)
    return (('simulator step, hand + cube, the grasp\'s torques',
             f'{figure(runs)}; {1e-3 / median(runs):.2f}× real time',
             f'median (min–max) of {REPEATS} replays of the {seconds:g} s the graph runs (the '
             'default grasp closed in-process, the cube touched): the physics the floor counts'
             + (f'; {note}' if note else ''))), median(runs)


def floor_table(quick: bool, repeats: int) -> list[Row]:
    """The floor rows alone, measured together (``--floor``): the hand's physics, the KF and
    ``sdre_ff`` compute on the closed loop's states, the raw-CDR hop, and the graph in lockstep,
    in pipelined mode and pipelined with the estimator and the controller in one process, taking
    turns ``repeats`` times, and what waking up costs the loop's callbacks
    (:mod:`~soft_gripper_sdre.tools.benchmarks.wake`); each row the median (min–max) of its runs,
    with the load it ran under."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    from soft_gripper_sdre.tools.benchmarks.bench_graph import (
        LAYOUTS,
        SCHEDULED,
        hop_runs,
        mode_rows,
        mode_runs,
        scheduled_layouts,
    )
    load = lambda: f'load average {os.getloadavg()[0]:.1f}'    # noqa: E731
    hands = bench_sim('hand', 0.5 if quick else 2.0, REPEATS)
    hand = median(hands)
    out: list[Row] = [('simulator step, hand + cube',
                       f'{figure(hands)}; {1e-3 / hand:.2f}× real time',
                       f'median (min–max) of {REPEATS} runs; {load()}')]
    seconds = 1.0 if quick else 3.0
    loop = default_grasp(seconds, noise_std=5e-5)
    row, physics = grasp_physics_row(loop, seconds, load())
    out.append(row)
    kf_runs: list[float] = []
    bench_kf(loop, REPEATS, kf_runs)
    ctrl = bench_control(loop, 'sdre_ff', REPEATS, 20)
    out += [('KF step, 4 fingers (compiled)', figure(kf_runs, digits=1), load()),
            ('controller compute, sdre_ff, 4 fingers (compiled)', figure(ctrl['runs']['fast']),
             f'the kernel call alone {figure(ctrl["runs"]["kernel"])}; {load()}')]
    kinds = {'': (0, False), **{k: LAYOUTS[k][2:4] for k in scheduled_layouts()}}
    hops = {k: hop_runs('events', 300 if quick else 1000, raw=True, realtime=priority, pin=pin)
            for k, (priority, pin) in kinds.items()}
    for k, raw in hops.items():
        out.append(('one DDS hop, tip_positions as raw CDR (nodes/cdr.py), EventsExecutor'
                    + (f', {SCHEDULED[k]}' if k else ''),
                    f'{figure(raw["p50"], scale=1)} / {figure(raw["p99"], scale=1)}',
                    f'p50 / p99 one way, median (min–max) of {len(raw["p50"])} runs; {load()}'))
    figures: dict[str, float] = {}
    layouts = ('lockstep', 'pipelined', 'pipelined_composed', *scheduled_layouts())
    out += mode_rows(mode_runs(seconds, repeats, layouts=layouts), seconds, figures)
    return out + floor_rows(
        physics, median(hops['']['p50']), median(kf_runs), median(ctrl['runs']['fast']), figures,
        rest=hand, scheduled=[(SCHEDULED[k], median(hops[k]['p50']), k) for k in hops if k]
    ) + wake_rows(quick)


def deploy_rows(quick: bool) -> list[Row]:
    """The deployment loop's rows (:mod:`soft_gripper_sdre.tools.benchmarks.bench_deploy`)."""
    from soft_gripper_sdre.tools.benchmarks.bench_deploy import rows as deploy
    return deploy(quick)


def simulator_rows(quick: bool) -> tuple[list[Row], float]:
    """The simulator's rows: one finger, the hand + cube and the hand's markers, each the median
    (min–max) of :data:`REPEATS` runs; and the hand's median period [s], which the floor rows
    compare."""
    finger_s, hand_s = (1.0, 0.5) if quick else (4.0, 2.0)
    fingers = bench_sim('finger', finger_s, REPEATS)
    hands = bench_sim('hand', hand_s, REPEATS)
    markers = bench_markers(REPEATS)
    finger, hand, marker = median(fingers), median(hands), median(markers)
    return [('simulator step, one finger', f'{figure(fingers)}; {1e-3 / finger:.2f}× real time',
             f'1 ms period, 2 physics substeps; {REPEATS} runs of {finger_s / REPEATS:g} s of sim '
             'time each; SoMo reports 6–8× for one finger'),
            ('simulator step, hand + cube', f'{figure(hands)}; {1e-3 / hand:.2f}× real time',
             f'{REPEATS} runs of {hand_s / REPEATS:g} s each; {hand / finger:.1f}× one finger'),
            ('simulator markers, hand (one update)', figure(markers),
             f'{REPEATS} runs of 50 updates; ground truth + forward kinematics + MarkerArray '
             'bytes, on a wall timer; at the '
             f'default marker_rate 10 Hz {100 * 10 * marker / (1000 * hand):.1f} % of the hand '
             "simulator's stepping at 1 kHz (publishing the 12 KB adds a DDS write)")], hand


def closed_loop_row(loops: list) -> Row:
    """The in-process closed loop's speed over ``loops`` (runs of it): 1 ms over each run's
    median period, and over each whole run; medians (min–max)."""
    T = len(loops[0].t)
    periods = [float(np.median(loop.period_seconds)) for loop in loops]
    whole = [len(loop.t) * 1e-3 / loop.step_seconds for loop in loops]
    speed = [1e-3 / p for p in periods]
    return ('closed loop in-process (sim + KF + controller)',
            f'{figure(speed, "× real time", 1, 2, sep="")}',
            f'median (min–max) of {len(loops)} runs of {T * 1e-3:.0f} s; median period '
            f'{figure(periods)}; over each whole run {figure(whole, "×", 1, 2, sep="")} (load '
            'bursts included); hand + cube, 0.05 mm noise, stepping only')


def startup_rows(quick: bool) -> list[Row]:
    """The start-up rows, each the median (min–max) of :data:`REPEATS` runs: numba's compilation
    from an empty cache and from the one it left (not with ``quick``: about a minute each), and
    the graph's start-up to its first torque."""
    out: list[Row] = []
    repeats = 2 if quick else REPEATS
    if not quick:
        runs = [compile_seconds() for _ in range(repeats)]
        total = {k: [r[f'{k} import'] + r[f'{k} warm_up'] for r in runs] for k in ('cold',
                                                                                   'cached')}
        imports = {k: [r[f'{k} import'] for r in runs] for k in ('cold', 'cached')}
        out.append(('compiled kernels: import + warm_up(), empty cache / cached',
                    f'{figure(total["cold"], "s", 1, 1)} / {figure(total["cached"], "s", 1, 1)}',
                    f'median (min–max) of {repeats} runs; a fresh interpreter with '
                    'NUMBA_CACHE_DIR empty, then again with what it left; of which importing '
                    f'numba and the kernels {figure(imports["cold"], "s", 1, 1)} / '
                    f'{figure(imports["cached"], "s", 1, 1)}'))
    starts = [graph_startup() for _ in range(repeats)]
    out.append(('graph start-up (processes launched → first torque command)',
                figure(starts, 's', 1, 1),
                f'median (min–max) of {repeats} runs; simulator, estimator, trajectory, '
                "controller started together on the shipped configuration, numba's cache filled "
                "(make's kernels stamp)"))
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


def rows(quick: bool, load: LoadWatch | None = None) -> list[Row]:
    """Every row of the table, measured now: the simulator; the compute and the closed loop on
    the default settings (0.05 mm measurement noise), its states replayed; the node graph, each
    of its modes against its floor, the deployment loop; start-up, training, data collection.
    ``load`` notes the load average before and after."""
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    load = load or LoadWatch()
    load.note()
    out, hand = simulator_rows(quick)
    loops = [default_grasp(1.0 if quick else 3.0, noise_std=5e-5)
             for _ in range(2 if quick else REPEATS)]
    figures: dict[str, float] = {}
    row, physics = grasp_physics_row(loops[0], 1.0 if quick else 3.0)
    out.append(row)
    out += compute_rows(loops[0], quick, figures)
    out.append(closed_loop_row(loops))
    del loops[1:]
    out += graph_rows(quick, figures)
    if 'hop_p50_us' in figures:
        from soft_gripper_sdre.tools.benchmarks.bench_graph import SCHEDULED
        out += floor_rows(physics, figures['hop_p50_us'], figures['kf_s'], figures['control_s'],
                          figures, rest=hand,
                          scheduled=[(words, figures[f'hop_{k}_p50_us'], k)
                                     for k, words in SCHEDULED.items()
                                     if f'hop_{k}_p50_us' in figures])
    out += wake_rows(quick)
    out += deploy_rows(quick)
    out += startup_rows(quick)
    out += training_rows()
    collects = [bench_collect(1.0 if quick else 3.0) for _ in range(2 if quick else REPEATS)]
    out.append(('data collection, one finger', figure(collects, '× real time', 1, 2, sep=''),
                f'median (min–max) of {len(collects)} runs; one excitation signal of '
                f'{1.0 if quick else 3.0:g} s with ground truth, 0.5 s settle included'))
    load.note()
    return out


def markdown(table: list[Row], quick: bool, load: LoadWatch | None = None) -> str:
    lines = ['# Benchmarks', '',
             'Reproduce: `make bench` '
             '(= `python -m soft_gripper_sdre.tools.benchmarks.bench --write BENCHMARKS.md`).',
             f'Measured {time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())} on '
             f'{platform.machine()}, {os.cpu_count()} cores, Python '
             f'{platform.python_version()}, a shared machine (other jobs running; 1-minute load '
             f'average {(load or LoadWatch([os.getloadavg()[0]])).text().removeprefix("load ")} '
             'from the start to the end of the run)'
             + (', short runs (`--quick`)' if quick else '')
             + '. Every timing is the median of at least five runs with their min–max in '
             'brackets (`tools/benchmarks/spread.py`), never the best run; the note says how '
             'long each run is. Compare the ratios, which are measured in one run.', '',
             '| what | figure | note |', '| --- | ---: | --- |']
    lines += [f'| {n} | {v} | {note} |' for n, v, note in table]
    lines += ['', 'The controller and KF rows replay the estimates and references of the '
              'in-process closed loop (hand + cube, default weights and 40 Hz roll-off), so the '
              'fast path\'s warm starts are as far off as in the loop; the first, cold step is '
              'left out. The closed-loop row times the stepping only, not the simulator\'s '
              'construction and settle; its figure is 1 ms over the median period. '
              'Training is timed by the train tool itself; data collection includes the '
              'finger\'s 0.5 s settle.', '',
              'The deployment rows (`soft_gripper_sdre.tools.benchmarks.bench_deploy`) run a '
              'driver stand-in (tips from prebuilt CDR bytes on an absolute wall-clock schedule, '
              'the commands timed by their stamps) with the estimator, the trajectory node and '
              'the controller, each run a 2 s warm-up and then the measured seconds its note '
              'gives, the configurations taking turns run by run; every figure is the median '
              'over the runs, the late share and the p99 with their min–max. CPU per period is '
              'each process\'s `/proc/<pid>/schedstat` over the measured window. "One process" '
              'is `controller --with-estimator` '
              '([docs/performance.md](docs/performance.md#the-deployment-loop)); what makes a '
              'period late, measured inside the processes (`bench_deploy --probe DIR`), is in '
              '[docs/performance.md](docs/performance.md#what-makes-a-period-late).']
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.bench',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--write', type=Path, default=None,
                    help='also write the results as Markdown here')
    ap.add_argument('--quick', action='store_true', help='shorter runs (smoke test)')
    ap.add_argument('--floor', type=int, default=None, const=REPEATS, metavar='REPEATS', nargs='?',
                    help='only the floor rows: physics, compute, one hop, and the graph in '
                         'lockstep and pipelined mode alternating REPEATS times '
                         '(prints; --write is refused)')
    a = ap.parse_args(argv)
    if a.floor is not None and (a.floor < 1 or a.write):
        ap.error('--floor takes a number of repeats >= 1 and prints only (no --write)')
    from soft_gripper_sdre.learning.model import set_torch_threads
    set_torch_threads(1)
    load = LoadWatch()
    table = floor_table(a.quick, a.floor) if a.floor is not None else rows(a.quick, load)
    width = max(len(r[0]) for r in table)
    for name, value, note in table:
        print(f'{name:<{width}}  {value:>28}  {note}')
    if a.write:
        a.write.write_text(markdown(table, a.quick, load))
        print(f'wrote {a.write}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
