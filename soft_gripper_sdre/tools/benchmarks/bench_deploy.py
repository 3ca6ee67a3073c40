"""The deployment loop's benchmark: a minimal driver stand-in with the estimator and the controller.

    python -m soft_gripper_sdre.tools.benchmarks.bench_deploy [--quick] [--seconds S] [--repeats N]
        [--rate 1000 500] [--variants base shm composed ...]

On a robot the simulator is replaced by the robot's driver, a light process that publishes the
measured tips every period and applies the newest command. This benchmark puts the cheapest such
driver we can write in Python in that place, so what it measures is the estimator, the
controller and rclpy/Fast DDS between them:

* **the driver** (its own process: :mod:`soft_gripper_sdre.tools.benchmarks.deploy_driver`)
  publishes ``tip_positions`` on an absolute wall-clock schedule (1 kHz or 500 Hz) from CDR bytes
  built before the run (no message object, no serialization per period: as cheap as a C++
  driver's publisher), and takes ``torque_commands`` as raw bytes, reading only each command's
  stamp. The tips are the measured tips of the in-process closed loop (hand + cube, 0.05 mm
  noise, the default grasp), replayed, so the estimator and the controller see the states and the
  Newton–Kleinman iterations of the real grasp; they are stamped k·period from 0, as the
  simulator stamps them.
* **the graph**: the estimator, the trajectory node (the plan, once) and the controller as
  separate processes on their shipped parameters (``control_period`` = the driver's period),
  optionally the recorder (all topics into an MCAP bag), or the estimator and the controller
  composed in one process (``controller --with-estimator``).

Per run, over the periods after a warm-up: **late periods** (at the driver's tick k the newest
command answers tips older than k − 1, the simulator's realtime rule; a tick whose command never
came counts too), **latency** tips out → the command with the same stamp back, p50 / p99 / max,
and **CPU per period** of each process from ``/proc/<pid>/schedstat`` (nanoseconds on a CPU, all
threads) over the same window. The variants change one thing each (environment, composition,
scheduling); see :data:`VARIANTS`.
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager
from dataclasses import replace
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Iterator

import numpy as np

from soft_gripper_sdre.nodes import scheduling
from soft_gripper_sdre.nodes.graph import (
    NodeSpec,
    cpus_prefix,
    default_params_file,
    pinned_cpus,
    pinning_problem,
    realtime_prefix,
)
from soft_gripper_sdre.tools.benchmarks.deploy_driver import driver
from soft_gripper_sdre.tools.benchmarks.graph_run import measured_env
from soft_gripper_sdre.tools.benchmarks.loop_probe import late_causes, probe_env
from soft_gripper_sdre.tools.benchmarks.spread import REPEATS, median, span
from soft_gripper_sdre.tools.graph.procs import Graph

#: periods before the measured window: discovery, the plan, the first cold steps
WARMUP_S = 2.0
#: the estimator's and the controller's start-up log lines begin so (their kernels are loaded)
ESTIMATOR_UP, CONTROLLER_UP = ']: 4 fingers (', ']: model '
#: variant → (what it changes, environment additions, options)
VARIANTS: dict[str, tuple[str, dict[str, str], dict]] = {
    'base': ('separate processes, shipped settings', {}, {}),
    'shm': ('Fast DDS shared memory only (FASTDDS_BUILTIN_TRANSPORTS=SHM)',
            {'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'}, {}),
    'sync': ('Fast DDS synchronous publication (RMW_FASTRTPS_PUBLICATION_MODE=SYNCHRONOUS)',
             {'RMW_FASTRTPS_PUBLICATION_MODE': 'SYNCHRONOUS'}, {}),
    'composed': ('estimator + controller in one process, one executor', {}, {'composed': True}),
    'pinned': ('the estimator and the controller on one CPU (as deploy --cpu), the driver on '
               'another (graph.pinned_cpus, the driver in the simulator\'s place; both started '
               'behind taskset)', {}, {'pinned': True}),
    'fifo': ('estimator, controller and driver at SCHED_FIFO priority 50 (started behind chrt -f '
             '50)', {}, {'fifo': 50}),
    'hold': ('the processes at real-time priority holding the CPU wake-up latency at 0 µs '
             f'({scheduling.CPU_LATENCY_ENV}=0)', {scheduling.CPU_LATENCY_ENV: '0'}, {}),
    'loop_nice': ('estimator, controller and driver at nice -10', {}, {'loop_nice': -10}),
    'hog': ('a busy machine: a CPU-bound process per core beside the loop, at nice 0', {},
            {'hog': True}),
    'recorder_nice': ('the recorder at nice 10', {}, {'recorder_nice': 10}),
    'recorder_batch': ('the recorder under SCHED_BATCH (no wake-up preemption)', {},
                       {'recorder_batch': True}),
}


def variant_settings(name: str) -> tuple[str, dict[str, str], dict]:
    """The variant ``name``, or several joined by '+' (``composed+fifo``): their descriptions,
    environments and options together."""
    parts = [VARIANTS[part] for part in name.split('+')]
    env = {k: v for _, e, _ in parts for k, v in e.items()}
    options = {k: v for _, _, o in parts for k, v in o.items()}
    return '; '.join(what for what, _, _ in parts), env, options


# -- the run ------------------------------------------------------------------------------------

def replay_tips(seconds: float, path: Path) -> Path:
    """The measured tips (n, 3 with z = 0) of ``seconds`` of the in-process closed loop, every
    1 ms, saved to ``path`` (.npy) unless it holds them already."""
    if path.is_file():
        return path
    from soft_gripper_sdre.analysis.closed_loop import default_grasp
    meas = default_grasp(seconds, noise_std=5e-5).meas
    tips = np.concatenate([meas, np.zeros(meas.shape[:2] + (1,))], axis=2)
    np.save(path, tips)
    return path


def _threads(pid: int) -> list[int]:
    try:
        return [int(t) for t in os.listdir(f'/proc/{pid}/task')]
    except OSError:
        return []


def _renice(pid: int, nice: int = 0, batch: bool = False) -> None:
    """Every thread of ``pid`` at ``nice``, and under SCHED_BATCH if ``batch``."""
    for tid in _threads(pid):
        try:
            if batch:
                os.sched_setscheduler(tid, os.SCHED_BATCH, os.sched_param(0))
            if nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError:
            pass


@contextmanager
def _hogs(on: bool) -> Iterator[None]:
    """While the block runs, a CPU-bound process per core at nice 0 (``on``), killed after."""
    procs = ([subprocess.Popen([sys.executable, '-c', 'while True: pass'])
              for _ in range(os.cpu_count() or 1)] if on else [])
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def _spec(name: str, parameters: dict, realtime: int = 0,
          cpus: dict[str, int] | None = None) -> NodeSpec:
    """The node ``name`` on its default parameter file and ``parameters``; at SCHED_FIFO
    ``realtime``; on its CPU of ``cpus`` (:func:`~soft_gripper_sdre.nodes.graph.pinned_cpus`;
    None: anywhere)."""
    return NodeSpec(name, name, params_file=default_params_file(name), parameters=parameters,
                    realtime=realtime, cpus=(cpus[name],) if cpus else ())


def loop_specs(timing: dict, options: dict, cpus: dict[str, int] | None) -> list[NodeSpec]:
    """The loop's processes for a variant's ``options``: the estimator and the controller (one
    process when composed) at its real-time priority and on their CPU of ``cpus``, and the
    trajectory node, which is left to the scheduler as ``deploy --cpu`` leaves it (idle once it
    has planned; docs/performance.md "Cores")."""
    fifo = options.get('fifo', 0)
    if options.get('composed'):
        loop = [replace(_spec('controller', timing, fifo, cpus),
                        hosted=(_spec('estimator', timing),))]
    else:
        loop = [_spec('estimator', timing, fifo, cpus), _spec('controller', timing, fifo, cpus)]
    return loop + [_spec('trajectory', {})]


def driver_prefix(options: dict, cpus: dict[str, int] | None) -> list[str]:
    """The driver stand-in's command prefix: on the simulator's CPU of ``cpus`` (the plant's
    place), at the variant's real-time priority."""
    return [*cpus_prefix((cpus['simulator'],) if cpus else ()),
            *realtime_prefix(options.get('fifo', 0))]


