"""One run of the node graph as processes, for the graph benchmarks: the figures it reports.

:func:`run_graph` starts the loop processes (and the recorder), lets the simulator step a given
sim time, and returns every node's final /diagnostics values, heard by a monitor node, with the
CPU time each process spent per step while the simulator stepped (from /proc, the start-up
excluded) and the start-up to the first torque. The benchmarks' rows are built from these in
:mod:`soft_gripper_sdre.tools.benchmarks.bench_graph`.
"""
from __future__ import annotations

import os
from pathlib import Path
import tempfile
import time

from soft_gripper_sdre.nodes.graph import GraphSpec, grasp_graph
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


def measured_env(cpu_latency: int | None = None) -> dict[str, str]:
    """The graph's environment (``procs.ros_env``) for a measured run: the CPU wake-up latency
    held at ``cpu_latency`` µs by the processes at real-time priority when the benchmark asks for
    it, and never because the calling shell had ``SOFT_GRIPPER_CPU_LATENCY_US`` set."""
    from soft_gripper_sdre.nodes.scheduling import CPU_LATENCY_ENV
    env = ros_env()
    env.pop(CPU_LATENCY_ENV, None)
    if cpu_latency is not None:
        env[CPU_LATENCY_ENV] = str(cpu_latency)
    return env


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
              realtime: int = 0, pin: bool = False, cpu_latency: int | None = None,
              timeout: float = 600.0, during=None,
              history: dict[str, list] | None = None,
              probe: Path | None = None) -> dict[str, dict[str, float]]:
    """Run the loop processes (and the recorder into ``record``) for ``seconds`` of sim time;
    ``composed``: the estimator and the controller as one process (``controller --with-estimator``),
    whose CPU time is the controller's; ``realtime``: the loop's processes under SCHED_FIFO at that
    priority (0: none); ``pin``: the simulator on one CPU and the loop's other nodes on another
    (``grasp_graph(pin=True)``); ``cpu_latency``: the CPU wake-up latency [µs] the processes at
    real-time priority hold (``SOFT_GRIPPER_CPU_LATENCY_US``; None: none). ``during(monitor)`` is
    called about 10 times a second while the simulator steps; ``history``, if given, gets the
    monitor's /diagnostics history (node → its successive values). ``probe``: every process
    records its timestamps there (:mod:`~soft_gripper_sdre.tools.benchmarks.loop_probe`, read by
    its :func:`graph_periods`).

    Returns every node's final /diagnostics values as floats (non-numeric values dropped), for
    each node its CPU time per step while the simulator stepped (``cpu_per_step_us``), and for the
    simulator the wall time from launching the processes to its first command (``startup_s``).

    Raises:
        RuntimeError: a node died or the run did not finish within ``timeout``.
    """
    from soft_gripper_sdre.nodes.common import EXECUTOR_ENV
    from soft_gripper_sdre.tools.benchmarks.loop_probe import probe_env
    env = measured_env(cpu_latency)
    if executor is not None:
        env[EXECUTOR_ENV] = executor
    if probe is not None:
        env = probe_env(env, probe)
    fast = {'state_rate': 1000.0, 'clock_rate': 1000.0} if all_at_1khz else {}
    params = {'estimator': {}, 'controller': {}, 'trajectory': {},
              'simulator': {'duration': seconds, 'mode': mode,
                            'min_tip_subscribers': 2 + bool(record),
                            # the monitor (+ recorder)
                            'min_diagnostics_subscribers': 1 + bool(record),
                            **fast}}
    if record:
        params['recorder'] = {'output': str(record)}
    spec = grasp_graph(record=bool(record), parameters=params, composed=composed,
                       realtime=realtime, pin=pin)
    monitor = DiagnosticsMonitor(env, 'bench_monitor')
    steps = int(round(seconds / 0.001))
    try:
        cpu, launched = _run_processes(graph_env=env, monitor=monitor, spec=spec, record=record,
                                       steps=steps, timeout=timeout, during=during)
    finally:
        monitor.close()
    out = {node: _numbers(values) for node, values in monitor.values.items()}
    for node, seconds in cpu.items():       # CPU of the stepping only (start-up excluded)
        out.setdefault(node, {})['cpu_per_step_us'] = 1e6 * seconds / steps
    sim = out.setdefault('simulator', {})
    if 'first_command_monotonic_s' in sim:
        sim['startup_s'] = sim['first_command_monotonic_s'] - launched
    if history is not None:
        history.update(monitor.history)
    return out


def _run_processes(graph_env: dict[str, str], monitor: DiagnosticsMonitor, spec: GraphSpec,
                   record: Path | None, steps: int, timeout: float,
                   during=None) -> tuple[dict[str, float], float]:
    """:func:`run_graph`'s processes: start, step, drain, stop; returns CPU seconds per node
    while the simulator stepped, and the monotonic time the processes were launched."""
    with (tempfile.TemporaryDirectory(prefix='sgs_bench_graph_') as logs,
          Graph(graph_env, Path(logs)) as graph):
        names = [n for n in spec.names if n != 'simulator']
        launched = time.monotonic()
        for node in spec.nodes[:-1]:
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
