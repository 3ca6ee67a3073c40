"""The grasp graph across two hosts: the simulator and the recorder on one, the estimator, the
trajectory node and the controller on the other, joined by one network link.

    sudo python -m soft_gripper_sdre.tools.graph.two_hosts --out runs/two_hosts [--duration 6]
        [--link-fault 0.5]

On one Linux machine the two hosts are two network namespaces joined by a veth pair
(:class:`~soft_gripper_sdre.tools.graph.netns.HostPair`: its addresses, routes and the DDS
settings between the hosts). Every process is started as ``ip netns exec <host> python -m
soft_gripper_sdre.nodes.<node> ...`` (so it needs root and iproute2).

The command runs the same lockstep grasp three ways, one after another: on one host (all five
processes here, the project's default DDS settings), split across the two hosts, and split with
the link taken down for ``--link-fault`` seconds mid-grasp; it compares their tracking, real-time
factor and loop latency (:mod:`~soft_gripper_sdre.tools.graph.host_comparison`) and writes
``OUT/two_hosts.json`` and each run's bag, report and logs.
A supervisor process in the simulator's namespace starts and watches the split graph (its
/diagnostics monitor must reach both hosts); the namespaces are removed whatever happens.
"""
from __future__ import annotations

import argparse
from dataclasses import asdict
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys

from soft_gripper_sdre.nodes.graph import GraphSpec, NodeSpec, grasp_graph
from soft_gripper_sdre.tools.graph.hands import PATIENT_LOCKSTEP, GraphRun, Placement, run_graphs
from soft_gripper_sdre.tools.graph.host_comparison import compare, summary
from soft_gripper_sdre.tools.graph.netns import HostPair, LinkFault, netns_unavailable
from soft_gripper_sdre.tools.graph.procs import ros_env

#: the nodes on the simulator's host; the others run on the controller's
SIM_HOST_NODES = ('recorder', 'simulator')


def split_graph(bag: Path, duration: float, parameters: dict[str, dict] | None = None) -> GraphSpec:
    """The grasp graph of these runs: recording to ``bag``, ``duration`` s of sim time."""
    params = {node: dict(values) for node, values in (parameters or {}).items()}
    params.setdefault('simulator', {})['duration'] = duration
    params.setdefault('recorder', {})['output'] = str(bag)
    return grasp_graph(parameters=params)


def shared_memory_files(pid: int) -> list[str]:
    """The Fast DDS shared-memory files (/dev/shm/fastrtps_*, fast_datasharing*) a process maps."""
    try:
        maps = Path(f'/proc/{pid}/maps').read_text()
    except OSError:
        return []
    return sorted({line.split()[-1] for line in maps.splitlines()
                   if '/dev/shm/fast' in line})


def _supervise(job_path: Path) -> int:
    """The split run, from inside the simulator's namespace (``--supervise JOB``): run the graph
    with the controller's host behind ``ip netns exec``, write the result next to the job."""
    job = json.loads(job_path.read_text())
    pair = HostPair(job['tag'])
    base = dict(os.environ)
    envs = {ns: pair.env(ns, base) for ns in (pair.sim_ns, pair.ctl_ns)}
    spec = split_graph(Path(job['bag']), job['duration'], job['parameters'])
    fault = (LinkFault(pair.sim_link, job['fault_at'], job['fault_seconds'])
             if job['fault_seconds'] else None)
    mapped: dict[str, list[str]] = {}

    def on_poll(monitor, graphs) -> None:
        if not mapped and monitor.get('simulator', 'sim_time') > 0.1:     # DDS is fully set up
            mapped.update({key: shared_memory_files(p.popen.pid)
                           for g in graphs for key, p in g.procs.items()})
        if fault is not None:
            fault(monitor, graphs)

    def place(node: NodeSpec) -> Placement:
        ns = pair.sim_ns if node.name in SIM_HOST_NODES else pair.ctl_ns
        return Placement(() if ns == pair.sim_ns else pair.exec_prefix(ns), envs[ns])

    os.environ.update(envs[pair.sim_ns])
    result: dict = {}
    try:
        run = run_graphs([spec], envs[pair.sim_ns], Path(job['logs']), place=place,
                         timeout=job['timeout'], on_poll=on_poll,
                         monitor_name='two_hosts_monitor')[0]
        result = {'diagnostics': run.diagnostics, 'exit_codes': run.exit_codes,
                  'wall_s': run.wall_s, 'pids': run.pids, 'during_run': run.during_run,
                  'shared_memory': mapped, 'fault': None if fault is None else asdict(fault)}
    except RuntimeError as exc:
        result = {'error': str(exc)}
    Path(job['result']).write_text(json.dumps(result, indent=2))
    return 0 if 'error' not in result else 1