def run_deploy(period: float, seconds: float, tips: Path, *, record: bool = False,
               variant: str = 'base', warmup: float = WARMUP_S, probe: Path | None = None
               ) -> dict:
    """One run of the deployment loop (see the module doc); returns
    :func:`~soft_gripper_sdre.tools.benchmarks.deploy_driver.driver`'s figures plus
    ``variant``, ``rate_hz``, ``record``, ``load`` (the 1-minute load average at the end) and
    ``load_before`` (at the start). ``probe``: every process of the run records its timestamps
    there (:mod:`~soft_gripper_sdre.tools.benchmarks.loop_probe`)."""
    _, extra_env, options = variant_settings(variant)
    env = measured_env() | extra_env
    if probe is not None:
        env = probe_env(env, probe)
    load_before = os.getloadavg()[0]
    timing = {'control_period': float(period)}
    fifo = options.get('fifo', 0)
    cpus = pinned_cpus() if options.get('pinned') else None
    with tempfile.TemporaryDirectory(prefix='sgs_bench_deploy_') as tmp, \
            Graph(env, Path(tmp) / 'logs') as graph:
        if record:
            graph.start_node(_spec('recorder', {'output': str(Path(tmp) / 'bag')}))
        for spec in loop_specs(timing, options, cpus):
            graph.start_node(spec)
        loop = [n for n in ('estimator', 'controller') if n in graph.procs]
        _wait_ready(graph, {'controller': (ESTIMATOR_UP, CONTROLLER_UP)} if options.get('composed')
                    else {'estimator': (ESTIMATOR_UP,), 'controller': (CONTROLLER_UP,)})
        pids = {name: proc.popen.pid for name, proc in graph.procs.items()}
        granted = all(scheduling.realtime(pids[name]) for name in loop)
        if record and (options.get('recorder_nice') or options.get('recorder_batch')):
            _renice(pids['recorder'], options.get('recorder_nice', 0),
                    options.get('recorder_batch', False))
        readers = 2 + record
        cmd = [*driver_prefix(options, cpus), sys.executable, '-m',
               'soft_gripper_sdre.tools.benchmarks.bench_deploy', '--driver',
               json.dumps({'period': period, 'warmup': warmup, 'seconds': seconds,
                           'tips': str(tips), 'readers': readers, 'pids': pids})]
        with _hogs(options.get('hog', False)):
            drv = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True)
            if options.get('loop_nice'):
                time.sleep(1.0)
                for pid in [pids[name] for name in loop] + [drv.pid]:
                    _renice(pid, options['loop_nice'])
            out, err = drv.communicate(timeout=warmup + seconds + 120.0)
        if drv.returncode != 0:
            tails = {n: p.log_tail(800) for n, p in graph.procs.items()}
            raise RuntimeError(f'the driver failed ({drv.returncode}): {err[-2000:]}\n{tails}')
    result = json.loads(out.strip().splitlines()[-1])
    result.update(variant=variant, rate_hz=round(1.0 / period), record=record,
                  load=os.getloadavg()[0], load_before=load_before)
    if fifo:
        result['fifo_granted'] = granted
    return result


