"""Several hands on one ROS domain: one grasp graph per namespace, all running at once.

    python -m soft_gripper_sdre.tools.graph.hands --hands left_hand right_hand --duration 6
        --out runs/hands

starts, for each hand, the graph of :func:`soft_gripper_sdre.nodes.graph.grasp_graph` in its own
namespace (five processes: recorder, estimator, trajectory, controller, simulator), with its own
sim time on ``/<hand>/clock``; runs them together in lockstep for ``--duration`` seconds of sim
time; stops everything; and writes per hand ``OUT/<hand>/bag`` (rosbag2) and the report of
:mod:`soft_gripper_sdre.tools.judging.report` (figures and ``metrics.json``), then prints a summary.

:func:`run_graphs` is the runner underneath, also for one graph spread over several hosts
(:mod:`soft_gripper_sdre.tools.graph.two_hosts`): a ``place`` function tells, per node, the command
prefix (e.g. ``ip netns exec <host>``) and the environment its process gets.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import json
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import time
from typing import Callable, NamedTuple, Sequence

from soft_gripper_sdre.nodes.graph import GraphSpec, NodeSpec, grasp_graph, readiness_problem
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env

#: wall time for the graphs to connect before the simulators start [s]
CONNECT_TIMEOUT = 90.0
#: lockstep that waits out a node starved of CPU (many processes on few cores, at start-up
#: especially) instead of stepping without its command, so two runs of one grasp step alike and
#: any timeout is a fault; the controller's estimate watchdog stays longer than the simulator's wait
PATIENT_LOCKSTEP = {'simulator': {'lockstep_timeout': 2.0},
                    'controller': {'estimate_watchdog': 5.0}}
#: counters that say a message was refused, lost, late or out of order, or a node started over
TROUBLE = ('stale_command', 'future_command', 'late_command', 'bad_command', 'timeouts',
           'safe_periods', 'late_periods', 'resets', 'duplicate', 'out_of_order', 'bad_message',
           'dropouts', 'gaps', 'missed_periods', 'late_start', 'old_estimate', 'old_reference',
           'skipped_estimates', 'unanswered_estimates', 'nonfinite_torque', 'bad_estimate',
           'bad_reference', 'bad_clock')


@dataclass(frozen=True)
class Placement:
    """Where a node's process runs: behind ``prefix`` (none: here), with ``env`` (None: the
    run's)."""

    prefix: tuple[str, ...] = ()
    env: dict[str, str] | None = None


@dataclass
class GraphRun:
    """What one graph of :func:`run_graphs` did."""

    spec: GraphSpec
    diagnostics: dict[str, dict[str, str]]      # node name → its last /diagnostics values
    exit_codes: dict[str, int]
    wall_s: float                               # from starting the simulator to its last step
    pids: dict[str, int] = field(default_factory=dict)
    #: node name → its /diagnostics values as last heard while the simulator stepped (the
    #: recorder's matched publishers, say, before the others stop)
    during_run: dict[str, dict[str, str]] = field(default_factory=dict)

    def value(self, node: str, key: str, default: float = float('nan')) -> float:
        """``key`` of ``node``'s last /diagnostics as a number (``default`` if absent)."""
        try:
            return float(self.diagnostics.get(node, {}).get(key, default))
        except ValueError:
            return default

    @property
    def bag(self) -> Path | None:
        """The recorder's bag directory, if the graph records."""
        if 'recorder' not in self.spec.names:
            return None
        output = (self.diagnostics.get('recorder', {}).get('output')
                  or self.spec.node('recorder').parameters.get('output'))
        return Path(output) if output else None


def _connected(spec: GraphSpec, monitor: DiagnosticsMonitor) -> bool:
    """The graph's start rule (:func:`~soft_gripper_sdre.nodes.graph.readiness_problem`) holds
    for every node but the lead: each has reported and matched its peers among them. The lead
    (the simulator) applies the same rule, itself included, before its first step."""
    others = [n for n in spec.nodes if n.name != spec.lead]
    reports = {n.name: monitor.by_full_name.get(n.full_name) for n in others}
    return readiness_problem([n.name for n in others], reports, spec.topic) is None


def _finished(spec: GraphSpec, monitor: DiagnosticsMonitor) -> bool:
    """The lead (simulator) reports its last step: its sim time reached its ``duration``."""
    duration = float(spec.node(spec.lead).parameters.get('duration', 0.0))
    return duration > 0 and monitor.get(spec.node(spec.lead).full_name, 'sim_time') >= duration


