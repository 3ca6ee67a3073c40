"""Record identification runs over the node graph: excitation node + simulator node + recorder.

    python -m soft_gripper_sdre.tools.graph.excite --out runs/bags/train --signals u1 u2 u3 x1 x2
    python -m soft_gripper_sdre.tools.graph.excite --out runs/bags/val --signals u4

For each signal a fresh graph is started (so every run begins from the settled finger, as
``tools.learning.collect``'s records do): the recorder (``tip_positions``, ``torque_commands``,
``/clock``, ``/diagnostics``), the excitation node playing the signal after ``--settle`` seconds of
zero torque, and the simulator in lockstep; the tool waits for the excitation node to finish, stops
the simulator, and stops the recorder once its count of tips holds still over two of its reports
(a loaded machine can leave it a second behind). ``OUT/<signal>/`` is the signal's rosbag2
directory and ``OUT/logs/<signal>/`` holds the node logs; ``tools.learning.train --bag OUT``
reads every bag in ``OUT``. ``--one-bag`` plays all signals in one run into
``OUT/<first signal>/`` instead.

``--amplitude`` scales every signal before ``--torque-limit`` clips it; ``--level auto`` lets the
excitation node choose the amplitude on the finger instead (probes aiming at ``--level-target`` ×
``--max-excursion``, docs/identification.md). The node logs the amplitude and the share of the
signals at the clip, and puts both in /diagnostics, which the bag records.

This is the recipe a robot follows with its own driver in place of the simulator node
(README "Use with your own gripper"). Arguments are checked before anything starts (exit 2); a
node that fails ends the tool with exit status 1, its log's last lines and no partial bag.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import shutil
import sys
import time

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.nodes.graph import NodeSpec, default_params_file
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.sim.signal_specs import SignalSpecError, resolve_signals
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env

#: the simulator's actuator limit [N·m]: the excitation's limit may not exceed it
SIM_LIMIT = SimConfig().torque_limit

RECORDED = ['tip_positions', 'torque_commands', '/clock', '/diagnostics']


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.excite',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, required=True,
                    help='directory of the bags (one per signal)')
    ap.add_argument('--signals', nargs='+', default=['u1', 'u2', 'u3', 'x1', 'x2'],
                    help='signals to play: built-in or from --spec-file (default: %(default)s)')
    ap.add_argument('--spec-file', type=Path, default=None,
                    help='YAML file of user-defined signals')
    ap.add_argument('--one-bag', action='store_true',
                    help='play every signal in one run and one bag')
    ap.add_argument('--settle', type=float, default=0.5,
                    help='zero torque before each signal [s] (default %(default)s)')
    ap.add_argument('--duration', type=float, default=None,
                    help='length of each signal [s] (default: its own)')
    ap.add_argument('--torque-limit', type=float, default=0.1, help='N·m (default %(default)s)')
    ap.add_argument('--amplitude', type=float, default=1.0,
                    help='scale on every signal before the clip, --level fixed '
                         '(default %(default)s)')
    ap.add_argument('--level', choices=('fixed', 'auto'), default='fixed',
                    help='fixed: play at --amplitude; auto: the node chooses the amplitude by '
                         'probes (needs --max-excursion) (default %(default)s)')
    ap.add_argument('--max-excursion', type=float, default=0.0, metavar='MM',
                    help='stop a run whose tip moves further than this from rest [mm] (0 = off; '
                         '--level auto aims at a fraction of it) (default %(default)s)')
    ap.add_argument('--level-target', type=float, default=0.5,
                    help='--level auto: the peak excursion aimed at, as a fraction of '
                         '--max-excursion (default %(default)s)')
    ap.add_argument('--scene', choices=('finger', 'hand'), default='finger',
                    help='one finger mounted as in the hand (as tools.learning.collect), or the '
                         'hand without its cube')
    ap.add_argument('--finger', type=int, default=-1,
                    help='hand scene: excite only this finger (default: all)')
    ap.add_argument('--noise', type=float, default=0.05, metavar='MM',
                    help='tip measurement noise σ [mm] (default %(default)s)')
    ap.add_argument('--seed', type=int, default=0, help='noise seed of the first run (+1 per run)')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: env or random)')
    ap.add_argument('--timeout', type=float, default=600.0, help='wall-clock limit per run [s]')
    return ap


def argument_problem(a: argparse.Namespace) -> str | None:
    """What is wrong with the arguments, or None (checked before anything starts)."""
    try:
        resolve_signals(a.signals, a.spec_file, a.duration)
    except SignalSpecError as exc:
        return str(exc)
    if not 0 <= a.settle <= 600:
        return f'--settle must be in [0, 600] s, got {a.settle}'
    if a.duration is not None and not 0 < a.duration <= 3600:
        return f'--duration must be in (0, 3600] s, got {a.duration}'
    if not 0 < a.torque_limit <= SIM_LIMIT:
        return (f'--torque-limit must be in (0, {SIM_LIMIT:g}] N·m (the simulator clips to '
                f'±{SIM_LIMIT:g}), got {a.torque_limit}')
    if not 1e-6 <= a.amplitude <= 100:
        return f'--amplitude must be in [1e-6, 100], got {a.amplitude}'
    if not 0 <= a.max_excursion <= 1000:
        return f'--max-excursion is in mm, from 0 (off) to 1000, got {a.max_excursion}'
    if not 0.05 <= a.level_target <= 1:
        return (f'--level-target must be in [0.05, 1] (a fraction of --max-excursion), '
                f'got {a.level_target}')
    if a.level == 'auto':
        if a.max_excursion <= 0:
            return ('--level auto needs --max-excursion > 0 (it aims at --level-target × '
                    '--max-excursion)')
        if a.settle <= 0:
            return '--level auto needs --settle > 0 (the rest pose the probes are measured from)'
        if a.amplitude != 1.0:
            return '--amplitude is chosen by --level auto; leave it out, or use --level fixed'
    if not -1 <= a.finger <= 3 or (a.scene == 'finger' and a.finger > 0):
        return f'--finger must be -1 (all) or 0..3 (0 in the finger scene), got {a.finger}'
    if not 0 <= a.noise <= 10:
        return f'--noise is σ in mm, from 0 to 10, got {a.noise}'
    if not 0 <= a.seed < 2**31 - 64:
        return f'--seed must be in [0, 2^31 - 64), got {a.seed}'
    if a.domain_id is not None and not 0 <= a.domain_id <= 232:
        return f'--domain-id must be in [0, 232], got {a.domain_id}'
    if not a.timeout > 0:
        return f'--timeout must be > 0 s, got {a.timeout}'
    runs = [a.signals[0]] if a.one_bag else a.signals
    if len(set(runs)) != len(runs):
        return 'each signal may appear once (one bag per signal); use --one-bag to repeat one'
    taken = [str(a.out / name) for name in runs if (a.out / name).exists()]
    if taken:
        return f'bag directories exist already (a bag is never overwritten): {", ".join(taken)}'
    return None


def record_run(out: Path, signals: list[str], a: argparse.Namespace, seed: int, env: dict) -> Path:
    """One graph run playing ``signals`` into the bag ``out/<signals[0]>``.

    Raises:
        RuntimeError: a node failed, the graph did not connect or the run timed out (no bag is
            left).
    """
    bag, logs = out / signals[0], out / 'logs' / signals[0]
    names = [FINGER_NAMES[0]] if a.scene == 'finger' else list(FINGER_NAMES)
    excitation = {'signals': signals, 'settle_time': a.settle, 'torque_limit': a.torque_limit,
                  'finger_names': names, 'finger': a.finger, 'amplitude': a.amplitude,
                  'level': a.level, 'level_target': a.level_target,
                  'max_excursion': a.max_excursion * 1e-3,
                  # the simulator's start rule (min_tip_subscribers 2) holds its first tips until
                  # the recorder's reader is matched, so the run starts at t = 0 as the in-process
                  # collection does, without waiting for the recorder's report
                  'recorder_node': ''}
    if a.duration is not None:
        excitation['duration'] = a.duration
    if a.spec_file is not None:
        excitation['spec_file'] = str(a.spec_file.resolve())
    simulator = {'scene': a.scene, 'noise_std': a.noise * 1e-3, 'seed': seed,
                 'min_tip_subscribers': 2, 'finger_names': names,
                 'hand_fingers': list(range(len(names)))}
    if a.scene == 'hand':
        simulator['with_cube'] = False
    monitor = DiagnosticsMonitor(env, f'excite_monitor_{signals[0]}')
    try:
        with Graph(env, logs) as graph:
            graph.start('recorder', {'output': str(bag), 'topics': RECORDED})
            graph.start('excitation', excitation)
            deadline = time.monotonic() + 60.0
            while monitor.get('recorder', 'publishers /torque_commands') < 1:
                dead = [p.name for p in graph.procs.values() if not p.alive()]
                if dead or time.monotonic() > deadline:
                    who = dead[0] if dead else 'recorder'
                    raise RuntimeError('the graph did not connect '
                                       f'({who} {"exited" if dead else "sees no excitation"}); '
                                       f'last lines of {who}.log:\n{graph.procs[who].log_tail()}')
                monitor.poll()
                time.sleep(0.05)
            graph.start_node(NodeSpec('simulator', 'simulator',
                                      params_file=default_params_file('simulator'),
                                      parameters=simulator))
            code = graph.wait('excitation', a.timeout, monitor.poll)
            if code != 0:
                dead = next((p.name for p in graph.procs.values()
                             if not p.alive() and p.name != 'excitation'),
                            'excitation')
                why = 'timed out' if code is None and dead == 'excitation' else f'{dead} failed'
                raise RuntimeError(f'the run of {", ".join(signals)} {why}; '
                                   f'last lines of {dead}.log:\n'
                                   f'{graph.procs[dead].log_tail()}')
            graph.stop('simulator')
            # no tip comes any more: the recorder, which a loaded machine can leave behind, is
            # stopped once it has taken every one
            if not monitor.wait_steady('recorder', 'messages /tip_positions'):
                raise RuntimeError(f'the run of {", ".join(signals)}: the recorder did not '
                                   'settle on its last tips; last lines of recorder.log:\n'
                                   f'{graph.procs["recorder"].log_tail()}')
    except RuntimeError:
        shutil.rmtree(bag, ignore_errors=True)
        raise
    finally:
        monitor.close()
    return bag


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    problem = argument_problem(a)
    if problem:
        ap.error(problem)
    a.out.mkdir(parents=True, exist_ok=True)
    env = ros_env(a.domain_id)
    runs = [a.signals] if a.one_bag else [[name] for name in a.signals]
    for i, signals in enumerate(runs):
        t0 = time.monotonic()
        try:
            bag = record_run(a.out, signals, a, a.seed + i, env)
        except RuntimeError as exc:
            print(f'error: {exc}', file=sys.stderr)
            return 1
        print(f'{bag}: {", ".join(signals)} recorded in {time.monotonic() - t0:.1f} s wall',
              flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