def _wait_ready(graph: Graph, ready: dict[str, tuple[str, ...]], timeout: float = 120.0) -> None:
    """Until every process of ``ready`` has logged each of its words (the nodes' start-up lines,
    written once the kernels are loaded)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        dead = [n for n, p in graph.procs.items() if not p.alive()]
        if dead:
            raise RuntimeError(f'{dead} exited: {[graph.procs[n].log_tail(800) for n in dead]}')
        if all(all(w in graph.procs[n].log_tail(100_000) for w in words)
               for n, words in ready.items()):
            return
        time.sleep(0.1)
    raise RuntimeError(f'not ready within {timeout:g} s: '
                       f'{[graph.procs[n].log_tail(800) for n in ready]}')


# -- the table ----------------------------------------------------------------------------------

def summary(runs: list[dict]) -> dict:
    """Repeated runs of one configuration: each figure's median over the runs (``late_pct``,
    ``latency_*``, ``cpu_us``), the runs' figures (``runs_late``, ``runs_p99``) and the loads
    (``loads``: before the first run, after each run)."""
    first = runs[0]
    med = lambda key: median([r[key] for r in runs])    # noqa: E731
    cpu = {name: median([r['cpu_us'].get(name, float('nan')) for r in runs])
           for name in first['cpu_us']}
    return {'rate_hz': first['rate_hz'], 'variant': first['variant'], 'record': first['record'],
            'periods': first['periods'], 'seconds': first['periods'] / first['rate_hz'],
            'late_pct': med('late_pct'), 'slow_pct': med('slow_pct'),
            'latency_p50': med('latency_p50'),
            'latency_p99': med('latency_p99'), 'latency_max': med('latency_max'), 'cpu_us': cpu,
            'runs_late': [r['late_pct'] for r in runs], 'runs_slow': [r['slow_pct'] for r in runs],
            'runs_p99': [r['latency_p99'] for r in runs],
            'loads': [round(first.get('load_before', first['load']), 1)]
            + [round(r['load'], 1) for r in runs], 'repeats': len(runs)}


def describe(s: dict) -> tuple[str, str, str]:
    """(what, figure, note) of a :func:`summary`: the medians, the late share's and the p99's
    min–max over the runs, and the load."""
    cpu = s['cpu_us']
    loop = [n for n in ('estimator', 'controller') if n in cpu]
    parts = ' + '.join(f'{n} {cpu[n]:.0f}' for n in loop)
    total = sum(cpu[n] for n in loop)
    what = (f'deployment loop at {s["rate_hz"]} Hz, {variant_settings(s["variant"])[0]}'
            + (', with the recorder' if s['record'] else ''))
    figure = (f'{s["late_pct"]:.2f} % late ({span(s["runs_late"], digits=2)}), the loop\'s own '
              f'{s["slow_pct"]:.2f} % ({span(s["runs_slow"], digits=2)}); '
              f'{s["latency_p50"]:.0f} / {s["latency_p99"]:.0f} ({span(s["runs_p99"])}) / '
              f'{s["latency_max"]:.0f} µs')
    note = (f'median (min–max) of {s["repeats"]} runs of {s["seconds"]:g} s '
            f'({s["periods"]} periods) each: late share at the driver\'s tick, and of the loop '
            f'alone (round trips longer than a period); latency p50 / p99 / max; CPU per period '
            f'{parts} = {total:.0f} µs'
            + (f', recorder {cpu["recorder"]:.0f}' if 'recorder' in cpu else '')
            + f', driver {cpu["driver"]:.0f} µs; load {s["loads"][0]} before, '
            f'{s["loads"][1:]} after each run')
    return what, figure, note


def measure(rates: list[int], variants: list[str], seconds: float, repeats: int,
            record_too: bool | str, tips: Path, echo=print, probe: Path | None = None
            ) -> list[dict]:
    """:func:`summary` of ``repeats`` runs of every rate × variant × (recorder or not;
    ``record_too='only'``: with the recorder only). The
    repeats go round all the configurations in turn, so a load that drifts meets each alike.
    ``probe``: each run records its processes' timestamps in a directory of its own there, and
    its :func:`~soft_gripper_sdre.tools.benchmarks.loop_probe.late_causes` are echoed and kept
    (``causes``)."""
    configs = [(rate, v, record) for rate in rates for v in variants
               for record in ((False, True) if record_too is True
                              else (True,) if record_too == 'only' else (False,))]
    runs: dict[tuple, list[dict]] = {c: [] for c in configs}
    for i in range(repeats):
        for rate, v, record in configs:
            where = (None if probe is None
                     else probe / f'{rate}-{v}{"-recorder" if record else ""}-{i}')
            run = run_deploy(1.0 / rate, seconds, tips, record=record, variant=v, probe=where)
            if where is not None:
                run['causes'] = late_causes(where)
            runs[rate, v, record].append(run)
            echo(json.dumps(run))
    out = [summary(runs[c]) for c in configs]
    for s in out:
        echo(' | '.join(describe(s)))
    return out


#: the layouts :func:`rows` measures: the shipped one, the composed one, and the composed one at
#: real-time priority (where this user may start one), with the CPU wake-up latency held and
#: without, and pinned (``deploy --cpu``) with it
ROW_VARIANTS = ('base', 'composed', 'composed+fifo+hold', 'composed+fifo',
                'composed+fifo+hold+pinned')
#: the busy machine's rows: the composed loop at 1 kHz with a CPU-bound process on every core,
#: at ordinary and at real-time priority
HOG_VARIANTS = ('composed+hog', 'composed+fifo+hold+hog')
#: the runs per configuration of :func:`rows`, and the measured seconds of each (after the warm-up)
ROW_REPEATS, ROW_SECONDS = REPEATS, 6.0


def rows(quick: bool = False) -> list[tuple[str, str, str]]:
    """The deployment rows of BENCHMARKS.md: each of :data:`ROW_VARIANTS` at 1 kHz and 500 Hz,
    with and without the recorder, then :data:`HOG_VARIANTS` at 1 kHz without it; the median and
    min–max of :data:`ROW_REPEATS` runs of :data:`ROW_SECONDS` each (one short run with
    ``quick``). Without permission for SCHED_FIFO its rows say why instead."""
    seconds = 3.0 if quick else ROW_SECONDS
    repeats = 1 if quick else ROW_REPEATS
    refused = scheduling.fifo_problem(50)
    unpinned = pinning_problem()
    variants = [v for v in ROW_VARIANTS
                if not (refused and 'fifo' in v) and not (unpinned and 'pinned' in v)]
    hogs = [v for v in HOG_VARIANTS if not (refused and 'fifo' in v)]
    with tempfile.TemporaryDirectory(prefix='sgs_deploy_tips_') as tmp:
        tips = replay_tips(WARMUP_S + seconds + 1.0, Path(tmp) / 'tips.npy')
        table = measure([1000, 500], variants, seconds, repeats, True, tips, echo=lambda _: None)
        table += measure([1000], hogs, seconds, repeats, False, tips, echo=lambda _: None)
    out = [describe(s) for s in table]
    if refused:
        out.append(('deployment loop at SCHED_FIFO priority 50', 'not measured', refused))
    if unpinned:
        out.append(('deployment loop pinned (deploy --cpu)', 'not measured', unpinned))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.bench_deploy',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--driver', default=None, help=argparse.SUPPRESS)     # the driver process
    ap.add_argument('--quick', action='store_true', help='short runs, once each')
    ap.add_argument('--seconds', type=float, default=None, help='measured seconds per run')
    ap.add_argument('--repeats', type=int, default=None, help='runs per configuration')
    ap.add_argument('--rate', type=int, nargs='+', default=[1000, 500], help='driver rates [Hz]')
    ap.add_argument('--variants', nargs='+', default=list(ROW_VARIANTS),
                    help=f'any of {", ".join(VARIANTS)}, or several joined by + (composed+fifo)')
    ap.add_argument('--no-recorder', action='store_true', help='only the runs without recorder')
    ap.add_argument('--only-recorder', action='store_true', help='only the runs with the recorder')
    ap.add_argument('--tips', type=Path, default=None, help='cache of the replayed tips (.npy)')
    ap.add_argument('--probe', type=Path, default=None, metavar='DIR',
                    help='record timestamps inside every process of each run under DIR and '
                         'print what made its late periods late (tools/benchmarks/loop_probe.py)')
    a = ap.parse_args(argv)
    if a.probe is not None and a.probe.exists() and not a.probe.is_dir():
        ap.error(f'--probe {a.probe}: not a directory')
    if (a.repeats is not None and a.repeats < 1) or (a.seconds is not None and a.seconds <= 0):
        ap.error('--repeats takes a count >= 1 and --seconds a duration > 0')
    if a.driver is not None:
        d = json.loads(a.driver)
        result = driver(d['period'], d['warmup'], d['seconds'], Path(d['tips']), d['readers'],
                        d['pids'])
        print(json.dumps(result), flush=True)
        return 0
    seconds = a.seconds or (3.0 if a.quick else ROW_SECONDS)
    repeats = a.repeats or (1 if a.quick else ROW_REPEATS)
    with tempfile.TemporaryDirectory(prefix='sgs_deploy_tips_') as tmp:
        tips = a.tips or Path(tmp) / 'tips.npy'
        replay_tips(WARMUP_S + seconds + 1.0, tips)
        measure(a.rate, a.variants, seconds, repeats,
                'only' if a.only_recorder else not a.no_recorder, tips, probe=a.probe)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
