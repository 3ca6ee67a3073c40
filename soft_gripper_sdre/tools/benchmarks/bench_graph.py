"""Benchmarks of the node graph as processes: lockstep speed, CPU and latency, realtime lateness
(also through a CPU hog), start-up, recorder loss.

    python -m soft_gripper_sdre.tools.benchmarks.bench_graph [--quick] [--graph-only]
        [--executor events|single]

prints the rows that :mod:`soft_gripper_sdre.tools.benchmarks.bench` appends to BENCHMARKS.md
(:func:`rows`). Every figure comes from the nodes' own /diagnostics, read by a monitor node, or
from /proc (CPU time of each process while the simulator stepped):

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
import time

from soft_gripper_sdre.nodes.graph import GraphSpec, grasp_graph
from soft_gripper_sdre.tools.benchmarks.bench_hog import PHASES, SETTLE_S, CpuHog, phase_figures
from soft_gripper_sdre.tools.benchmarks.hop import hop
from soft_gripper_sdre.tools.graph.procs import (
    WIRED_BEFORE_START,
    DiagnosticsMonitor,
    Graph,
    ros_env,
)

LOOP_NODES = ('estimator', 'trajectory', 'controller')
#: topics the simulator publishes once per step when state_rate and clock_rate are 1 kHz
#: (and at t = 0)
SIM_TOPICS = ('/clock', '/tip_positions', '/joint_states', '/cube_pose', '/cube_contacts')


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a running process [s] (Linux /proc; NaN elsewhere)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')     # utime, stime


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def _numbers(values: dict[str, str]) -> dict[str, float]:
    return {k: _number(v) for k, v in values.items() if _number(v) is not None}


def published(d: dict[str, dict[str, float]]) -> dict[str, int]:
    """Topic → messages the loop published, from the nodes' diagnostics ``d``: the simulator sends
    each of its topics once per step and once at t = 0 (when they all run at 1 kHz), the others
    count what they send."""
    sim, ctrl = d.get('simulator', {}), d.get('controller', {})
    out = {t: int(sim.get('steps') or 0) + 1 for t in SIM_TOPICS}
    out['/state_estimate'] = int(d.get('estimator', {}).get('estimates') or 0)
    out['/grasp_reference'] = int(d.get('trajectory', {}).get('references') or 0)
    out['/torque_commands'] = int(ctrl.get('commands') or 0)
    return out


def run_graph(seconds: float, *, mode: str = 'lockstep', record: Path | None = None,
              all_at_1khz: bool = False, executor: str | None = None, composed: bool = False,
              timeout: float = 600.0) -> dict[str, dict[str, float]]:
    """Run the loop processes (and the recorder into ``record``) for ``seconds`` of sim time;
    ``composed``: the estimator and the controller as one process (``controller --with-estimator``),
    whose CPU time is the controller's.

    Returns every node's final /diagnostics values as floats (non-numeric values dropped), for
    each node its CPU time per step while the simulator stepped (``cpu_per_step_us``), and for the
    simulator the wall time from launching the processes to its first command (``startup_s``).

    Raises:
        RuntimeError: a node died or the run did not finish within ``timeout``.
    """
    return _graph_run(seconds, mode, record, all_at_1khz, executor, timeout, composed=composed)[0]


def hog_run(seconds: float, hog_at: float, hog_seconds: float = 1.0, executor: str | None = None,
            timeout: float = 600.0) -> dict[str, dict[str, float]]:
    """The realtime graph for ``seconds`` of sim time, with one busy process per core for
    ``hog_seconds`` of wall time from ``hog_at`` of sim time on.

    Returns :func:`~soft_gripper_sdre.tools.benchmarks.bench_hog.phase_figures` of the simulator's
    /diagnostics: for each of :data:`PHASES`, lateness and loop latency.
    """
    hog = CpuHog(hog_at, hog_seconds)
    try:
        _, history = _graph_run(seconds, 'realtime', None, False, executor, timeout,
                                during=hog.poll)
    finally:
        hog.stop()
    if hog.span is None:
        raise RuntimeError(f'the run ended before the hog started at {hog_at} s of sim time')
    return phase_figures(history.get('simulator', []), *hog.span)


def _graph_run(seconds: float, mode: str, record: Path | None, all_at_1khz: bool,
               executor: str | None, timeout: float, during=None,
               composed: bool = False) -> tuple[dict[str, dict[str, float]], dict[str, list]]:
    """:func:`run_graph`, also returning the monitor's /diagnostics history; ``during(monitor)``
    is called about 10 times a second while the simulator steps."""
    from soft_gripper_sdre.nodes.common import EXECUTOR_ENV
    env = ros_env()
    if executor is not None:
        env[EXECUTOR_ENV] = executor
    fast = {'state_rate': 1000.0, 'clock_rate': 1000.0} if all_at_1khz else {}
    params = {'estimator': {}, 'controller': {}, 'trajectory': {},
              'simulator': {'duration': seconds, 'mode': mode,
                            'min_tip_subscribers': 2 + bool(record),
                            # the monitor (+ recorder)
                            'min_diagnostics_subscribers': 1 + bool(record),
                            **fast}}
    if record:
        params['recorder'] = {'output': str(record)}
    if composed:     # the readiness rule expects a controller that reads state_estimate itself
        params['simulator']['wait_for_nodes'] = 'recorder,trajectory' if record else 'trajectory'
    spec = grasp_graph(record=bool(record), parameters=params)
    monitor = DiagnosticsMonitor(env, 'bench_monitor')
    steps = int(round(seconds / 0.001))
    try:
        cpu, launched = _run(graph_env=env, monitor=monitor, spec=spec, record=record, steps=steps,
                             timeout=timeout, during=during, composed=composed)
    finally:
        monitor.close()
    out = {node: _numbers(values) for node, values in monitor.values.items()}
    for node, seconds in cpu.items():       # CPU of the stepping only (start-up excluded)
        out.setdefault(node, {})['cpu_per_step_us'] = 1e6 * seconds / steps
    sim = out.setdefault('simulator', {})
    if 'first_command_monotonic_s' in sim:
        sim['startup_s'] = sim['first_command_monotonic_s'] - launched
    return out, monitor.history


def _run(graph_env: dict[str, str], monitor: DiagnosticsMonitor, spec: GraphSpec,
         record: Path | None, steps: int, timeout: float, during=None,
         composed: bool = False) -> tuple[dict[str, float], float]:
    """:func:`run_graph`'s processes: start, step, drain, stop; returns CPU seconds per node
    while the simulator stepped, and the monotonic time the processes were launched."""
    with (tempfile.TemporaryDirectory(prefix='sgs_bench_graph_') as logs,
          Graph(graph_env, Path(logs)) as graph):
        names = spec.names[:-1]
        launched = time.monotonic()
        for node in spec.nodes[:-1]:
            if composed and node.name == 'estimator':
                continue                    # it runs in the controller's process
            if composed and node.name == 'controller':
                _start_composed(graph, node, spec.node('estimator'))
            else:
                graph.start_node(node)
        # every node is up (its diagnostics arrive) before the simulator starts stepping
        monitor.spin_until(lambda: all(n in monitor.values for n in names)
                           or any(not p.alive() for p in graph.procs.values()), 60.0)
        dead = [n for n, p in graph.procs.items() if not p.alive()]
        if dead or not all(n in monitor.values for n in names):
            raise RuntimeError(f'the graph did not start (dead: {dead}; '
                               f'heard from {sorted(monitor.values)}): '
                               f'{ {n: graph.procs[n].log_tail(600) for n in dead} }')
        if record:       # the recorder hears every stream before the first step
            monitor.spin_until(lambda: all(monitor.get('recorder', f'publishers {t}') > 0
                                           for t in WIRED_BEFORE_START), 30.0)
        cpu0 = {n: _cpu_seconds(graph.procs[n].popen.pid) for n in names if n in graph.procs}
        graph.start_node(spec.node('simulator'))

        def poll() -> None:
            monitor.spin_until(lambda: False, 0.05)
            if during is not None:
                during(monitor)
        code = graph.wait('simulator', timeout, poll)
        cpu = {n: _cpu_seconds(graph.procs[n].popen.pid) - cpu0[n] for n in cpu0}
        if code != 0:
            tails = {n: p.log_tail(600) for n, p in graph.procs.items()}
            raise RuntimeError(f'the graph run failed (simulator exit {code}): {tails}')
        # the simulator's final diagnostics, then the others' (published at their shutdown)
        monitor.spin_until(lambda: monitor.get('simulator', 'steps') >= steps, 5.0)
        for name in ('controller', 'trajectory', 'estimator'):
            if name in graph.procs:
                graph.stop(name)
        if record:       # let a recorder that lags behind drain its queues before it is stopped
            monitor.spin_until(lambda: False, 0.5)      # the stopped nodes' final diagnostics
            sent = published({n: _numbers(monitor.values[n]) for n in ('simulator', *LOOP_NODES)
                              if n in monitor.values})
            monitor.spin_until(lambda: all(monitor.get('recorder', f'messages {t}') >= n
                                           for t, n in sent.items()), 15.0)
            graph.stop('recorder')
        monitor.spin_until(lambda: False, 0.5)
    return cpu, launched


def _start_composed(graph: Graph, controller, estimator) -> None:
    """``controller --with-estimator`` as the controller's process, the estimator node reading
    its own parameters file (and overrides)."""
    import subprocess
    import sys

    from soft_gripper_sdre.nodes.controller import WITH_ESTIMATOR
    from soft_gripper_sdre.tools.graph.procs import NodeProcess
    cmd = [sys.executable, '-m', controller.module, WITH_ESTIMATOR, *controller.ros_arguments(),
           *estimator.ros_arguments()[1:]]
    graph.log_dir.mkdir(parents=True, exist_ok=True)
    log_path = graph.log_dir / 'controller.log'
    with open(log_path, 'w', encoding='utf-8') as log:
        popen = subprocess.Popen(cmd, env=graph.env, stdout=log, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL)
    graph.procs['controller'] = NodeProcess('controller', popen, log_path)


def recorder_loss(seconds: float, executor: str | None = None,
                  mode: str = 'realtime') -> dict[str, tuple[int, int]]:
    """Topic → (messages published, messages in the bag), every topic at 1 kHz.

    The published counts are the nodes' own (:func:`published`). In ``'realtime'`` the simulator
    keeps the wall clock whatever the recorder manages (the benchmark: what a recorder loses when
    the machine cannot carry it); in ``'lockstep'`` it is paced by the loop, not by the recorder.
    """
    from soft_gripper_sdre.analysis.bag import topic_counts
    with tempfile.TemporaryDirectory(prefix='sgs_bench_bag_') as tmp:
        bag = Path(tmp) / 'bag'
        d = run_graph(seconds, mode=mode, record=bag, all_at_1khz=True, executor=executor)
        counts = topic_counts(bag)
    return {t: (n, counts.get(t, 0)) for t, n in published(d).items()}


#: the graph layouts :func:`mode_runs` can alternate: (simulator mode, estimator + controller in
#: one process), and the words of their rows
LAYOUTS = {'lockstep': ('lockstep', False, '4 processes, lockstep'),
           'pipelined': ('pipelined', False, '4 processes, pipelined'),
           'pipelined_composed': ('pipelined', True,
                                  '3 processes (controller --with-estimator), pipelined')}


def mode_runs(seconds: float, repeats: int = 1, executor: str | None = None,
              layouts: tuple[str, ...] = ('lockstep', 'pipelined')) -> dict[str, list[dict]]:
    """The graph in each of ``layouts`` (:data:`LAYOUTS`), ``seconds`` of sim time each, one after
    the other ``repeats`` times so that all meet the same load. Per layout, each run's
    :func:`run_graph` result; its simulator's values also hold the 1-minute load average at the
    run's end (``load``)."""
    runs: dict[str, list[dict]] = {name: [] for name in layouts}
    for _ in range(repeats):
        for name, done in runs.items():
            mode, composed, _ = LAYOUTS[name]
            d = run_graph(seconds, mode=mode, executor=executor, composed=composed)
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
    """The rows of :func:`mode_runs`: each layout's real-time factor (the median run, with the
    range and the loads when there are several), latency and CPU per period (a composed
    estimator's is the controller's). ``figures`` gets ``<layout>_rtf`` and ``<layout>_cpu_us``
    (every process's CPU per period, summed)."""
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
            figures[f'{mode}_cpu_us'] = sum(cpu.values())
        spread = (f'; median of {len(done)} runs taking turns with the other layouts: '
                  + ', '.join(f'{r:.2f}×' for r in rtfs) + ' at load '
                  + ', '.join(f'{r["simulator"]["load"]:.1f}'
                              for r in done)) if len(done) > 1 else ''
        out.append((f'node graph, {LAYOUTS[mode][2]} 1 ms',
                    f'{sim.get("real_time_factor", nan):.2f}× real time',
                    f'{seconds:g} s of sim time; {int(sim.get("timeouts", 0))} timeouts; '
                    f'loop latency p50 / p99 {sim.get("loop_latency_us_p50", nan):.0f} / '
                    f'{sim.get("loop_latency_us_p99", nan):.0f} µs; '
                    f'CPU per period {" / ".join(cpu)} '
                    + ' / '.join(f'{c:.0f}' for c in cpu.values())
                    + f' µs (sum {sum(cpu.values()):.0f})'
                    + spread))
    return out


