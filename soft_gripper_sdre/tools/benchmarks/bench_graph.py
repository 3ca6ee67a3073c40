"""Benchmarks of the node graph as processes: lockstep speed, CPU and latency, realtime lateness
(also through a CPU hog), start-up, recorder loss.

    python -m soft_gripper_sdre.tools.benchmarks.bench_graph [--quick] [--graph-only]
        [--executor events|single]

prints the rows that :mod:`soft_gripper_sdre.tools.benchmarks.bench` appends to BENCHMARKS.md
(:func:`rows`). Every figure comes from the nodes' own /diagnostics, read by a monitor node, or
from /proc (CPU time of each process while the simulator stepped), of runs of
:func:`~soft_gripper_sdre.tools.benchmarks.graph_run.run_graph`:

* **lockstep**: the four loop processes (simulator, estimator, trajectory, controller) at the 1 ms
  period. The simulator reports the real-time factor of its stepping and the loop latency, the
  wall time from publishing ``tip_positions`` for t_k to receiving the torque command stamped t_k
  (three DDS hops and the estimator's and controller's work), and when the first command came:
  the start-up is measured from launching the processes to that first torque.
* **pipelined**: the same graph with the simulator's ``mode: pipelined`` (the physics of t_k →
  t_(k+1) steps with the answer to t_(k−1) while t_k is answered), right after the lockstep run,
  so both see about the same load (:func:`mode_runs` alternates them).
* **realtime**: the simulator steps on a 1 ms wall timer with its newest command; a period is
  late when that command answers tips older than the previous period's (more than one period of
  transport delay, ``late_periods``), and safe when it is older than ``hold_limit`` and zero torque
  is applied instead.
* **real-time priority**: the realtime and CPU hog rows again with the loop's processes (simulator,
  estimator, controller) under SCHED_FIFO (``grasp_graph(realtime=…)``, started behind ``chrt``).
* **CPU hog**: the same realtime graph while one busy process per core runs for a second; the
  latency and lateness of the windows before, during and after it (the simulator's
  ``recent_latency_us_*`` of each /diagnostics) show whether the loop comes back by itself.
* **recorder**: all five processes in realtime with every simulator topic at 1 kHz
  (``state_rate`` and ``clock_rate`` 1000 Hz) into the recorder; lost = messages the nodes
  published (their counters) minus the messages in the bag.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import tempfile

from soft_gripper_sdre.nodes.graph import pinning_problem
from soft_gripper_sdre.nodes.scheduling import fifo_problem
from soft_gripper_sdre.tools.benchmarks.bench_hog import PHASES, SETTLE_S, CpuHog, phase_figures
from soft_gripper_sdre.tools.benchmarks.graph_run import LOOP_NODES, published, run_graph
from soft_gripper_sdre.tools.benchmarks.hop import hop
from soft_gripper_sdre.tools.benchmarks.spread import REPEATS, LoadWatch, figure, median, span


def hog_run(seconds: float, hog_at: float, hog_seconds: float = 1.0, executor: str | None = None,
            timeout: float = 600.0, realtime: int = 0,
            cpu_latency: int | None = None) -> dict[str, dict[str, float]]:
    """The realtime graph for ``seconds`` of sim time, with one busy process per core for
    ``hog_seconds`` of wall time from ``hog_at`` of sim time on; ``realtime``: the loop's
    processes under SCHED_FIFO at that priority (0: none), holding the CPU wake-up latency at
    ``cpu_latency`` µs (None: not).

    Returns :func:`~soft_gripper_sdre.tools.benchmarks.bench_hog.phase_figures` of the simulator's
    /diagnostics: for each of :data:`PHASES`, lateness and loop latency.
    """
    hog, history = CpuHog(hog_at, hog_seconds), {}
    try:
        run_graph(seconds, mode='realtime', executor=executor, timeout=timeout, during=hog.poll,
                  history=history, realtime=realtime, cpu_latency=cpu_latency)
    finally:
        hog.stop()
    if hog.span is None:
        raise RuntimeError(f'the run ended before the hog started at {hog_at} s of sim time')
    return phase_figures(history.get('simulator', []), *hog.span)


def recorder_loss(seconds: float, executor: str | None = None,
                  mode: str = 'realtime') -> dict[str, tuple[int, int]]:
    """Topic → (messages published, messages in the bag), every topic at 1 kHz.

    The published counts are the nodes' own
    (:func:`~soft_gripper_sdre.tools.benchmarks.graph_run.published`). In ``'realtime'`` the
    simulator keeps the wall clock whatever the recorder manages (the benchmark: what a recorder
    loses when the machine cannot carry it); in ``'lockstep'`` it is paced by the loop, not by the
    recorder.
    """
    from soft_gripper_sdre.analysis.bag import topic_counts
    with tempfile.TemporaryDirectory(prefix='sgs_bench_bag_') as tmp:
        bag = Path(tmp) / 'bag'
        d = run_graph(seconds, mode=mode, record=bag, all_at_1khz=True, executor=executor)
        counts = topic_counts(bag)
    return {t: (n, counts.get(t, 0)) for t, n in published(d).items()}


#: the real-time priority the realtime rows and the ``lockstep_fifo`` layout run the loop's
#: processes at
REALTIME_PRIORITY = 50


def held_latency(priority: int) -> int | None:
    """The CPU wake-up latency [µs] the graph benchmarks hold at real-time priority ``priority``
    (0 µs; None at ordinary priority): their rows at SCHED_FIFO measure the loop waking fast."""
    return 0 if priority else None


#: the graph layouts :func:`mode_runs` can alternate: (simulator mode, estimator + controller in
#: one process, the loop's real-time priority or 0 (with the CPU wake-up latency held at 0 µs),
#: pinned to two CPUs), and the words of their rows
LAYOUTS = {'lockstep': ('lockstep', False, 0, False, '4 processes, lockstep'),
           'pipelined': ('pipelined', False, 0, False, '4 processes, pipelined'),
           'pipelined_composed': ('pipelined', True, 0, False,
                                  '3 processes (controller --with-estimator), pipelined'),
           'lockstep_fifo': ('lockstep', False, REALTIME_PRIORITY, False,
                             f'4 processes, lockstep, the loop at SCHED_FIFO {REALTIME_PRIORITY} '
                             '(CPU wake-up latency held)'),
           'lockstep_fifo_pinned': ('lockstep', False, REALTIME_PRIORITY, True,
                                    '4 processes, lockstep, at SCHED_FIFO '
                                    f'{REALTIME_PRIORITY} (CPU wake-up latency held) and pinned '
                                    '(the simulator on one CPU, the estimator and the '
                                    'controller on another)')}
#: the lockstep layouts run otherwise than the default, each also held against a floor measured
#: the same way (its hop so): layout → the words of its rows
SCHEDULED = {'lockstep_fifo': f'at SCHED_FIFO {REALTIME_PRIORITY}, the CPU wake-up latency held',
             'lockstep_fifo_pinned': f'at SCHED_FIFO {REALTIME_PRIORITY}, the CPU wake-up latency '
                                     'held, pinned to two CPUs'}


def scheduled_layouts() -> tuple[str, ...]:
    """The layouts of :data:`SCHEDULED` this user and machine can run (SCHED_FIFO permitted; two
    CPUs and taskset for the pinned one)."""
    if fifo_problem(REALTIME_PRIORITY):
        return ()
    if pinning_problem():
        return ('lockstep_fifo',)
    return tuple(SCHEDULED)


def mode_runs(seconds: float, repeats: int = 1, executor: str | None = None,
              layouts: tuple[str, ...] = ('lockstep', 'pipelined')) -> dict[str, list[dict]]:
    """The graph in each of ``layouts`` (:data:`LAYOUTS`), ``seconds`` of sim time each, one after
    the other ``repeats`` times so that all meet the same load. Per layout, each run's
    :func:`~soft_gripper_sdre.tools.benchmarks.graph_run.run_graph` result; its simulator's
    values also hold the 1-minute load average at the run's end (``load``)."""
    runs: dict[str, list[dict]] = {name: [] for name in layouts}
    for _ in range(repeats):
        for name, done in runs.items():
            mode, composed, priority, pin, _ = LAYOUTS[name]
            d = run_graph(seconds, mode=mode, executor=executor, composed=composed,
                          realtime=priority, pin=pin, cpu_latency=held_latency(priority))
            d['simulator']['load'] = os.getloadavg()[0]
            done.append(d)
    return runs