def run_split(pair: HostPair, out: Path, duration: float, parameters: dict[str, dict] | None = None,
              *, fault_at: float = 0.0, fault_seconds: float = 0.0,
              timeout: float = 600.0) -> tuple[GraphRun, dict]:
    """The graph across ``pair``'s two hosts, recording to ``out/bag``; returns the run and what
    only the split run has: ``shared_memory`` (node → Fast DDS shared-memory files it mapped),
    ``traffic`` (bytes over the link), ``fault`` (:class:`LinkFault`'s record).

    Raises:
        RuntimeError: the run failed (the message quotes the failing node's log).
    """
    out = Path(out)
    shutil.rmtree(out / 'bag', ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    job = {'tag': pair.tag, 'bag': str(out / 'bag'), 'duration': duration,
           'parameters': parameters or {}, 'fault_at': fault_at, 'fault_seconds': fault_seconds,
           'logs': str(out / 'logs'), 'result': str(out / 'supervisor.json'), 'timeout': timeout}
    job_path = out / 'job.json'
    job_path.write_text(json.dumps(job, indent=2))
    before = pair.traffic()
    env = pair.env(pair.sim_ns, ros_env())
    with open(out / 'supervisor.log', 'w', encoding='utf-8') as log:
        code = subprocess.run([*pair.exec_prefix(pair.sim_ns), sys.executable, '-m',
                               'soft_gripper_sdre.tools.graph.two_hosts', '--supervise',
                               str(job_path)],
                              env=env, stdout=log, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL, timeout=timeout + 180).returncode
    after = pair.traffic()
    result_path = Path(job['result'])
    result = json.loads(result_path.read_text()) if result_path.is_file() else {}
    if code != 0 or 'error' in result:
        raise RuntimeError(result.get('error')
                           or f'the supervisor exited with {code}; see {out / "supervisor.log"}:\n'
                           + (out / 'supervisor.log').read_text()[-2000:])
    spec = split_graph(out / 'bag', duration, parameters)
    run = GraphRun(spec, result['diagnostics'], result['exit_codes'], result['wall_s'],
                   result['pids'], result['during_run'])
    extra = {'shared_memory': result['shared_memory'], 'fault': result['fault'],
             'traffic': {k: after[k] - before[k] for k in after}}
    return run, extra


def run_one_host(out: Path, duration: float, parameters: dict[str, dict] | None = None, *,
                 timeout: float = 600.0) -> GraphRun:
    """The same graph with every process here (the project's default DDS settings)."""
    out = Path(out)
    shutil.rmtree(out / 'bag', ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    spec = split_graph(out / 'bag', duration, parameters)
    return run_graphs([spec], ros_env(), out / 'logs', timeout=timeout,
                      monitor_name='one_host_monitor')[0]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.two_hosts',
                                 description=__doc__.split('\n\n')[0].replace('\n', ' '))
    ap.add_argument('--out', type=Path, default=Path('runs/two_hosts'),
                    help='output directory (default %(default)s)')
    ap.add_argument('--duration', type=float, default=6.0,
                    help='sim time of each run [s] (default %(default)s)')
    ap.add_argument('--link-fault', type=float, default=0.5, metavar='SECONDS',
                    help='a third run with the link down this long mid-grasp '
                         '(0: none; default %(default)s)')
    ap.add_argument('--timeout', type=float, default=900.0, help='wall-clock limit of each run [s]')
    ap.add_argument('--supervise', type=Path, default=None,
                    help=argparse.SUPPRESS)   # run_split's far end
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    if a.supervise is not None:
        return _supervise(a.supervise)
    if not 0 < a.duration <= 600 or not 0 <= a.link_fault <= 10:
        ap.error('--duration must be in (0, 600] s and --link-fault in [0, 10] s')
    reason = netns_unavailable()
    if reason:
        print(f'error: cannot make the two hosts: {reason}', file=sys.stderr)
        return 2
    try:
        one = run_one_host(a.out / 'one_host', a.duration, PATIENT_LOCKSTEP, timeout=a.timeout)
        with HostPair.new() as pair:
            two, extra = run_split(pair, a.out / 'two_hosts', a.duration, PATIENT_LOCKSTEP,
                                   timeout=a.timeout)
            faulted = None
            if a.link_fault:
                faulted = run_split(pair, a.out / 'link_fault', a.duration,
                                    {'simulator': {'lockstep_timeout': 0.1}},
                                    fault_at=min(1.0, a.duration / 3), fault_seconds=a.link_fault,
                                    timeout=a.timeout)
    except RuntimeError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    result = compare(one, two, extra, faulted, a.out)
    (a.out / 'two_hosts.json').write_text(json.dumps(result, indent=2, default=float))
    print(summary(result))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