def rows(quick: bool = False, executor: str | None = None, graph_only: bool = False,
         figures: dict[str, float] | None = None) -> list[tuple[str, str, str]]:
    """(what, figure, note) rows for BENCHMARKS.md. ``graph_only``: the graph runs alone, without
    the DDS hops, the SingleThreadedExecutor run and the recorder run. ``figures``, if given, gets
    the numbers the floor rows of :mod:`soft_gripper_sdre.tools.benchmarks.bench` compare: the
    lockstep and pipelined real-time factors and CPU per period (``lockstep_rtf``,
    ``pipelined_rtf``, ``lockstep_cpu_us``, ``pipelined_cpu_us``: :func:`mode_rows`) and the raw-CDR
    hop's one-way p50 [µs] (``hop_p50_us``)."""
    nan = float('nan')
    seconds, real_s = (1.0, 3.0) if quick else (3.0, 20.0)
    runs = mode_runs(seconds, 1 if quick else 3,
                     executor=executor)      # one run of each swings 0.4–0.8×
    lock_all = median_run(runs['lockstep'])
    lock = lock_all['simulator']
    pipelined_row = mode_rows(runs, seconds, figures)[1]
    real = run_graph(real_s, mode='realtime', executor=executor)['simulator']
    hog = hog_run(9.0 if quick else 14.0, 4.5 if quick else 6.0, executor=executor)
    steps = max(real.get('steps', 1.0), 1.0)
    cpu = cpu_per_period(lock_all)
    compute = lock_all['controller'].get('compute_us_mean', nan)

    def latency(d: dict, prefix: str = 'loop_latency_us') -> str:
        return ' / '.join(f'{d.get(f"{prefix}_{k}", nan):.0f}'
                          for k in ('p50', 'p99', 'max')) + ' µs'
    table = [
        ('node graph, 4 processes, lockstep 1 ms',
         f'{lock.get("real_time_factor", nan):.2f}× real time',
         f'{seconds:g} s of sim time; {int(lock.get("timeouts", 0))} timeouts'
         + (f'; median of {len(runs["lockstep"])} runs taking turns with pipelined: '
            + ', '.join(f'{r["simulator"].get("real_time_factor", nan):.2f}×'
                        for r in runs['lockstep'])
            if len(runs['lockstep']) > 1 else '')),
        pipelined_row,
        ('loop latency p50 / p99 / max, lockstep (tips out → torque back)', latency(lock),
         'measured in the simulator: 3 DDS hops + estimator + controller'),
        ('CPU per period, lockstep: simulator / estimator / trajectory / controller',
         ' / '.join(f'{c:.0f}' for c in cpu.values()) + ' µs',
         f'sum {sum(cpu.values()):.0f} µs per 1 ms period on {os.cpu_count()} cores; '
         f'controller compute {compute:.0f} µs (mean of its last second)'),
        ('start-up to the first torque, lockstep', f'{lock.get("startup_s", nan):.1f} s',
         f'from launching the 4 processes; {lock.get("first_command_after_tips_ms", nan):.0f} '
         'ms of it from the first tips to the first command'),
        (f'realtime mode at 1 kHz, {real_s:g} s: late periods',
         f'{100 * real.get("late_periods", 0.0) / steps:.1f} %',
         f'a period is late when its newest command answers tips older than the previous '
         f'period\'s; {100 * real.get("safe_periods", 0.0) / steps:.2f} % stepped with zero torque '
         f'(hold_limit); stepping at {real.get("real_time_factor", nan):.2f}× real time; '
         f'latency p50 / p99 / max {latency(real)}'),
        ('realtime with a 1 s CPU hog on every core: latency p50 before / during / after',
         ' / '.join(f'{hog[p]["p50"]:.0f}' for p in PHASES) + ' µs',
         'late periods ' + ' / '.join(f'{100 * hog[p]["late"]:.1f}' for p in PHASES) + ' %, p99 '
         + ' / '.join(f'{hog[p]["p99"]:.0f}' for p in PHASES) + f' µs; "after" from {SETTLE_S:g} s '
         'of sim time past the hog'),
    ]
    if graph_only:
        return table
    single = run_graph(seconds, executor='single')['simulator'] if executor != 'single' else lock
    ev, st = (hop(kind, 1000 if quick else 3000) for kind in ('events', 'single'))
    ev_raw = hop('events', 1000 if quick else 3000, raw=True)
    if figures is not None:
        figures['hop_p50_us'] = ev_raw['p50']
    recorded = recorder_loss(0.5 if quick else 2.0, executor=executor)
    sent = sum(n for n, _ in recorded.values())
    lost = sum(max(0, n - got) for n, got in recorded.values())
    worst = max(recorded, key=lambda t: recorded[t][0] - recorded[t][1])
    return [
        ('one DDS hop, tip_positions, EventsExecutor', f'{ev["p50"]:.0f} / {ev["p99"]:.0f} µs',
         f'p50 / p99 one way (ping-pong of 2 processes); {ev["cpu"]:.0f} µs CPU per message '
         f'received + sent'),
        ('one DDS hop, tip_positions as raw CDR (nodes/cdr.py), EventsExecutor',
         f'{ev_raw["p50"]:.0f} / {ev_raw["p99"]:.0f} µs',
         f'{ev_raw["cpu"]:.0f} µs CPU per message received, decoded, encoded and sent, '
         f'as the loop nodes do'),
        ('one DDS hop, tip_positions, SingleThreadedExecutor',
         f'{st["p50"]:.0f} / {st["p99"]:.0f} µs',
         f'{st["cpu"]:.0f} µs CPU per message: {st["cpu"] / ev["cpu"]:.1f}× the EventsExecutor\'s'),
        *table[:2],
        ('node graph, lockstep, SingleThreadedExecutor in every node',
         f'{single.get("real_time_factor", nan):.2f}× real time',
         f'rclpy\'s default executor; loop latency p50 '
         f'{single.get("loop_latency_us_p50", nan):.0f} µs'),
        *table[2:],
        ('recorder, all topics at 1 kHz: messages lost', f'{lost} of {sent}',
         '5 processes in realtime; published (node counters) − in the bag'
         + (f'; most on {worst}' if lost else '')),
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
