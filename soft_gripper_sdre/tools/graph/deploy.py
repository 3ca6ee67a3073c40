"""Deploy a trained model on the lab's running driver, record the grasp and score it: one command.

    python -m soft_gripper_sdre.tools.graph.deploy --params runs/mine/params.yaml \
        [--law L] [--out DIR] [--realtime PRIORITY] [--cpu N]

Against a driver already serving ``tip_positions`` and taking ``torque_commands`` (the lab's, or
``plant_driver``), it starts, as separate processes over DDS, the composed loop (``controller
--with-estimator`` on ``params.yaml``, with the law ``--law``, default ``sdre_ff``: the law the
settings were derived for; with ``--realtime`` under SCHED_FIFO, with ``--cpu`` on that CPU), the
recorder and, once the loop has come up, the trajectory node on ``params.yaml`` (its fingers, the
move the settings were checked on, the plan's timing; every finger grasps, none opens). It ends
when the plan ends (its length from ``params.yaml``: t_start + t_close + t_hold + t_open, plus
``--tail`` seconds), stops the nodes (the controller last sends nothing, and the driver's
stale-command rule takes over), and prints the score of the run from the bag
(:func:`~soft_gripper_sdre.analysis.run_score.score_run`): the RMSE of the tips against the plan
as a share of the travel (on ``true_tip_positions`` when the driver publishes them, else the
measured tips), the share of commands at a bound while the plan holds at rest, and the commands
outside the controller's bounds; then a line of what the loop's nodes counted while the plan ran
(:func:`loop_report`: skipped estimates, resets, lost messages, a reporting driver's late ticks),
with advice when the loop was troubled.

Every node reads the tips best effort (which also matches a reliable driver); the nodes run on
the caller's ROS domain (or ``--domain-id``) with the caller's DDS settings. ``OUT`` (default:
``deploy_<law>`` beside ``params.yaml``) gets ``bag/``, ``logs/`` and ``score.json`` (the
score, and the loop's counts as ``loop``). Bad
arguments or a ``params.yaml`` without what the deployment needs: exit 2, nothing started and
nothing written; a node that fails or a bag that cannot be scored: exit 1, naming it.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import re
import sys
import time

import yaml

from soft_gripper_sdre.sim.shape import FingerShape, InputBounds, ShapeError

#: the trajectory node's timing keys, whose sum is the plan's length
PLAN_TIMES = ('t_start', 't_close', 't_hold', 't_open')
#: what the deployment records
TOPICS = ['tip_positions', 'true_tip_positions', 'state_estimate', 'grasp_reference',
          'torque_commands']
BEST_EFFORT = {'tips_reliability': 'best_effort'}
#: the key of a node's section in a parameters file
SECTION = '/**/{}'
#: the loop's troubles each node counts on /diagnostics (docs/faults.md), as the report gives them
LOOP_COUNTERS = {'controller': ('estimates', 'skipped_estimates', 'estimate_jumps',
                                'wrong_task_dim'),
                 'estimator': ('resets', 'dropouts', 'bad_message'),
                 'driver': ('ticks', 'late_ticks', 'stale_ticks', 'clipped_commands')}
#: what the run's line calls a troubled loop (beyond a best-effort link's few lost messages): more
#: than this share of the estimates skipped, or of the driver's ticks late, no estimate answered,
#: or any refusal for another task_dim, reset, stamp jump, dropout or stale tick
TROUBLE_SHARE = 0.05


def _number(value) -> int:
    """A counter's /diagnostics value as an int (0 where it is not a number: a lab's node may
    publish anything under a key)."""
    try:
        return int(float(value))
    except (TypeError, ValueError, OverflowError):
        return 0


def loop_report(start: dict[str, dict[str, str]], end: dict[str, dict[str, str]]) -> dict:
    """What the loop's nodes counted while the plan ran: the change between their /diagnostics
    values (by node name) at its ``start`` and at its ``end`` (each node reports about once a
    second, so the window is the plan's to about a second): the controller's estimates, those it
    skipped, the stamp jumps it warned of and what it refused for another task_dim, the
    estimator's resets and dropouts, the messages the recorder found missing per topic
    (``lost``), and the late and stale ticks of a driver that reports them (``late_ticks``, as
    ``plant_driver`` does from its start; ``driver`` None where no node does; counted from the
    start, so a lab's driver that runs on between deployments counts this one's alone). A counter
    a node never raised is 0."""
    def count(node: str, key: str) -> int:
        return _number(end.get(node, {}).get(key, 0)) - _number(start.get(node, {}).get(key, 0))

    def counts(node: str, keys: tuple[str, ...]) -> dict[str, int]:
        return {k: count(node, k) for k in keys}

    driver = next((n for n, v in end.items()
                   if n not in ('controller', 'estimator', 'recorder') and 'late_ticks' in v),
                  None)
    return {'controller': counts('controller', LOOP_COUNTERS['controller']),
            'estimator': counts('estimator', LOOP_COUNTERS['estimator']),
            'lost': {k.split(' ', 1)[1]: count('recorder', k)
                     for k in sorted(end.get('recorder', {})) if k.startswith('lost ')},
            'driver': None if driver is None else
            {'node': driver, **counts(driver, LOOP_COUNTERS['driver'])}}


def loop_text(report: dict) -> str:
    """:func:`loop_report` in a line, ending with what to do when the loop was troubled
    (:data:`TROUBLE_SHARE`)."""
    c, e, d = report['controller'], report['estimator'], report['driver']
    lost = ', '.join(f'{t} {n}' for t, n in report['lost'].items() if n) or 'none'
    periods = c['estimates'] + c['skipped_estimates']
    text = (f"the loop: estimates skipped {c['skipped_estimates']} of {periods}, estimate stamp "
            f"jumps {c['estimate_jumps']}, estimator resets {e['resets']}, tip dropouts "
            f"{e['dropouts']}"
            + (f", refused for another task_dim {c['wrong_task_dim']}" if c['wrong_task_dim']
               else '')
            + f"; messages lost: {lost}")
    if d is not None:
        text += (f"; {d['node']}: late ticks {d['late_ticks']} of {d['ticks']}, stale ticks "
                 f"{d['stale_ticks']}"
                 + (f", clipped commands {d['clipped_commands']}" if d['clipped_commands']
                    else ''))
    if c['wrong_task_dim']:
        return text + ('. A node of another task_dim fed the controller (its log names it): '
                       'give it the model\'s')
    if c['estimates'] <= 0:
        return text + '. The controller answered no estimate: is the estimator running?'
    if d is not None and d['clipped_commands']:
        text += ('. The driver clipped commands: its bounds are narrower than the controller\'s '
                 '(its log names them); give the controller the driver\'s (input_lower / '
                 'input_upper), or train with them (--input-lower / --input-upper)')
    busy = (c['skipped_estimates'] > TROUBLE_SHARE * periods or e['resets']
            or c['estimate_jumps'] or e['dropouts']
            or (d is not None and (d['late_ticks'] > TROUBLE_SHARE * d['ticks']
                                   or d['stale_ticks'])))
    if busy:
        text += ('. A busy machine moves the score: give the loop its cores or --realtime '
                 '(docs/faults.md)')
    return text


class Settings:
    """What ``params.yaml`` tells the deployment (module doc).

    Raises:
        ValueError: the file is missing, not YAML, or lacks a section or key the deployment
            needs (the message names the file and the key).
    """

    def __init__(self, path: Path) -> None:
        if not path.is_file():
            hint = ''
            if (path.parent / 'metrics.json').is_file():    # training ran there and wrote none
                hint = (': training judged that model not fit to control (exit status 3); its '
                        'output and metrics.json\'s "fitness" say why')
            raise ValueError(f'--params {path}: no such file{hint}')
        try:
            data = yaml.safe_load(path.read_text(encoding='utf-8'))
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise ValueError(f'--params {path}: not YAML ({exc})') from None
        sections = {}
        for node in ('estimator', 'controller', 'trajectory'):
            section = (data or {}).get(SECTION.format(node)) if isinstance(data, dict) else None
            values = section.get('ros__parameters') if isinstance(section, dict) else None
            if not isinstance(values, dict):
                raise ValueError(f'--params {path}: no {SECTION.format(node)} ros__parameters '
                                 'section (the file tools.learning.train writes has one per '
                                 'node)')
            sections[node] = values
        self.path = path
        ctrl, plan = sections['controller'], sections['trajectory']
        names = plan.get('finger_names', ctrl.get('finger_names'))
        if not (isinstance(names, list) and 1 <= len(names) <= 4
                and all(isinstance(n, str) and n for n in names)):
            raise ValueError(f'--params {path}: finger_names must be a list of 1 to 4 names, '
                             f'got {names!r}')
        self.finger_names = names
        missing = [k for k in PLAN_TIMES if k not in plan]
        if missing:
            raise ValueError(f'--params {path}: the trajectory section has no {", ".join(missing)}'
                             ' (the plan\'s length; train again, or add them)')
        times = [plan[k] for k in PLAN_TIMES]
        if not all(isinstance(t, (int, float)) and math.isfinite(t) and t >= 0 for t in times):
            raise ValueError(f'--params {path}: {", ".join(PLAN_TIMES)} must be numbers >= 0 s, '
                             f'got {times!r}')
        self.plan_seconds = float(sum(times))
        self.rest_seconds = float(plan['t_start'])
        self.d = plan.get('task_dim', 2)
        if self.d not in (2, 3) or isinstance(self.d, bool):
            raise ValueError(f'--params {path}: the trajectory section\'s task_dim must be 2 or 3 '
                             f'(the tip\'s coordinates), got {self.d!r}')
        try:
            shape = _model_shape(ctrl)
        except ShapeError as exc:
            raise ValueError(f'--params {path}: the controller\'s {exc}') from None
        for node, section in (('estimator', sections['estimator']), ('trajectory', plan)):
            d = section.get('task_dim', 2)
            if shape is not None and d != shape.d:
                raise ValueError(f'--params {path}: the {node} section\'s task_dim is {d!r}, the '
                                 f'model at model_path has {shape.d}-D tips; give task_dim '
                                 f'{shape.d} (train writes it)')
        close = plan.get('close_distance')
        side = plan.get('side_distance', 0.0) if self.d == 2 and 'close_path' not in plan else 0.0
        if not (isinstance(close, (int, float)) and isinstance(side, (int, float))
                and math.hypot(close, side) > 0):
            raise ValueError(f'--params {path}: the trajectory section needs close_distance > 0 '
                             f'(the travel scored against), got {close!r}')
        self.travel = float(math.hypot(close, side))
        try:
            self.bounds = controller_bounds(ctrl, path, 2 if shape is None else shape.m)
        except (ShapeError, KeyError, TypeError) as exc:
            raise ValueError(f'--params {path}: the controller\'s bounds: {exc}') from None


def _model_shape(ctrl: dict) -> FingerShape | None:
    """The shape of the model at the controller section's ``model_path`` (None without one).

    Raises:
        ShapeError: the model file does not load (naming ``model_path`` and the file).
    """
    if not ctrl.get('model_path'):
        return None
    from soft_gripper_sdre.learning.model import ModelFileError, read_checkpoint
    try:
        return read_checkpoint(Path(ctrl['model_path']))['shape']
    except ModelFileError as exc:
        raise ShapeError(f'model_path: {exc}') from None


def controller_bounds(ctrl: dict, path: Path, m: int | None = None) -> InputBounds:
    """The bounds the controller section ``ctrl`` commands within: its ``input_lower`` and
    ``input_upper``, or ±``torque_limit`` on each of the model's ``m`` inputs (None: the
    checkpoint's at ``model_path``, the hand's two torques without one).

    Raises:
        ShapeError: bounds that cannot be used, or a ``model_path`` that does not load.
    """
    if 'input_lower' in ctrl or 'input_upper' in ctrl:
        lower, upper = ctrl['input_lower'], ctrl['input_upper']
        return InputBounds.parse(lower, upper, len(lower), f'{path}: input_lower/input_upper')
    limit = ctrl['torque_limit']
    if not (isinstance(limit, (int, float)) and limit > 0):
        raise ShapeError(f'torque_limit must be > 0, got {limit!r}')
    if m is None:
        shape = _model_shape(ctrl)
        m = 2 if shape is None else shape.m
    return InputBounds.symmetric(float(limit), m)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.deploy',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--params', type=Path, required=True,
                    help='the params.yaml training wrote (tools.learning.train --out DIR)')
    ap.add_argument('--law', default='sdre_ff', help='the control law (default: %(default)s)')
    ap.add_argument('--out', type=Path, default=None,
                    help='output directory, must not exist (default: deploy_<law> beside '
                         '--params)')
    ap.add_argument('--tail', type=float, default=1.0,
                    help='seconds recorded after the plan ends (default: %(default)s)')
    ap.add_argument('--startup-timeout', type=float, default=120.0,
                    help='seconds for the loop to come up and the plan to start '
                         '(default: %(default)s)')
    ap.add_argument('--realtime', type=int, default=0, metavar='PRIORITY',
                    help='run the loop\'s process (the estimator and the controller) under '
                         'SCHED_FIFO at this priority (1 to 98, behind chrt -f; default: ordinary '
                         'scheduling): on time on a busy machine; needs root, CAP_SYS_NICE or an '
                         'rtprio limit (docs/performance.md "Real-time priority")')
    ap.add_argument('--cpu', type=int, default=None, metavar='N',
                    help='run the loop\'s process on CPU N (behind taskset -c N), so it finds its '
                         'caches as it left them every period; keep the driver and other work '
                         'off that CPU (docs/performance.md "Cores"; default: any CPU)')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: the environment\'s)')
    return ap


def check(a: argparse.Namespace) -> tuple[Settings | None, str | None]:
    """The deployment's settings, or what is wrong with the arguments."""
    from soft_gripper_sdre.control.laws import GRAPH_LAWS
    if a.law not in GRAPH_LAWS:
        return None, f'--law: unknown law {a.law!r}; known: {", ".join(GRAPH_LAWS)}'
    if not (math.isfinite(a.tail) and 0 <= a.tail <= 600):
        return None, f'--tail must be in [0, 600] s, got {a.tail}'
    if not (math.isfinite(a.startup_timeout) and 1 <= a.startup_timeout <= 3600):
        return None, f'--startup-timeout must be in [1, 3600] s, got {a.startup_timeout}'
    if a.domain_id is not None and not 0 <= a.domain_id <= 232:
        return None, f'--domain-id must be in [0, 232], got {a.domain_id}'
    if a.realtime:
        from soft_gripper_sdre.nodes.scheduling import fifo_problem
        problem = fifo_problem(a.realtime)
        if problem:
            return None, f'--realtime {a.realtime}: {problem}'
    import os
    if a.cpu is not None:
        allowed = sorted(os.sched_getaffinity(0))
        if a.cpu not in allowed:
            return None, (f'--cpu {a.cpu}: not a CPU this process may run on '
                          f'({", ".join(map(str, allowed))})')
        from soft_gripper_sdre.nodes.graph import taskset_problem
        problem = taskset_problem()
        if problem:
            return None, f'--cpu {a.cpu}: {problem}'
    if a.domain_id is None and not re.fullmatch(r'\d{0,3}', os.environ.get('ROS_DOMAIN_ID', '')):
        return None, (f'ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]!r} is not a domain number; '
                      'set it to one, or give --domain-id')
    try:
        settings = Settings(a.params)
    except ValueError as exc:
        return None, str(exc)
    if a.out is None:
        a.out = a.params.resolve().parent / f'deploy_{a.law}'
    if a.out.exists():
        return None, f'--out {a.out} exists already (nothing is overwritten)'
    return settings, None