def _exit_code(graph: Graph, name: str, timeout: float = 15.0) -> int:
    """The exit status of a process that is stopping by itself; stopped after ``timeout``."""
    try:
        return graph.procs[name].popen.wait(timeout)
    except subprocess.TimeoutExpired:
        return graph.stop(name)


def _failure(what: str, graphs: Sequence[Graph], name: str | None = None) -> RuntimeError:
    """A RuntimeError naming the first dead process (or ``name``'s) with the tail of its log."""
    for graph in graphs:
        for key, proc in graph.procs.items():
            if (name is None and not proc.alive()) or key == name:
                return RuntimeError(f'{what}: {graph.log_dir.name}/{key} '
                                    f'(exit status {proc.popen.returncode}); '
                                    f'last lines of its log {proc.log_path}:\n{proc.log_tail()}')
    return RuntimeError(what)


def run_graphs(specs: Sequence[GraphSpec], env: dict[str, str], log_dir: Path, *,
               place: Callable[[NodeSpec], Placement] | None = None, timeout: float = 600.0,
               on_poll: Callable[[DiagnosticsMonitor, list[Graph]], None] | None = None,
               monitor_name: str = 'graphs_monitor') -> list[GraphRun]:
    """Run ``specs`` together: start every node but the leads, wait until each graph is
    connected, start the leads (simulators), wait for them to exit, stop the rest.

    Args:
        specs: graphs with distinct namespaces (or one graph).
        env: the environment of the processes and of the monitor node in this process.
        log_dir: one directory of logs per graph (named by its namespace, ``root`` for '').
        place: where each node runs (default: here, with ``env``).
        timeout: wall-time limit of the stepping [s].
        on_poll: called with the monitor and the graphs' processes about 20 times a second
            while the simulators step.
        monitor_name: the node name of this process's /diagnostics listener.

    Returns:
        One :class:`GraphRun` per spec, with each node's final /diagnostics.

    Raises:
        RuntimeError: a node died, the graphs did not connect, or the run timed out; the message
            names the node and quotes its log (the logs are kept).
    """
    place = place or (lambda spec: Placement())
    specs = _waiting_for_readers(specs)
    monitor = DiagnosticsMonitor(env, monitor_name)
    graphs = [Graph(env, Path(log_dir) / (s.namespace.strip('/').replace('/', '_') or 'root'))
              for s in specs]
    try:
        for spec, graph in zip(specs, graphs):
            _start(graph, [node for node in spec.nodes if node.name != spec.lead], place)
        _await_connection(specs, graphs, monitor, log_dir)
        started = time.monotonic()
        for spec, graph in zip(specs, graphs):
            _start(graph, [spec.node(spec.lead)], place)
        ends = _await_leads(specs, graphs, monitor, started, timeout, on_poll, log_dir)
        codes = [_stop_in_order(spec, graph, monitor) for spec, graph in zip(specs, graphs)]
        monitor.spin_until(lambda: False, 0.5)
        return [GraphRun(spec, _last_heard(spec, monitor), code, end.wall_s,
                         {k: p.popen.pid for k, p in graph.procs.items()}, end.during_run)
                for spec, graph, code, end in zip(specs, graphs, codes, ends)]
    finally:
        for graph in graphs:
            graph.stop_all()
        monitor.close()


def _waiting_for_readers(specs: Sequence[GraphSpec]) -> list[GraphSpec]:
    """``specs`` with each lead (simulator) waiting at start-up for every /diagnostics reader, the
    monitor of :func:`run_graphs` and each recorder, so a short run's final counters reach them
    (a lead's own setting is kept)."""
    readers = 1 + sum('recorder' in s.names for s in specs)
    return [s if 'min_diagnostics_subscribers' in s.node(s.lead).parameters
            else s.with_parameters(s.lead, min_diagnostics_subscribers=readers) for s in specs]


def _start(graph: Graph, nodes: Sequence[NodeSpec],
           place: Callable[[NodeSpec], Placement]) -> None:
    """Start ``nodes`` in ``graph``, each where ``place`` puts it."""
    for node in nodes:
        where = place(node)
        graph.start_node(node, prefix=where.prefix, env=where.env)


def _last_heard(spec: GraphSpec, monitor: DiagnosticsMonitor) -> dict[str, dict[str, str]]:
    """Node name → the /diagnostics values the monitor last heard from that node of ``spec``."""
    return {n.name: dict(monitor.by_full_name.get(n.full_name, {})) for n in spec.nodes}