def cpu_per_period(d: dict[str, dict[str, float]]) -> dict[str, float]:
    """Each loop process's CPU time per period [µs] in the run ``d`` (:func:`run_graph`)."""
    return {n: d.get(n, {}).get('cpu_per_step_us', float('nan'))
            for n in ('simulator', *LOOP_NODES)}


def median_run(done: list[dict]) -> dict:
    """The run of median real-time factor (the lower middle one of an even count)."""
    ranked = sorted(done, key=lambda d: d['simulator'].get('real_time_factor', 0.0))
    return ranked[(len(ranked) - 1) // 2]


def mode_rows(runs: dict[str, list[dict]], seconds: float,
              figures: dict[str, float] | None = None) -> list[tuple[str, str, str]]:
    """The rows of :func:`mode_runs`: each layout's real-time factor (the median run's, with the
    min–max, every run's and the loads when there are several), latency and CPU per period (a
    composed estimator's is the controller's). ``figures`` gets ``<layout>_rtf``,
    ``<layout>_period_us`` (the mean period from the first command on, the median run's) and
    ``<layout>_cpu_us`` (every process's CPU per period, summed)."""
    nan = float('nan')
    out = []
    for mode, done in runs.items():
        d = median_run(done)
        sim = d['simulator']
        cpu = {n: c for n, c in cpu_per_period(d).items()
               if not (LAYOUTS[mode][1] and n == 'estimator')}
        rtfs = [r['simulator'].get('real_time_factor', nan) for r in done]
        if figures is not None:
            figures[f'{mode}_rtf'] = sim.get('real_time_factor', nan)
            figures[f'{mode}_period_us'] = sim.get('step_period_us', nan)
            figures[f'{mode}_cpu_us'] = sum(cpu.values())
        spread = (f'; median of {len(done)} runs taking turns with the other layouts: '
                  + ', '.join(f'{r:.2f}×' for r in rtfs) + ' at load '
                  + ', '.join(f'{r["simulator"]["load"]:.1f}'
                              for r in done)) if len(done) > 1 else ''
        out.append((f'node graph, {LAYOUTS[mode][4]} 1 ms',
                    f'{sim.get("real_time_factor", nan):.2f}× real time'
                    + (f' ({span(rtfs, digits=2)})' if len(done) > 1 else ''),
                    f'{seconds:g} s of sim time; {int(sim.get("timeouts", 0))} timeouts; '
                    f'loop latency p50 / p99 {sim.get("loop_latency_us_p50", nan):.0f} / '
                    f'{sim.get("loop_latency_us_p99", nan):.0f} µs; '
                    f'CPU per period {" / ".join(cpu)} '
                    + ' / '.join(f'{c:.0f}' for c in cpu.values())
                    + f' µs (sum {sum(cpu.values()):.0f})'
                    + spread))
    return out


def lockstep_rows(runs: dict[str, list[dict]], seconds: float) -> list[tuple[str, str, str]]:
    """The lockstep rows of :func:`mode_runs`' ``runs``: its speed (the run of median real-time
    factor, with every run's), and its latency, CPU per period and start-up, each the median
    (min–max) over the runs."""
    nan = float('nan')
    done = runs['lockstep']
    lock = median_run(done)['simulator']
    sims = [d['simulator'] for d in done]
    over = lambda key, src=sims: [v.get(key, nan) for v in src]   # noqa: E731
    cpus = [cpu_per_period(d) for d in done]
    cpu = {n: median([c[n] for c in cpus]) for n in cpus[0]}
    latency = ' / '.join(figure(over(f'loop_latency_us_{k}'), scale=1)
                         for k in ('p50', 'p99', 'max'))
    runs_of = f'median (min–max) of {len(done)} runs of {seconds:g} s'
    return [
        ('node graph, 4 processes, lockstep 1 ms',
         f'{lock.get("real_time_factor", nan):.2f}× real time'
         + (f' ({span([r["simulator"].get("real_time_factor", nan) for r in done], digits=2)})'
            if len(done) > 1 else ''),
         f'{seconds:g} s of sim time; {int(lock.get("timeouts", 0))} timeouts'
         + (f'; median of {len(done)} runs taking turns with pipelined: '
            + ', '.join(f'{r["simulator"].get("real_time_factor", nan):.2f}×' for r in done)
            if len(done) > 1 else '')),
        ('loop latency p50 / p99 / max, lockstep (tips out → torque back)', latency,
         f'{runs_of}; measured in the simulator: 3 DDS hops + estimator + controller'),
        ('CPU per period, lockstep: simulator / estimator / trajectory / controller',
         ' / '.join(f'{c:.0f}' for c in cpu.values()) + ' µs',
         f'medians of {len(done)} runs (sums {span([sum(c.values()) for c in cpus])} µs) per '
         f'1 ms period on {os.cpu_count()} cores; controller compute '
         f'{figure(over("compute_us_mean", [d["controller"] for d in done]), scale=1)} (mean '
         'of its last second)'),
        ('start-up to the first torque, lockstep', figure(over('startup_s'), 's', 1, 1),
         f'{runs_of}; from launching the 4 processes; '
         f'{median(over("first_command_after_tips_ms")):.0f} ms of it from the first tips to '
         'the first command'),
    ]


#: the realtime rows: runs, seconds of sim time per run; the hog runs' length and the hog's start
REALTIME_RUNS, REALTIME_S, HOG_S, HOG_AT = REPEATS, 6.0, 11.0, 5.0


def realtime_rows(quick: bool, executor: str | None) -> list[tuple[str, str, str]]:
    """The realtime graph's rows, measured now: its late and safe periods, and its latency
    before, during and after a CPU hog (:func:`hog_run`); each figure the median (min–max) of
    :data:`REALTIME_RUNS` runs (two short ones with ``quick``), with the loop's processes at
    ordinary scheduling and at SCHED_FIFO priority :data:`REALTIME_PRIORITY` with the CPU wake-up
    latency held (where this user may start one; the runs of the two take turns)."""
    runs = 2 if quick else REALTIME_RUNS
    real_s, hog_s, hog_at = (2.0, 9.0, 4.5) if quick else (REALTIME_S, HOG_S, HOG_AT)
    refused = fifo_problem(REALTIME_PRIORITY)
    priorities = (0,) if refused else (0, REALTIME_PRIORITY)
    load = LoadWatch()
    load.note()
    reals = {p: [] for p in priorities}
    for _ in range(runs):
        for p in priorities:
            reals[p].append(run_graph(real_s, mode='realtime', executor=executor, realtime=p,
                                      cpu_latency=held_latency(p))['simulator'])
    load.note()
    hogs = {p: [] for p in priorities}
    for _ in range(runs):
        for p in priorities:
            hogs[p].append(hog_run(hog_s, hog_at, executor=executor, realtime=p,
                                   cpu_latency=held_latency(p)))
    load.note()
    out = []
    for p in priorities:
        at = f', the loop at SCHED_FIFO {p} (CPU wake-up latency held)' if p else ''
        out += _realtime_figures(reals[p], hogs[p], at, real_s, hog_s, hog_at, load)
    if refused:
        out.append((f'realtime mode, the loop at SCHED_FIFO {REALTIME_PRIORITY}', 'not measured',
                    refused))
    return out


def _realtime_figures(reals: list[dict], hogs: list[dict], at: str, real_s: float,
                      hog_s: float, hog_at: float, load: LoadWatch) -> list[tuple[str, str, str]]:
    """The two realtime rows (:func:`realtime_rows`) of one scheduling, ``at`` naming it."""
    nan = float('nan')
    runs = len(reals)
    share = lambda d, k: 100 * d.get(k, 0.0) / max(d.get('steps', 1.0), 1.0)  # noqa: E731
    lat = {k: [d.get(f'loop_latency_us_{k}', nan) for d in reals] for k in ('p50', 'p99', 'max')}
    per = lambda key: {p: [h[p][key] for h in hogs] for p in PHASES}   # noqa: E731
    p50, p99, late = per('p50'), per('p99'), per('late')
    return [
        (f'realtime mode at 1 kHz{at}: late periods',
         figure([share(d, 'late_periods') for d in reals], '%', 1, 1),
         f'median (min–max) of {runs} runs of {real_s:g} s; a period is late when its newest '
         'command answers tips older than the previous period\'s; '
         f'{median([share(d, "safe_periods") for d in reals]):.2f} % stepped with zero torque '
         '(hold_limit); stepping at '
         f'{figure([d.get("real_time_factor", nan) for d in reals], "×", 1, 2, sep="")} real '
         f'time; latency p50 / p99 / max {figure(lat["p50"], scale=1)} / '
         f'{figure(lat["p99"], scale=1)} / {figure(lat["max"], scale=1)}; load '
         f'{load.seen[0]:.1f} → {load.seen[1]:.1f}'),
        (f'realtime with a 1 s CPU hog on every core{at}: latency p50 before / during / after',
         ' / '.join(f'{median(p50[p]):.0f}' for p in PHASES) + ' µs',
         f'medians of {runs} runs of {hog_s:g} s, the hog from {hog_at:g} s: p50 ranges '
         + ' / '.join(span(p50[p]) for p in PHASES) + ' µs; late periods '
         + ' / '.join(f'{100 * median(late[p]):.1f} ({span(late[p], 100, 1)})' for p in PHASES)
         + ' %, p99 ' + ' / '.join(f'{median(p99[p]):.0f} ({span(p99[p])})' for p in PHASES)
         + f' µs; "after" from {SETTLE_S:g} s of sim time past the hog; load '
         f'{load.seen[1]:.1f} → {load.seen[2]:.1f}'),
    ]


def hop_runs(kind: str, count: int, raw: bool = False, repeats: int = REPEATS,
             realtime: int = 0, pin: bool = False) -> dict[str, list[float]]:
    """:func:`~soft_gripper_sdre.tools.benchmarks.hop.hop` ``repeats`` times (each its own
    pair of processes, ``count`` rounds; ``realtime``: at that SCHED_FIFO priority; ``pin``: on
    two CPUs of their own; at real-time priority with the CPU wake-up latency held): per figure
    (``p50``, ``p99``, ``cpu`` [µs]) every run's."""
    runs = [hop(kind, count, raw=raw, realtime=realtime, pin=pin,
                cpu_latency=held_latency(realtime)) for _ in range(repeats)]
    return {k: [r[k] for r in runs] for k in ('p50', 'p99', 'cpu')}


def hop_rows(quick: bool, figures: dict[str, float] | None = None) -> list[tuple[str, str, str]]:
    """One DDS hop, measured now: ``tip_positions`` with the EventsExecutor, as raw CDR (also run
    as each of :func:`scheduled_layouts` runs the loop), and with the SingleThreadedExecutor; each
    the median (min–max) of :data:`REPEATS` runs of 1000 rounds (two of 300 with ``quick``), the
    kinds taking turns. ``figures``, if given, gets the raw-CDR hop's median p50 (``hop_p50_us``,
    and ``hop_<layout>_p50_us`` for each scheduled layout)."""
    count, repeats = (300, 2) if quick else (1000, REPEATS)
    kinds = {'ev': ('events', False, 0, False), 'st': ('single', False, 0, False),
             'raw': ('events', True, 0, False),
             **{k: ('events', True, *LAYOUTS[k][2:4]) for k in scheduled_layouts()}}
    got: dict[str, list[dict]] = {k: [] for k in kinds}
    for _ in range(repeats):
        for key, (kind, raw, priority, pin) in kinds.items():
            got[key].append(hop(kind, count, raw=raw, realtime=priority, pin=pin,
                                cpu_latency=held_latency(priority)))
    runs_of = {key: {k: [r[k] for r in got[key]] for k in ('p50', 'p99', 'cpu')} for key in kinds}
    ev, st, ev_raw = runs_of['ev'], runs_of['st'], runs_of['raw']
    scheduled = [k for k in kinds if k in SCHEDULED]
    if figures is not None:
        figures['hop_p50_us'] = median(ev_raw['p50'])
        figures.update({f'hop_{k}_p50_us': median(runs_of[k]['p50']) for k in scheduled})
    us = lambda xs: figure(xs, scale=1)  # noqa: E731
    runs = f'median (min–max) of {repeats} runs of {count} round trips'
    return [
        ('one DDS hop, tip_positions, EventsExecutor', f'{us(ev["p50"])} / {us(ev["p99"])}',
         f'p50 / p99 one way (ping-pong of 2 processes), {runs}; {us(ev["cpu"])} CPU per '
         'message received + sent'),
        ('one DDS hop, tip_positions as raw CDR (nodes/cdr.py), EventsExecutor',
         f'{us(ev_raw["p50"])} / {us(ev_raw["p99"])}',
         f'{runs}; {us(ev_raw["cpu"])} CPU per message received, decoded, encoded and sent, '
         'as the loop nodes do'),
        *[(f'the same, {SCHEDULED[k]}', f'{us(runs_of[k]["p50"])} / {us(runs_of[k]["p99"])}',
           f'{runs}; {us(runs_of[k]["cpu"])} CPU per message; both processes as the loop\'s run '
           'so (nodes/scheduling.py, graph.pinned_cpus)') for k in scheduled],
        ('one DDS hop, tip_positions, SingleThreadedExecutor',
         f'{us(st["p50"])} / {us(st["p99"])}',
         f'{runs}; {us(st["cpu"])} CPU per message: '
         f'{median(st["cpu"]) / median(ev["cpu"]):.1f}× the EventsExecutor\'s'),
    ]


def recorder_row(quick: bool, executor: str | None) -> tuple[str, str, str]:
    """The recorder's loss with every topic at 1 kHz in realtime, measured now
    (:func:`recorder_loss`)."""
    recorded = recorder_loss(0.5 if quick else 2.0, executor=executor)
    sent = sum(n for n, _ in recorded.values())
    lost = sum(max(0, n - got) for n, got in recorded.values())
    worst = max(recorded, key=lambda t: recorded[t][0] - recorded[t][1])
    return ('recorder, all topics at 1 kHz: messages lost', f'{lost} of {sent}',
            '5 processes in realtime; published (node counters) − in the bag'
            + (f'; most on {worst}' if lost else ''))


def rows(quick: bool = False, executor: str | None = None, graph_only: bool = False,
         figures: dict[str, float] | None = None) -> list[tuple[str, str, str]]:
    """(what, figure, note) rows for BENCHMARKS.md. ``graph_only``: the graph runs alone, without
    the DDS hops, the SingleThreadedExecutor run and the recorder run. ``figures``, if given, gets
    the numbers the floor rows of :mod:`soft_gripper_sdre.tools.benchmarks.bench` compare: the
    lockstep and pipelined real-time factors and CPU per period (``lockstep_rtf``,
    ``pipelined_rtf``, ``lockstep_cpu_us``, ``pipelined_cpu_us``: :func:`mode_rows`) and the raw-CDR
    hop's one-way p50 [µs] (``hop_p50_us``)."""
    nan = float('nan')
    seconds = 1.0 if quick else 3.0
    layouts = ('lockstep', 'pipelined', *scheduled_layouts())
    runs = mode_runs(seconds, 2 if quick else REPEATS, executor=executor,
                     layouts=layouts)      # one run of each swings 0.4–0.8×
    lock_speed, *lock_details = lockstep_rows(runs, seconds)
    others = mode_rows(runs, seconds, figures)[1:]       # pipelined, the scheduled lockstep
    graph = [*lock_details, *realtime_rows(quick, executor)]
    if graph_only:
        return [lock_speed, *others, *graph]
    singles = ([run_graph(seconds, executor='single')['simulator']
                for _ in range(2 if quick else REPEATS)] if executor != 'single'
               else [d['simulator'] for d in runs['lockstep']])
    return [
        *hop_rows(quick, figures),
        lock_speed, *others,
        ('node graph, lockstep, SingleThreadedExecutor in every node',
         figure([d.get('real_time_factor', nan) for d in singles], '× real time', 1, 2, sep=''),
         f'median (min–max) of {len(singles)} runs of {seconds:g} s; rclpy\'s default executor; '
         'loop latency p50 '
         f'{figure([d.get("loop_latency_us_p50", nan) for d in singles], scale=1)}'),
        *graph,
        recorder_row(quick, executor),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.bench_graph',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--quick', action='store_true', help='shorter runs (smoke test)')
    ap.add_argument('--graph-only', action='store_true',
                    help='only the graph runs: no DDS hops, SingleThreadedExecutor run or '
                         'recorder run')
    ap.add_argument('--executor', choices=('events', 'single'), default=None,
                    help='executor of the node processes '
                         '(default: $SOFT_GRIPPER_EXECUTOR or events)')
    a = ap.parse_args(argv)
    table = rows(a.quick, a.executor, a.graph_only)
    width = max(len(r[0]) for r in table)
    for name, value, note in table:
        print(f'{name:<{width}}  {value:>18}  {note}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
