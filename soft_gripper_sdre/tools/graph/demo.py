"""The grasp demo: the whole node graph as separate processes, in lockstep (or ``--mode``), \
recorded and reported.

    python -m soft_gripper_sdre.tools.graph.demo --out runs/demo

starts the recorder, the estimator, the controller, the trajectory node and the simulator (each the
process ``ros2 run soft_gripper_sdre <node>`` would start, with its ``config/<node>.yaml``), runs
the grasp for ``--duration`` seconds of sim time, stops everything cleanly and writes

    OUT/bag/            rosbag2 directory (metadata.yaml + MCAP) of every topic
    OUT/logs/           one log per node
    OUT/fig5_positions.png, fig6_velocities.png, fig7_torques.png, metrics.json
    OUT/fig1_hand.png, fig4_snapshots.png, grasp.gif   the hand drawn from the bag

then prints a summary. Every argument is checked before anything starts
(:mod:`~soft_gripper_sdre.tools.graph.demo_checks`; bad usage: exit 2); a node that dies is named
with the last lines of its own log (exit 1), and the partial bag of a failed run is removed.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import json
from pathlib import Path
import shutil
import sys
import time

from soft_gripper_sdre.control.laws import GRAPH_LAWS
from soft_gripper_sdre.nodes.graph import CUBE_FINGERS, GraphSpec, finger_parameters, grasp_graph
from soft_gripper_sdre.sim.lockstep import MODES
from soft_gripper_sdre.tools.graph.demo_checks import argument_problem, parse_fingers
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.demo',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=Path('runs/demo'),
                    help='output directory (default %(default)s)')
    ap.add_argument('--duration', type=float, default=6.0,
                    help='sim time to run [s] (default %(default)s)')
    ap.add_argument('--model', type=Path, default=None,
                    help='model checkpoint (default: the shipped one)')
    ap.add_argument('--noise', type=float, default=None, metavar='MM',
                    help='tip measurement noise σ [mm] (default: config/simulator.yaml, 0.05 mm)')
    ap.add_argument('--seed', type=int, default=None,
                    help='measurement noise seed (default: config)')
    ap.add_argument('--period', type=float, default=None, metavar='MS',
                    help='control period of the whole loop [ms], from 1 to 10: the simulator, the '
                         'estimator and the controller all take it, the torque roll-off\'s corner '
                         'is capped at a tenth of the control rate (default: the config files, '
                         '1 ms; tracking per period: docs/results.md "Control rates")')
    ap.add_argument('--law', default=None, choices=GRAPH_LAWS,
                    help='control law of the controller node (default: config/controller.yaml)')
    ap.add_argument('--fingers', default=None, metavar='NAME=HAND_FINGER,...',
                    help='run the graph on these fingers of the hand, named (e.g. left=0,right=2: '
                         f'hand fingers {CUBE_FINGERS[0]} and {CUBE_FINGERS[1]} face each other '
                         'across the cube); default all four, finger_0=0,...,finger_3=3')
    ap.add_argument('--mode', default=None, choices=MODES,
                    help='the simulator\'s stepping (default: config/simulator.yaml, lockstep): '
                         'pipelined steps the physics with the previous period\'s command while '
                         'the current one is computed, deterministic as lockstep and faster on '
                         'two or more cores; realtime steps on a wall timer and is not '
                         'reproducible (docs/design/loop_rules.md)')
    ap.add_argument('--integral-gain', type=float, default=None, metavar='KI',
                    help='the default law\'s integral gain [1/s³], 0 = off '
                         '(default: config/controller.yaml)')
    ap.add_argument('--composed', action='store_true',
                    help='run the estimator in the controller\'s process (controller '
                         '--with-estimator): one process and one DDS hop fewer per period')
    ap.add_argument('--realtime', type=int, default=0, metavar='PRIORITY',
                    help='run the simulator, the estimator and the controller under SCHED_FIFO '
                         'at this priority (1 to 98, behind chrt -f; default: ordinary '
                         'scheduling): on time on a busy machine; needs root, CAP_SYS_NICE or an '
                         'rtprio limit (docs/performance.md "Real-time priority")')
    ap.add_argument('--pin', action='store_true',
                    help='run the simulator on one CPU and the estimator and the controller on '
                         'another (behind taskset; needs two CPUs): each keeps its caches from '
                         'period to period (docs/performance.md "Cores")')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: env or random)')
    ap.add_argument('--timeout', type=float, default=600.0,
                    help='wall-clock limit [s] (default %(default)s)')
    ap.add_argument('--no-progress', action='store_true', help='no progress bar')
    return ap


@dataclass(frozen=True)
class DemoGraph:
    """What the demo's graph runs, beyond the shipped configuration (None: the config files').

    ``model`` a checkpoint; ``noise`` the tips' σ [m]; ``seed`` the simulator's; ``law`` the
    controller's; ``fingers`` name → hand finger; ``period`` [s] the control period of every node
    of the loop; ``integral_gain`` the default law's; ``mode`` the simulator's stepping;
    ``composed`` the estimator in the controller's process (:meth:`GraphSpec.composed`);
    ``realtime`` the SCHED_FIFO priority of the loop's processes (0: none); ``pin`` the simulator
    and the other loop nodes each on a CPU of their own
    (:func:`~soft_gripper_sdre.nodes.graph.pinned_cpus`)."""

    model: Path | None = None
    noise: float | None = None
    seed: int | None = None
    law: str | None = None
    fingers: dict[str, int] | None = None
    period: float | None = None
    integral_gain: float | None = None
    mode: str | None = None
    composed: bool = False
    realtime: int = 0
    pin: bool = False

    def spec(self, bag: Path, duration: float) -> GraphSpec:
        """The grasp graph recording into ``bag`` for ``duration`` s of sim time."""
        params = {
            'recorder': {'output': str(bag)},
            'estimator': {},
            'controller': {'model_path': str(self.model.resolve())} if self.model else {},
            'trajectory': {},
            # the first run after an install compiles the control kernels (about a minute)
            # before the controller and the estimator report ready
            'simulator': {'duration': duration, 'min_tip_subscribers': 3,
                          'startup_timeout': 120.0},
        }
        for node, key, value in (('simulator', 'noise_std', self.noise),
                                 ('simulator', 'seed', self.seed),
                                 ('controller', 'law', self.law),
                                 ('simulator', 'mode', self.mode),
                                 ('controller', 'integral_gain',
                                  None if self.integral_gain is None
                                  else float(self.integral_gain))):
            if value is not None:
                params[node][key] = value
        for node, values in (finger_parameters(self.fingers) if self.fingers else {}).items():
            params[node].update(values)
        return grasp_graph(parameters=params, control_period=self.period, composed=self.composed,
                           realtime=self.realtime, pin=self.pin)


def run_demo(out: Path, duration: float, graph: DemoGraph = DemoGraph(), *,
             domain_id: int | None = None, timeout: float = 600.0, progress: bool = True,
             render: bool = True) -> dict:
    """Run ``graph`` for ``duration`` s of sim time, write bag/figures/metrics under ``out``;
    returns the report (plus run facts). ``render``: also draw the hand (Figs. 1 and 4, the
    animation) beside the tracking figures.

    Raises:
        RuntimeError: a node failed or the run did not finish within ``timeout`` (logs are kept).
    """
    from soft_gripper_sdre.tools.judging.report import report

    out = Path(out)
    bag = out / 'bag'
    if bag.exists():
        shutil.rmtree(bag)  # the demo owns its output directory; the recorder needs a new one
    out.mkdir(parents=True, exist_ok=True)
    env = ros_env(domain_id)
    spec = graph.spec(bag, duration)
    wall, stopped = _run_graph(spec, env, out, duration, timeout, progress)
    t_report = time.monotonic()
    if progress:
        print('reading the bag and drawing the figures ...', file=sys.stderr, flush=True)
    result = report(bag, out, torque_limit=_controller_limit(), render=render)
    result['controller'] = controller_stats(bag, len(result['fingers']))
    sim_diag = last_diagnostics(bag, 'simulator')
    stepping_rtf = sim_diag.get('real_time_factor')
    result['run'] = {'sim_duration_s': duration, 'control_period_s': float(_simulator_period(spec)),
                     'mode': sim_diag.get('mode', graph.mode),
                     'wall_s': round(wall, 2),
                     'report_wall_s': round(time.monotonic() - t_report, 2),
                     'real_time_factor': float(stepping_rtf) if stepping_rtf else None,
                     **{f'loop_latency_us_{k}': float(sim_diag[f'loop_latency_us_{k}'])
                        for k in ('p50', 'p99') if f'loop_latency_us_{k}' in sim_diag},
                     'exit_codes': stopped,
                     'domain_id': int(env['ROS_DOMAIN_ID'])}
    (out / 'metrics.json').write_text(json.dumps(result, indent=2, default=float))
    return result


def _run_graph(spec: GraphSpec, env: dict[str, str], out: Path, duration: float, timeout: float,
               progress: bool) -> tuple[float, dict[str, int]]:
    """Start every node of ``spec``, wait for the simulator to finish, stop the rest; returns the
    wall time [s] and every node's exit code. On a failure the bag is removed.

    Raises:
        RuntimeError: a node failed or the run timed out, naming it and quoting its log.
    """
    bag = out / 'bag'
    if progress:
        print(f'starting the node graph ({", ".join(spec.names)}) on ROS_DOMAIN_ID '
              f'{env["ROS_DOMAIN_ID"]}, logs in {out / "logs"} ...', file=sys.stderr, flush=True)
    monitor = DiagnosticsMonitor(env, 'demo_monitor')
    bar = None
    t_wall = time.monotonic()
    with Graph(env, out / 'logs') as graph:
        # the simulator takes its first step once the whole graph is wired and ready
        # (nodes/graph.readiness_problem): a recorder then holds the run from its first instant
        for node in spec.nodes:
            graph.start_node(node)
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=duration, desc='grasp (sim s)', unit='s', bar_format=(
                '{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} [{elapsed}<{remaining}]'))

        def poll() -> None:
            monitor.poll()
            if bar is not None:
                bar.update(max(0.0, min(monitor.get('simulator', 'sim_time'), duration) - bar.n))

        code = graph.wait('simulator', timeout, poll)
        wall = time.monotonic() - t_wall
        if bar is not None:
            if code == 0:
                bar.update(duration - bar.n)
            bar.close()
        failed = {name: p.popen.returncode for name, p in graph.procs.items()
                  if name != 'simulator' and not p.alive()}
        stopped = graph.stop_all()
    monitor.close()
    if code != 0 or failed:
        shutil.rmtree(bag, ignore_errors=True)
        if code is None and not failed:
            raise RuntimeError(f'the grasp run timed out after {timeout:g} s; last lines of '
                               f'simulator.log:\n{graph.procs["simulator"].log_tail()}')
        culprit = 'simulator' if code not in (0, None) else next(iter(failed))
        status = code if culprit == 'simulator' else failed[culprit]
        raise RuntimeError(f'the {culprit} node exited with status {status} (exit codes '
                           f'{stopped}); last lines of {culprit}.log:\n'
                           f'{graph.procs[culprit].log_tail()}')
    return wall, stopped


def _simulator_period(spec) -> float:
    """The control period the graph ``spec`` runs at: its override, else config/simulator.yaml's."""
    import yaml

    from soft_gripper_sdre.tools.graph.procs import default_params_file
    node = spec.node('simulator')
    if 'control_period' in node.parameters:
        return node.parameters['control_period']
    return yaml.safe_load(default_params_file('simulator').read_text())[
        '/**/simulator']['ros__parameters']['control_period']