def _await_connection(specs: Sequence[GraphSpec], graphs: Sequence[Graph],
                      monitor: DiagnosticsMonitor, log_dir: Path) -> None:
    """Poll until every graph is connected (:func:`_connected`), within :data:`CONNECT_TIMEOUT`.

    Raises:
        RuntimeError: a node exited first, or the time ran out.
    """
    deadline = time.monotonic() + CONNECT_TIMEOUT
    while not all(_connected(s, monitor) for s in specs):
        if any(not p.alive() for g in graphs for p in g.procs.values()):
            raise _failure('a node exited before the graph connected', graphs)
        if time.monotonic() > deadline:
            raise RuntimeError(f'the graphs did not connect within {CONNECT_TIMEOUT:g} s; '
                               f'heard from {sorted(monitor.by_full_name)}; logs in {log_dir}')
        monitor.poll()
        time.sleep(0.05)


class _LeadEnd(NamedTuple):
    """A graph at its lead's last step: the wall time since the leads started [s] and what each
    of its nodes had last reported then."""

    wall_s: float
    during_run: dict[str, dict[str, str]]


def _await_leads(specs: Sequence[GraphSpec], graphs: list[Graph],
                 monitor: DiagnosticsMonitor, started: float, timeout: float,
                 on_poll: Callable[[DiagnosticsMonitor, list[Graph]], None] | None,
                 log_dir: Path) -> list[_LeadEnd]:
    """Poll (and call ``on_poll``) until every graph's lead has taken its last step; as soon as
    one has, its graph's loop nodes are told to stop (:func:`_stop_loop_nodes`).

    Raises:
        RuntimeError: a lead failed, another node of a running graph died, or more than
            ``timeout`` s of wall time passed since ``started``.
    """
    ends: dict[int, _LeadEnd] = {}
    while len(ends) < len(specs):
        for i, (spec, graph) in enumerate(zip(specs, graphs)):
            lead = graph.procs[spec.lead]
            if i in ends:
                continue
            if not lead.alive() and lead.popen.returncode != 0:
                raise _failure(f'the {spec.lead} of {spec.namespace or "/"} failed', graphs,
                               spec.lead)
            if lead.alive() and not _finished(spec, monitor):
                continue
            ends[i] = _LeadEnd(time.monotonic() - started, _last_heard(spec, monitor))
            _stop_loop_nodes(spec, graph)
        running = [(s, g) for i, (s, g) in enumerate(zip(specs, graphs)) if i not in ends]
        if any(not p.alive() for s, g in running for p in g.procs.values() if p.name != s.lead):
            raise _failure('a node died during the run', [g for _, g in running])
        if time.monotonic() - started > timeout:
            raise RuntimeError(f'the run did not finish within {timeout:g} s of wall time; '
                               f'logs in {log_dir}')
        monitor.poll()
        if on_poll is not None:
            on_poll(monitor, graphs)
        time.sleep(0.05)
    return [ends[i] for i in range(len(specs))]


def _stop_loop_nodes(spec: GraphSpec, graph: Graph) -> None:
    """The lead (simulator) has taken its last step: the loop nodes are told to stop at once (the
    controller before its clock watchdog fires while the simulator closes), without waiting for
    them while other graphs still run."""
    for node in reversed(spec.nodes):
        if node.name not in (spec.lead, 'recorder'):
            graph.procs[node.name].popen.send_signal(signal.SIGINT)


def _stop_in_order(spec: GraphSpec, graph: Graph, monitor: DiagnosticsMonitor) -> dict[str, int]:
    """Every node's exit code, the graph taken in reverse start order, the recorder last: it
    receives the others' final counters (and so does the monitor). The lead and the signalled
    nodes are on their way out: a second signal could land after the interpreter has restored the
    default handlers and kill the process, so they are only waited for."""
    codes = {}
    for node in reversed(spec.nodes):
        codes[node.name] = (graph.stop(node.name) if node.name == 'recorder'
                            else _exit_code(graph, node.name))
        monitor.poll()
    return codes


def published_and_recorded(run: GraphRun) -> dict[str, tuple[int | None, int]]:
    """Loop topic → (messages its node counted as published, messages in the bag)."""
    from soft_gripper_sdre.analysis.bag import topic_counts
    counts = topic_counts(run.bag)
    steps = run.value('simulator', 'steps')

    def counter(node: str, *keys: str) -> int | None:
        values = [run.value(node, k, 0.0) for k in keys]
        return None if run.value(node, keys[0]) != run.value(node, keys[0]) else int(sum(values))
    published = {'tip_positions': None if steps != steps else int(steps) + 1,
                 'state_estimate': counter('estimator', 'estimates'),
                 'torque_commands': counter('controller', 'commands'),
                 'grasp_reference': counter('trajectory', 'references')}
    return {topic: (n, counts.get(run.spec.topic(topic), 0)) for topic, n in published.items()}


