"""The grasp graph across two hosts: the simulator and the recorder on one, the estimator, the
trajectory node and the controller on the other, joined by one network link.

    sudo python -m soft_gripper_sdre.tools.graph.two_hosts --out runs/two_hosts [--duration 6]
        [--link-fault 0.5]

On one Linux machine the two hosts are two network namespaces joined by a veth pair whose
addresses (:data:`SIM_ADDRESS`, :data:`CTL_ADDRESS`, /24) exist only inside them, each with its
loopback up and a route for multicast (224.0.0.0/4) over its end of the link, as a host on a LAN
has through its default route (without one the split graph did not connect on its first start:
docs/deployment.md). Every process is started as ``ip netns exec <host> python -m
soft_gripper_sdre.nodes.<node> ...`` (so it needs root and iproute2). DDS between the hosts (see
docs/deployment.md):

* ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``: UDP only. Two network namespaces share one kernel and one
  /dev/shm, so Fast DDS's shared-memory transport would otherwise carry the data past the link;
* ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``: discovery on the hosts' own subnet (each namespace has
  nothing else). ``LOCALHOST`` would not do: Jazzy's rmw_fastrtps then replaces the built-in
  transports with its own shared memory + UDP pair, and FASTDDS_BUILTIN_TRANSPORTS is ignored;
* ``ROS_STATIC_PEERS=<the other host>``: the other host's address for unicast discovery
  announcements as well.

The command runs the same lockstep grasp three ways, one after another: on one host (all five
processes here, the project's default DDS settings), split across the two hosts, and split with
the link taken down for ``--link-fault`` seconds mid-grasp; it compares their tracking, real-time
factor and loop latency and writes ``OUT/two_hosts.json`` and each run's bag, report and logs.
A supervisor process in the simulator's namespace starts and watches the split graph (its
/diagnostics monitor must reach both hosts); the namespaces are removed whatever happens.
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
import json
import os
from pathlib import Path
import secrets
import shutil
import subprocess
import sys
import threading
import time

from soft_gripper_sdre.nodes.graph import GraphSpec, NodeSpec, grasp_graph
from soft_gripper_sdre.tools.graph.hands import (
    PATIENT_LOCKSTEP,
    GraphRun,
    Placement,
    published_and_recorded,
    run_graphs,
    trouble,
)
from soft_gripper_sdre.tools.graph.procs import ros_env

SIM_ADDRESS = '10.231.0.1'
CTL_ADDRESS = '10.231.0.2'
PREFIX_LENGTH = 24
#: multicast leaves each host over its end of the link (the split graph connects with it)
MULTICAST_ROUTE = '224.0.0.0/4'
#: the nodes on the simulator's host; the others run on the controller's
SIM_HOST_NODES = ('recorder', 'simulator')


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be made here (not root, no iproute2), or None."""
    if shutil.which('ip') is None:
        return 'iproute2 (the ip command) is not installed'
    if os.geteuid() != 0:
        return 'network namespaces need root (ip netns add)'
    probe = f'sgs_probe_{secrets.token_hex(3)}'
    made = subprocess.run(['ip', 'netns', 'add', probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f'ip netns add failed: {made.stderr.strip()}'
    subprocess.run(['ip', 'netns', 'delete', probe], capture_output=True)
    return None


def _ip(*args: str, netns: str | None = None) -> str:
    cmd = ['ip'] + (['-n', netns] if netns else []) + list(args)
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'{" ".join(cmd)}: {done.stderr.strip()}')
    return done.stdout


@dataclass(frozen=True)
class HostPair:
    """Two network namespaces joined by a veth pair: the simulator's host and the controller's.

    Names carry a random tag so runs side by side do not meet; :meth:`create` builds them,
    :meth:`remove` (also on leaving a ``with`` block) deletes both namespaces, and the veth pair
    with them."""

    tag: str

    @classmethod
    def new(cls) -> HostPair:
        return cls(secrets.token_hex(4))

    @property
    def sim_ns(self) -> str:
        return f'sgs_{self.tag}_sim'

    @property
    def ctl_ns(self) -> str:
        return f'sgs_{self.tag}_ctl'

    @property
    def sim_link(self) -> str:          # interface names: at most 15 characters
        return f'sgs{self.tag}s'

    @property
    def ctl_link(self) -> str:
        return f'sgs{self.tag}c'

    def create(self) -> HostPair:
        try:
            _ip('netns', 'add', self.sim_ns)
            _ip('netns', 'add', self.ctl_ns)
            _ip('link', 'add', self.sim_link, 'netns', self.sim_ns, 'type', 'veth',
                'peer', 'name', self.ctl_link, 'netns', self.ctl_ns)
            for ns, link, address in ((self.sim_ns, self.sim_link, SIM_ADDRESS),
                                      (self.ctl_ns, self.ctl_link, CTL_ADDRESS)):
                _ip('addr', 'add', f'{address}/{PREFIX_LENGTH}', 'dev', link, netns=ns)
                _ip('link', 'set', 'lo', 'up', netns=ns)
                _ip('link', 'set', link, 'up', netns=ns)
                _ip('route', 'add', MULTICAST_ROUTE, 'dev', link, netns=ns)
        except RuntimeError:
            self.remove()
            raise
        return self

    def remove(self) -> None:
        """Delete both namespaces (and so the veth pair); quiet if they are gone already."""
        for ns in (self.sim_ns, self.ctl_ns):
            subprocess.run(['ip', 'netns', 'delete', ns], capture_output=True)

    def __enter__(self) -> HostPair:
        return self.create()

    def __exit__(self, *exc) -> None:
        self.remove()

    def exists(self) -> bool:
        names = _ip('netns', 'list')
        return any(line.split()[0] in (self.sim_ns, self.ctl_ns)
                   for line in names.splitlines() if line.strip())

    def interfaces(self, ns: str) -> list[str]:
        """The interface names in the namespace ``ns``."""
        return [link['ifname'] for link in json.loads(_ip('-j', 'link', 'show', netns=ns))]

    def traffic(self) -> dict[str, int]:
        """Bytes and packets the simulator's end of the link has sent and received."""
        stats = json.loads(_ip('-j', '-s', 'link', 'show', 'dev', self.sim_link,
                               netns=self.sim_ns))[0]['stats64']
        return {'tx_bytes': stats['tx']['bytes'], 'rx_bytes': stats['rx']['bytes'],
                'tx_packets': stats['tx']['packets'], 'rx_packets': stats['rx']['packets']}

    def exec_prefix(self, ns: str) -> tuple[str, ...]:
        return ('ip', 'netns', 'exec', ns)

    def env(self, ns: str, base: dict[str, str]) -> dict[str, str]:
        """``base`` with DDS over UDP only, discovering the other host (see module doc)."""
        peer = CTL_ADDRESS if ns == self.sim_ns else SIM_ADDRESS
        return {**base, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'ROS_STATIC_PEERS': peer,
                'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}


def split_graph(bag: Path, duration: float, parameters: dict[str, dict] | None = None) -> GraphSpec:
    """The grasp graph of these runs: recording to ``bag``, ``duration`` s of sim time."""
    params = {node: dict(values) for node, values in (parameters or {}).items()}
    params.setdefault('simulator', {})['duration'] = duration
    params.setdefault('recorder', {})['output'] = str(bag)
    return grasp_graph(parameters=params)


@dataclass
class LinkFault:
    """Take ``link`` down once the simulator's sim time reaches ``at`` s, and up ``seconds`` later
    (wall time). An ``on_poll`` of :func:`run_graphs`."""

    link: str
    at: float
    seconds: float
    down_sim_time: float | None = None
    down_wall: float | None = None
    up_wall: float | None = None

    def __call__(self, monitor, graphs) -> None:
        if self.down_wall is not None or monitor.get('simulator', 'sim_time') < self.at:
            return
        _ip('link', 'set', 'dev', self.link, 'down')
        self.down_wall, self.down_sim_time = time.monotonic(), monitor.get('simulator', 'sim_time')
        threading.Timer(self.seconds, self._up).start()

    def _up(self) -> None:
        _ip('link', 'set', 'dev', self.link, 'up')
        self.up_wall = time.monotonic()


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


def timing(run: GraphRun) -> dict[str, float]:
    """Real-time factor and loop latency p50 / p99 [µs] from the simulator's final diagnostics."""
    return {'real_time_factor': run.value('simulator', 'real_time_factor'),
            'loop_latency_us_p50': run.value('simulator', 'loop_latency_us_p50'),
            'loop_latency_us_p99': run.value('simulator', 'loop_latency_us_p99'),
            'controller_compute_us': run.value('controller', 'compute_us_mean')}


def finite_torques(run: GraphRun) -> bool:
    """Whether every torque command in the run's bag is finite."""
    import numpy as np

    from soft_gripper_sdre.analysis.bag import read_bag
    msgs = read_bag(run.bag, [run.spec.topic('torque_commands')])[run.spec.topic('torque_commands')]
    return all(np.isfinite(np.asarray(m.effort, dtype=float)).all() for _, m in msgs)


def paired_tracking(one: GraphRun, two: GraphRun) -> dict:
    """The two runs instant by instant, on the instants both bags hold (a recorder starved of CPU
    for longer than a topic's 50-message history loses the oldest, on either run): whether the
    measured tips and the torque commands are bit-identical there, and each run's free-space
    tracking (:func:`~soft_gripper_sdre.analysis.metrics.tracking_metrics`) over those instants."""
    import numpy as np

    from soft_gripper_sdre.analysis.bag import extract_run
    from soft_gripper_sdre.analysis.metrics import tracking_metrics
    from soft_gripper_sdre.tools.judging.report import hold
    runs = [extract_run(run.bag) for run in (one, two)]
    common, ia, ib = np.intersect1d(runs[0].tips.t, runs[1].tips.t, return_indices=True)
    u_common, ua, ub = np.intersect1d(runs[0].torques.t, runs[1].torques.t, return_indices=True)
    out = {'instants': int(len(common)), 'steps': int(one.value('simulator', 'steps')) + 1,
           'tips_identical': bool(np.array_equal(runs[0].tips.values[ia], runs[1].tips.values[ib])),
           'torques_identical': bool(np.array_equal(runs[0].torques.values[ua],
                                                    runs[1].torques.values[ub])),
           'torque_instants': int(len(u_common))}
    for name, run, idx in (('one_host', runs[0], ia), ('two_hosts', runs[1], ib)):
        ref = run.reference.values[idx][..., :2]
        valid = np.all(np.isfinite(ref.reshape(len(ref), -1)), axis=1)
        contact = hold(run.contacts.t, run.contacts.values, common) > 0.0
        excursion = np.linalg.norm(ref[valid] - ref[valid][0], axis=2).max(axis=0)
        metrics = tracking_metrics(run.tips.values[idx][valid], ref[valid], ~contact[valid],
                                   excursion)
        out[name] = {f'finger_{i}': m.as_dict() for i, m in enumerate(metrics)}
    out['tracking_identical'] = out['one_host'] == out['two_hosts']
    return out


def compare(one: GraphRun, two: GraphRun, extra: dict, faulted: tuple[GraphRun, dict] | None,
            out: Path) -> dict:
    """The figures of the three runs side by side (tracking from each bag's report)."""
    from soft_gripper_sdre.tools.judging.report import report
    fingers = {name: report(run.bag, Path(out) / name)['fingers']
               for name, run in (('one_host', one), ('two_hosts', two))}
    result = {
        'duration_s': float(two.spec.node('simulator').parameters['duration']),
        'load_average': os.getloadavg(), 'cpus': os.cpu_count(),
        'tracking': fingers, 'report_identical': fingers['one_host'] == fingers['two_hosts'],
        'paired': paired_tracking(one, two),
        'accounts': {'one_host': published_and_recorded(one),
                     'two_hosts': published_and_recorded(two)},
        'timing': {'one_host': timing(one), 'two_hosts': timing(two)},
        'trouble': {'one_host': trouble(one), 'two_hosts': trouble(two)},
        'shared_memory': extra['shared_memory'], 'link_traffic': extra['traffic'],
    }
    if faulted is not None:
        run, fault_extra = faulted
        result['link_fault'] = {
            'fault': fault_extra['fault'], 'exit_codes': run.exit_codes,
            'steps': run.value('simulator', 'steps'),
            'timeouts': run.value('simulator', 'timeouts', 0.0),
            'safe_periods': run.value('simulator', 'safe_periods', 0.0),
            'missed_by_estimator': run.value('estimator', 'missed_periods', 0.0),
            'trouble': trouble(run), 'finite_torques': finite_torques(run),
            'published_and_recorded': published_and_recorded(run),
            'tracking': report(run.bag, Path(out) / 'link_fault')['fingers'], 'timing': timing(run)}
    return result


def summary(result: dict) -> str:
    """A short human summary of :func:`compare`'s result."""
    one, two = result['timing']['one_host'], result['timing']['two_hosts']
    worst = {k: max(f['rmse_pct'] or 0.0 for f in v.values())
             for k, v in result['tracking'].items()}
    lines = [f'{result["duration_s"]:g} s lockstep grasp; load average '
             f'{result["load_average"][0]:.1f} on {result["cpus"]} cores',
             f'  one host : {one["real_time_factor"]:.2f}× real time, loop latency p50 '
             f'{one["loop_latency_us_p50"]:.0f} µs, p99 {one["loop_latency_us_p99"]:.0f} µs; '
             f'worst finger {worst["one_host"]:.2f} %',
             f'  two hosts: {two["real_time_factor"]:.2f}× real time, loop latency p50 '
             f'{two["loop_latency_us_p50"]:.0f} µs, p99 {two["loop_latency_us_p99"]:.0f} µs; '
             f'worst finger {worst["two_hosts"]:.2f} %; '
             f'{result["link_traffic"]["tx_bytes"] / 1e6:.1f} MB sent and '
             f'{result["link_traffic"]["rx_bytes"] / 1e6:.1f} MB received over the link; '
             f'Fast DDS shared memory mapped: '
             f'{sorted(k for k, v in result["shared_memory"].items() if v) or "none"}']
    paired = result['paired']
    missing = {run: {t: n - got for t, (n, got) in accounts.items() if n is not None and n != got}
               for run, accounts in result['accounts'].items()}
    lines.append(f'  the same loop: tips '
                 f'{"identical" if paired["tips_identical"] else "DIFFERENT"} and torque '
                 f'commands {"identical" if paired["torques_identical"] else "DIFFERENT"} at the '
                 f'{paired["instants"]} of {paired["steps"]} instants both bags hold; '
                 f'tracking over them '
                 f'{"identical" if paired["tracking_identical"] else "DIFFERENT"}; report figures '
                 f'{"identical" if result["report_identical"] else "not identical"}; '
                 f'messages missing from the bags (published − recorded): {missing}')
    fault = result.get('link_fault')
    if fault:
        lost = {t: (n - got if n is not None else None)
                for t, (n, got) in fault['published_and_recorded'].items()}
        worst_fault = max(f['rmse_pct'] or 0.0 for f in fault['tracking'].values())
        lines.append(f'  link down {fault["fault"]["seconds"]:g} s at t = '
                     f'{fault["fault"]["down_sim_time"]:.2f} s: {int(fault["steps"])} steps, '
                     f'{int(fault["timeouts"])} lockstep timeouts (held command), '
                     f'{int(fault["safe_periods"])} periods stepped with zero torque for lost '
                     f'commands, {int(fault["missed_by_estimator"])} tips the estimator skipped, '
                     f'torques finite: {fault["finite_torques"]}, counters {fault["trouble"]}; '
                     f'messages lost (published − in the bag) {lost}; '
                     f'worst finger {worst_fault:.2f} %')
    return '\n'.join(lines)


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