def _controller_limit() -> float:
    import yaml

    from soft_gripper_sdre.tools.graph.procs import default_params_file
    path = default_params_file('controller')
    return float(yaml.safe_load(path.read_text())['/**/controller']['ros__parameters'][
        'torque_limit'])


def last_diagnostics(bag: Path, node: str) -> dict[str, str]:
    """Key/values of ``node``'s last /diagnostics status in the bag ({} if none)."""
    from soft_gripper_sdre.analysis.bag import read_bag
    last = None
    for _, msg in read_bag(bag, ['/diagnostics'])['/diagnostics']:
        for status in msg.status:
            if status.name.endswith(node):
                last = status
    return {} if last is None else {kv.key: kv.value for kv in last.values}


def controller_stats(bag: Path, n_fingers: int = 4) -> dict:
    """The controller's last /diagnostics in the bag: counters, Riccati checks, compute time."""
    values = last_diagnostics(bag, 'controller')
    if not values:
        return {}
    stats: dict = {}
    for key, value in values.items():
        try:
            stats[key] = float(value)
        except ValueError:
            stats[key] = value            # the model path and the weights string
    solves = stats.get('commands', 0.0) * n_fingers
    if solves:
        stats['fallback_fraction'] = stats.get('fallbacks', 0.0) / solves
        stats['check_failure_fraction'] = stats.get('check_failures', 0.0) / solves
    return stats