def trouble(run: GraphRun) -> dict[str, dict[str, int]]:
    """Per node, the :data:`TROUBLE` counters that are not zero."""
    return {node: {k: int(run.value(node, k)) for k in TROUBLE if run.value(node, k, 0.0) > 0}
            for node in run.spec.names if any(run.value(node, k, 0.0) > 0 for k in TROUBLE)}


def hand_graphs(hands: Sequence[str], out: Path, duration: float, *, record: bool = True,
                parameters: dict[str, dict] | None = None) -> list[GraphSpec]:
    """One grasp graph per hand namespace, each recording to ``out/<hand>/bag``."""
    specs = []
    for hand in hands:
        params = {node: dict(values) for node, values in (parameters or {}).items()}
        params.setdefault('simulator', {})['duration'] = duration
        if record:
            params.setdefault('recorder', {})['output'] = str(Path(out) / hand.strip('/') / 'bag')
        specs.append(grasp_graph(hand, record=record, parameters=params))
    return specs


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.hands',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--hands', nargs='+', default=['left_hand', 'right_hand'], metavar='NAMESPACE',
                    help='one namespace per hand (default: %(default)s)')
    ap.add_argument('--out', type=Path, default=Path('runs/hands'),
                    help='output directory (default %(default)s)')
    ap.add_argument('--duration', type=float, default=6.0,
                    help='sim time to run [s] (default %(default)s)')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: env or random)')
    ap.add_argument('--timeout', type=float, default=900.0,
                    help='wall-clock limit [s] (default %(default)s)')
    return ap


def main(argv: list[str] | None = None) -> int:
    from soft_gripper_sdre.nodes.graph import normalize_namespace
    from soft_gripper_sdre.tools.judging.report import report
    ap = _parser()
    a = ap.parse_args(argv)
    try:
        hands = [normalize_namespace(h) for h in a.hands]
    except ValueError as exc:
        ap.error(str(exc))
    if '' in hands or len(set(hands)) != len(hands):
        ap.error(f'--hands needs distinct namespaces other than the root, got {a.hands}')
    if not 0 < a.duration <= 600:
        ap.error(f'--duration must be in (0, 600] s of sim time, got {a.duration}')
    for hand in hands:
        shutil.rmtree(a.out / hand.strip('/') / 'bag', ignore_errors=True)
    specs = hand_graphs(hands, a.out, a.duration, parameters=PATIENT_LOCKSTEP)
    try:
        runs = run_graphs(specs, ros_env(a.domain_id), a.out / 'logs', timeout=a.timeout,
                          monitor_name='hands_monitor')
    except RuntimeError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    summary = {}
    for run in runs:
        hand = run.spec.namespace
        metrics = report(run.bag, a.out / hand.strip('/'))
        summary[hand] = {'fingers': metrics['fingers'], 'wall_s': run.wall_s,
                         **{k: run.value('simulator', k)
                            for k in ('real_time_factor', 'steps', 'loop_latency_us_p50',
                                      'loop_latency_us_p99')},
                         'commands': run.value('controller', 'commands'), 'trouble': trouble(run)}
        print(f'{hand}: {a.duration:g} s of sim time in {run.wall_s:.1f} s wall '
              f'({summary[hand]["real_time_factor"]:.2f}× real time, loop latency p50 '
              f'{summary[hand]["loop_latency_us_p50"]:.0f} µs, '
              f'p99 {summary[hand]["loop_latency_us_p99"]:.0f} µs), '
              f'{int(summary[hand]["steps"])} steps, {int(summary[hand]["commands"])} commands '
              'of its own '
              f'controller; refused, late or lost: {summary[hand]["trouble"] or "none"}')
        for name, f in metrics['fingers'].items():
            pct = 'n/a' if f['rmse_pct'] is None else f'{f["rmse_pct"]:.2f} %'
            print(f'  {name}: free-space RMSE {f["rmse_mm"]:.3f} mm '
                  f'({pct} of {f["excursion_mm"]:.1f} mm)')
    (a.out / 'hands.json').write_text(json.dumps(summary, indent=2, default=float))
    print(f'bags, figures and metrics in {a.out}/<hand>/')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