def _env(domain_id: int | None) -> dict:
    """The nodes' environment: the caller's DDS settings as they are (the driver may run on
    another host: no discovery range is imposed), the domain ``--domain-id`` or the caller's
    (0 by default, as ROS), and the graph's pinned kernels."""
    import os

    from soft_gripper_sdre.tools.graph.procs import ros_env
    if domain_id is None:
        domain_id = int(os.environ.get('ROS_DOMAIN_ID') or 0)
    env = ros_env(domain_id)
    env.pop('ROS_AUTOMATIC_DISCOVERY_RANGE')
    if 'ROS_AUTOMATIC_DISCOVERY_RANGE' in os.environ:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']
    return env


def deploy(a: argparse.Namespace, s: Settings) -> tuple[Path, dict]:
    """Start the loop, the recorder and the plan; once the plan has ended, return the bag and
    what the loop's nodes counted meanwhile (:func:`loop_report`, taken before they stop).

    Raises:
        RuntimeError: a node exited, or the loop or the plan did not start in time (named, with
            the end of its log).
    """
    from soft_gripper_sdre.nodes.graph import NodeSpec
    from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph
    env = _env(a.domain_id)
    bag = a.out / 'bag'
    params = s.path.resolve()
    fingers = {'finger_names': s.finger_names}

    def fail(graph: Graph, who: str, what: str) -> RuntimeError:
        return RuntimeError(f'{what}; last lines of {who}.log:\n{graph.procs[who].log_tail()}')

    def watch(graph: Graph) -> None:
        dead = [p.name for p in graph.procs.values() if not p.alive()]
        if dead:
            raise fail(graph, dead[0], f'{dead[0]} exited (status '
                                       f'{graph.procs[dead[0]].popen.returncode})')

    monitor = DiagnosticsMonitor(env, 'deploy_monitor')
    try:
        with Graph(env, a.out / 'logs') as graph:
            graph.start('recorder', {'output': str(bag), 'topics': TOPICS, **BEST_EFFORT})
            estimator = NodeSpec('estimator', 'estimator', params_file=params,
                                 parameters={**BEST_EFFORT, **fingers})
            graph.start_node(NodeSpec('controller', 'controller', params_file=params,
                                      parameters={'law': a.law, **fingers},
                                      hosted=(estimator,), realtime=a.realtime,
                                      cpus=() if a.cpu is None else (a.cpu,)))
            deadline = time.monotonic() + a.startup_timeout
            while not all(n in monitor.values for n in ('estimator', 'controller', 'recorder')):
                watch(graph)
                if time.monotonic() > deadline:
                    raise fail(graph, 'controller', 'the loop did not come up within '
                                                    f'--startup-timeout ({a.startup_timeout:g} s)')
                monitor.spin_until(lambda: False, 0.1)
            graph.start('trajectory', {**fingers, 'grasp_fingers': list(range(len(fingers[
                'finger_names']))), 'others': 'hold', **BEST_EFFORT}, params_file=params)
            while monitor.get('recorder', 'messages /grasp_reference') <= 0:
                watch(graph)
                if time.monotonic() > deadline:
                    raise fail(graph, 'trajectory', 'no plan recorded within --startup-timeout '
                                                    f'({a.startup_timeout:g} s)')
                monitor.spin_until(lambda: False, 0.1)
            end = time.monotonic() + s.plan_seconds + a.tail
            monitor.poll()
            at_start = monitor.snapshot()
            print(f'plan started: {s.plan_seconds:g} s, {len(s.finger_names)} finger(s) with '
                  f'{a.law}', flush=True)
            while time.monotonic() < end:
                watch(graph)
                monitor.spin_until(lambda: False, 0.1)
            report = loop_report(at_start, monitor.values)
            for name in ('trajectory', 'controller', 'recorder'):
                graph.stop(name)
    finally:
        monitor.close()
    return bag, report


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    settings, problem = check(a)
    if problem:
        ap.error(problem)
    from soft_gripper_sdre.analysis.run_score import ScoreError, score_run
    try:
        bag, loop = deploy(a, settings)
        score = score_run(bag, settings.travel, settings.bounds, settings.d,
                          settings.plan_seconds, settings.rest_seconds)
    except (RuntimeError, ScoreError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    score = {'law': a.law, 'params': str(settings.path), 'travel_m': settings.travel,
             'plan_seconds': settings.plan_seconds, **score, 'loop': loop}
    (a.out / 'score.json').write_text(json.dumps(score, indent=2))
    print(f'{a.law}: RMSE {score["rmse_mm"]} mm = {score["rmse_pct_of_travel"]} % of the '
          f'{1e3 * settings.travel:.3g} mm travel (on {score["tips_topic"]}); at a bound at rest '
          f'{100 * score["saturated_at_rest"]:.1f} %; {score["outside_bounds"]} of '
          f'{score["commands"]} commands outside the bounds; {a.out}', flush=True)
    print(loop_text(loop), flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