def summary(result: dict, out: Path) -> str:
    """A short human summary of :func:`run_demo`'s result."""
    run = result['run']
    rtf = 'n/a' if run['real_time_factor'] is None else f'{run["real_time_factor"]:.2f}'
    latency = (f'; loop latency p50 {run["loop_latency_us_p50"]:.0f} µs, '
               f'p99 {run["loop_latency_us_p99"]:.0f} µs'
               if 'loop_latency_us_p50' in run else '')
    period = (f' at a {1e3 * run["control_period_s"]:g} ms control period'
              if 'control_period_s' in run else '')
    mode = f' ({run["mode"]})' if run.get('mode', 'lockstep') != 'lockstep' else ''
    lines = [f'grasp demo{mode}: {run["sim_duration_s"]:g} s of sim time{period}, '
             f'{run["wall_s"]:.1f} s wall with start-up '
             f'(stepping at {rtf}× real time{latency}), then {run.get("report_wall_s", 0.0):.1f} s '
             'to read the bag and draw the figures']
    for name, f in result['fingers'].items():
        pct = 'n/a' if f['rmse_pct'] is None else f'{f["rmse_pct"]:.2f} %'
        lines.append(f'  {name}: free-space RMSE {f["rmse_mm"]:.3f} mm ({pct} of its '
                     f'{f["excursion_mm"]:.1f} mm excursion), max {f["max_mm"]:.3f} mm; '
                     f'touching the cube {100 * (f["contact_fraction"] or 0):.0f} % of the time')
    held = [f.get('true_tip', f).get('held_mm') for f in result['fingers'].values()]
    if any(h is not None for h in held):
        where = ('true tip' if all('true_tip' in f for f in result['fingers'].values())
                 else 'measured tip')
        lines.append('  where the reference stands still and the finger is free: mean error '
                     + ', '.join('n/a' if h is None else f'{h:.3f}' for h in held)
                     + f' mm ({where})')
    if result.get('cube_max_displacement_mm') is not None:
        lines.append(f'  cube displaced at most {result["cube_max_displacement_mm"]:.2f} mm')
    c = result.get('controller', {})
    compute = (f'compute {c.get("compute_us_mean", float("nan")):.0f} µs mean per '
               f'{len(result["fingers"])}-finger step')
    if 'max_residual' in c:  # (reported by the laws that solve a Riccati equation each step)
        lines.append(f'  Riccati: checks failed on {c["check_failure_fraction"]:.2%} of solves, '
                     f'fallbacks {c["fallback_fraction"]:.2%}, '
                     f'max residual {c["max_residual"]:.1e}; {compute}')
    elif 'compute_us_mean' in c:
        lines.append(f'  {c.get("law", "the law")} (no per-step Riccati solve): {compute}')
    lines.append(f'  bag, figures and metrics.json in {out}/')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    problem = argument_problem(a)
    if problem:
        ap.error(problem)
    try:
        graph = DemoGraph(model=a.model, noise=None if a.noise is None else a.noise * 1e-3,
                          seed=a.seed, law=a.law,
                          fingers=parse_fingers(a.fingers) if a.fingers else None,
                          period=None if a.period is None else a.period * 1e-3,
                          integral_gain=a.integral_gain, mode=a.mode, composed=a.composed,
                          realtime=a.realtime, pin=a.pin)
        result = run_demo(a.out, a.duration, graph, domain_id=a.domain_id, timeout=a.timeout,
                          progress=not a.no_progress)
    except RuntimeError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    print(summary(result, a.out))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
