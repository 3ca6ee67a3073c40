"""The README's own-gripper recipe, end to end, on a gripper the package has never seen.

    python -m soft_gripper_sdre.tools.graph.foreign --plant tendon3 --out runs/foreign/tendon3
    python -m soft_gripper_sdre.tools.graph.foreign --plant stiff2 --out runs/foreign/stiff2
    python -m soft_gripper_sdre.tools.graph.foreign --plant pneumatic1 --out runs/foreign/pneumatic1
    python -m soft_gripper_sdre.tools.graph.foreign --plant trunk3 --out runs/foreign/trunk3

The gripper is the ``plant_driver`` node (two fingers of a preset of
:mod:`soft_gripper_sdre.sim.plants.presets`, served like a lab's driver: wall-clock loop,
best-effort tips stamped with wall time, jitter, dropped messages, noise): ``tendon3`` and
``stiff2`` (two torques, a planar tip), ``pneumatic1`` (one chamber, 0 to 60 kPa, a planar tip, at
100 Hz) and ``trunk3`` (three pull-only tendons, 0 to 4 N, a 3-D tip, at 250 Hz). Every step is
what README "Use with your own gripper" tells a user to run, as separate processes over DDS,
with the settings the tools produce and nothing tuned by hand (``--identify-only`` stops after
step 1; ``--bags`` reuses an earlier run's recordings and starts at step 2); a lab with
one-sided actuators gives their bounds (``input_lower``/``input_upper``) to the excitation, and
every lab gives training its driver's bounds (``--input-lower``/``--input-upper``), as the
preset's:

1. **identify** — recorder + excitation node, one bag per signal (u1 x1 x2 b1 b2 and the
   validation signal u4, on trunk3's three tendons staggered by a third of its period each so
   that it bends the segment, and on flexor2's two by half of it so that the pair moves the
   tip: :func:`~soft_gripper_sdre.sim.signals.u4_delays`), each with
   ``level:=auto`` (its amplitude found by probing the finger with the signal's start to half
   of ``max_excursion``; the first probe at u1's amplitude, ``level_start``) and the driver's
   limit (``torque_limit`` or the one-sided bounds);
2. **train** — ``tools.learning.train --bag … --val-bag … --input-lower … --input-upper …``
   (the driver's bounds; ``--task-dim 3`` for trunk3's 3-D tip): the model, its verdict and
   ``params.yaml``, whose loop stays within those bounds;
3. **deploy** — estimator, controller and trajectory node on ``params.yaml``: both fingers close
   along the move the settings were checked for (the way the finger moved most in the
   identification data, by at most half its reach that way: a learned model is only known where
   the data went; a one-input finger along the curve of the model's equilibria,
   ``close_path``), the recorder; once per law (``--laws``);
4. **score** — from each deployment's bag: the RMSE of the driver's true tips
   (``true_tip_positions``, in the tip's d coordinates) against the plan, as a share of the
   travel, the share of commands at a bound (not an input's rest bound: a vented chamber, a slack
   tendon) while the plan holds at rest, and the commands outside the controller's bounds
   (``params.yaml``) or the gripper's, which must be none; and what the loop's nodes counted
   over the plan (``loop``: skipped estimates, resets, lost messages, the driver's late and
   stale ticks: :func:`~soft_gripper_sdre.tools.graph.deploy.loop_report`).

``OUT/metrics.json`` holds every figure, ``OUT/<step>/logs`` the node logs. Arguments are checked
before anything starts (exit 2); a failed step ends the tool with exit status 1 and names it.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import fcntl
import json
import os
from pathlib import Path
import random
import re
import subprocess
import sys
import time

import yaml

from soft_gripper_sdre.sim.plants.presets import RATES, gripper_bounds, gripper_shape
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.tools.graph.deploy import loop_report, loop_text
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env
from soft_gripper_sdre.tools.learning import NOT_FIT


@dataclass(frozen=True)
class Setup:
    """What a lab chooses for its gripper: the driver's rate and how far the excitation may move
    a tip (SI)."""

    rate: float
    max_excursion: float


#: the foreign grippers, as their lab would set them up (the rate its driver serves; a
#: excursion well within the finger's reach: pneumatic1 24/18 mm at 60 kPa, trunk3 27/18 mm at
#: 4 N on one tendon)
SETUPS = {'tendon3': Setup(rate=RATES['tendon3'], max_excursion=0.016),
          'stiff2': Setup(rate=RATES['stiff2'], max_excursion=0.008),
          'pneumatic1': Setup(rate=RATES['pneumatic1'], max_excursion=0.016),
          'trunk3': Setup(rate=RATES['trunk3'], max_excursion=0.016),
          'flexor2': Setup(rate=RATES['flexor2'], max_excursion=0.016)}
FINGERS = ['index', 'thumb']
TRAIN_SIGNALS = ['u1', 'x1', 'x2', 'b1', 'b2']
#: the grasp: trajectory node defaults (hold 0.5 s at rest, close 2 s, hold 1 s, open 2 s)
T_START, GRASP_SECONDS = 0.5, 5.5
DEPLOY_TOPICS = ['tip_positions', 'true_tip_positions', 'state_estimate', 'grasp_reference',
                 'torque_commands']
BEST_EFFORT = {'tips_reliability': 'best_effort'}
#: the ROS domain IDs a run may take, and the lock file each is held by while in use (the test
#: sessions' own: test/conftest.py)
DOMAIN_IDS = (*range(1, 102), *range(215, 233))
DOMAIN_LOCK = '/tmp/soft_gripper_sdre_ros_domain_{}.lock'


def claim_domain(given: int | None) -> tuple[int | None, int | None]:
    """(the ROS domain ID of the run, the descriptor of its held lock): ``given`` or the
    environment's ``ROS_DOMAIN_ID`` as they are; else the first of :data:`DOMAIN_IDS`, in random
    order, whose lock no test session or other run holds, so that no other graph on the machine
    talks into this one. The lock goes with this process. (None, None): every one is taken."""
    if given is not None:
        return given, None
    if os.environ.get('ROS_DOMAIN_ID', '').isdigit() and int(os.environ['ROS_DOMAIN_ID']):
        return int(os.environ['ROS_DOMAIN_ID']), None
    ids = list(DOMAIN_IDS)
    random.SystemRandom().shuffle(ids)
    for domain_id in ids:
        try:
            fd = os.open(DOMAIN_LOCK.format(domain_id), os.O_RDONLY | os.O_CREAT, 0o644)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return domain_id, fd
    return None, None


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.graph.foreign',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--plant', choices=sorted(SETUPS), required=True, help='the foreign gripper')
    ap.add_argument('--out', type=Path, required=True, help='output directory (must not exist)')
    ap.add_argument('--laws', nargs='+', default=['sdre_ff', 'sdre'],
                    help='laws deployed in turn (default: %(default)s)')
    ap.add_argument('--seed', type=int, default=0, help='the driver\'s noise seed (+1 per run)')
    ap.add_argument('--epochs', type=int, default=None,
                    help='training epochs (default: the preset)')
    ap.add_argument('--bags', type=Path, default=None,
                    help='skip step 1: train on the bags an earlier run wrote (its OUT/bags, with '
                         'train/ and val/)')
    ap.add_argument('--identify-only', action='store_true',
                    help='step 1 only: record the bags into OUT/bags and stop (train on them '
                         'later with --bags OUT/bags)')
    ap.add_argument('--rollout-epochs', type=int, default=None,
                    help='simulation-stage epochs of training (default: the preset)')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: env or random)')
    return ap


def argument_problem(a: argparse.Namespace) -> str | None:
    """What is wrong with the arguments, or None."""
    from soft_gripper_sdre.control.laws import GRAPH_LAWS
    bad = [law for law in a.laws if law not in GRAPH_LAWS]
    if bad:
        return f'--laws: unknown law(s) {bad}; known: {", ".join(GRAPH_LAWS)}'
    if a.out.exists():
        return f'--out {a.out} exists already (nothing is overwritten)'
    if not 0 <= a.seed < 2**31 - 64:
        return f'--seed must be in [0, 2^31 - 64), got {a.seed}'
    if a.epochs is not None and a.epochs < 1:
        return f'--epochs must be >= 1, got {a.epochs}'
    if a.identify_only and a.bags is not None:
        return '--identify-only records new bags: it takes no --bags'
    if a.bags is not None and not all((a.bags / d).is_dir() for d in ('train', 'val')):
        return f'--bags {a.bags} has no train/ and val/ bag directories'
    if a.rollout_epochs is not None and a.rollout_epochs < 0:
        return f'--rollout-epochs must be >= 0, got {a.rollout_epochs}'
    if a.domain_id is not None and not 0 <= a.domain_id <= 232:
        return f'--domain-id must be in [0, 232], got {a.domain_id}'
    return None


def _driver(a: argparse.Namespace, seed: int) -> dict:
    return {'plant': a.plant, 'finger_names': FINGERS, 'rate': SETUPS[a.plant].rate, 'seed': seed}


def actuator_bounds(plant: str) -> dict:
    """What a lab with one-sided actuators tells the excitation: the preset's bounds as
    ``input_lower``/``input_upper`` (:func:`driver_bounds`); nothing for the symmetric torque
    grippers (their excitation takes ``torque_limit``)."""
    return {} if gripper_bounds(plant).symmetric_limit is not None else driver_bounds(plant)


def driver_bounds(plant: str) -> dict:
    """What a lab tells training: its driver's bounds, the preset's, as ``input_lower`` /
    ``input_upper`` (the loop training derives stays within them)."""
    bounds = gripper_bounds(plant)
    return {'input_lower': [float(v) for v in bounds.lower],
            'input_upper': [float(v) for v in bounds.upper]}


def excitation_limit(plant: str) -> dict:
    """The excitation's limit, the driver's: the one-sided bounds (:func:`actuator_bounds`), or
    the torque grippers' ``torque_limit`` (what the driver clamps at)."""
    limit = gripper_bounds(plant).symmetric_limit
    return {'torque_limit': float(limit)} if limit is not None else actuator_bounds(plant)


def _fail(graph: Graph, who: str, what: str) -> RuntimeError:
    return RuntimeError(f'{what}; last lines of {who}.log:\n{graph.procs[who].log_tail()}')


def excite(a: argparse.Namespace, env: dict, bag: Path, signals: list[str], level: dict,
           seed: int) -> str:
    """One identification run into ``bag``; returns the excitation node's log."""
    setup = SETUPS[a.plant]
    monitor = DiagnosticsMonitor(env, f'foreign_monitor_{bag.name}')
    with Graph(env, bag.parent / 'logs' / bag.name) as graph:
        graph.start('plant_driver', _driver(a, seed), params_file=None)
        graph.start('recorder', {'output': str(bag), 'topics': ['tip_positions', 'torque_commands'],
                                 **BEST_EFFORT})
        # as a user starts the excitation once the recorder runs: the bag then holds the settle
        # phase
        hearing = monitor.spin_until(lambda: monitor.get('recorder', 'messages /tip_positions') > 0,
                                     60.0)
        monitor.close()
        if not hearing:
            raise _fail(graph, 'recorder',
                        f'identification run {bag.name}: the recorder hears no tips')
        graph.start('excitation', {'signals': signals, 'finger_names': FINGERS,
                                   'max_excursion': setup.max_excursion, 'tips_timeout': 5.0,
                                   **BEST_EFFORT, **level, **excitation_limit(a.plant)})
        code = graph.wait('excitation', 600.0)
        if code != 0:
            who = next((p.name for p in graph.procs.values()
                        if not p.alive() and p.name != 'excitation'), 'excitation')
            raise _fail(graph, who, f'identification run {bag.name}: {who} failed (exit {code})')
        return graph.procs['excitation'].log_path.read_text(encoding='utf-8')


def deploy(a: argparse.Namespace, env: dict, out: Path, params: Path, law: str,
           seed: int) -> tuple[Path, dict]:
    """The grasp with ``law`` on ``params``, closing by the move they were checked on (their
    trajectory section); returns the bag and what the loop's nodes counted from the plan's start
    to its end (:func:`~soft_gripper_sdre.tools.graph.deploy.loop_report`)."""
    bag = out / 'bag'
    monitor = DiagnosticsMonitor(env, f'foreign_monitor_{law}')
    try:
        with Graph(env, out / 'logs') as graph:
            graph.start('plant_driver', _driver(a, seed), params_file=None)
            graph.start('recorder', {'output': str(bag), 'topics': DEPLOY_TOPICS, **BEST_EFFORT})
            graph.start('estimator', BEST_EFFORT, params_file=params)
            graph.start('controller', {'law': law}, params_file=params)
            ready = monitor.spin_until(lambda: all(n in monitor.values
                                                   for n in ('estimator', 'controller')), 120.0)
            if not ready:
                dead = next((p.name for p in graph.procs.values() if not p.alive()), 'controller')
                raise _fail(graph, dead,
                            f'deploying {law}: the estimator and controller did not come up')
            graph.start('trajectory', {'finger_names': FINGERS, 'grasp_fingers': [0, 1],
                                       'others': 'hold', **BEST_EFFORT}, params_file=params)
            end = time.monotonic() + GRASP_SECONDS + 3.0
            at_start = at_end = None
            while time.monotonic() < end:
                dead = [p.name for p in graph.procs.values() if not p.alive()]
                if dead:
                    raise _fail(graph, dead[0], f'deploying {law}: {dead[0]} exited')
                monitor.poll()
                if at_start is None and monitor.get('recorder', 'messages /grasp_reference') > 0:
                    at_start = monitor.snapshot()
                    plan_end = time.monotonic() + GRASP_SECONDS
                elif at_start is not None and at_end is None and time.monotonic() > plan_end:
                    at_end = monitor.snapshot()
                time.sleep(0.1)
    finally:
        monitor.close()
    return bag, loop_report(at_start or {}, at_end or monitor.values)


def controller_bounds(params: Path, m: int) -> InputBounds:
    """The bounds the controller of ``params`` commands within: its ``input_lower`` and
    ``input_upper``, or ±``torque_limit`` on each of the ``m`` inputs."""
    ctrl = yaml.safe_load(params.read_text())['/**/controller']['ros__parameters']
    if 'input_lower' in ctrl:
        return InputBounds.parse(ctrl['input_lower'], ctrl['input_upper'], m,
                                 f'{params}: input_lower/input_upper')
    return InputBounds.symmetric(ctrl['torque_limit'], m)


def score(bag: Path, travel: float, bounds: InputBounds, d: int = 2,
          plant_bounds: InputBounds | None = None) -> dict:
    """Tracking of the deployed grasp from its bag (module doc;
    :func:`~soft_gripper_sdre.analysis.run_score.score_run` over the grasp): ``bounds`` the
    controller's, ``plant_bounds`` the gripper's (None: the controller's), ``d`` the tip's
    coordinates."""
    from soft_gripper_sdre.analysis.run_score import ScoreError, score_run
    try:
        return score_run(bag, travel, bounds, d, GRASP_SECONDS, T_START, plant_bounds)
    except ScoreError as exc:
        raise RuntimeError(str(exc)) from None


def chosen_amplitude(log: str) -> float | None:
    """The amplitude the excitation node's level search chose, from its log line ('…;
    amplitude A for 8 mm' or, capped by the input bounds, '…; amplitude A (the largest the input
    bounds allow) for about …'), or None."""
    found = re.search(r'; amplitude ([0-9.eE+-]+) (?:\([^)]*\) )?for', log)
    return None if found is None else float(found.group(1))


def identify(a: argparse.Namespace, env: dict, bags: Path) -> dict:
    """Step 1 (module doc): one bag per signal, each at its own level (``level:=auto``: probes
    of the signal's start), the first probe of each at u1's amplitude."""
    t0 = time.monotonic()
    amplitudes, level = {}, {'level': 'auto'}
    for i, signal in enumerate(TRAIN_SIGNALS + ['u4']):
        bag = bags / ('train' if signal != 'u4' else 'val') / signal
        log = excite(a, env, bag, [signal], level, a.seed + i)
        amplitude = chosen_amplitude(log)
        if amplitude is None:
            raise RuntimeError(f'the excitation node did not report the amplitude it chose for '
                               f'{signal}')
        amplitudes[signal] = amplitude
        level = {'level': 'auto', 'level_start': amplitudes[TRAIN_SIGNALS[0]]}
    print(f'identified at amplitudes {amplitudes} in {time.monotonic() - t0:.0f} s', flush=True)
    return {'amplitude': amplitudes, 'wall_s': round(time.monotonic() - t0, 1)}


def train_command(a: argparse.Namespace, bags: Path, out: Path) -> list[str]:
    """The README's training command for ``a.plant`` on ``bags``' train/ and val/ into
    ``out/model``: ``--task-dim 3`` for a 3-D tip, the driver's bounds (:func:`driver_bounds`),
    and ``--epochs``/``--rollout-epochs`` when given."""
    cmd = [sys.executable, '-m', 'soft_gripper_sdre.tools.learning.train',
           '--bag', str(bags / 'train'),
           '--val-bag', str(bags / 'val'), '--out', str(out / 'model')]
    if gripper_shape(a.plant).d == 3:
        cmd += ['--task-dim', '3']
    bounds = driver_bounds(a.plant)
    cmd += ['--input-lower', *map(repr, bounds['input_lower']),
            '--input-upper', *map(repr, bounds['input_upper'])]
    if a.epochs is not None:
        cmd += ['--epochs', str(a.epochs)]
    if a.rollout_epochs is not None:
        cmd += ['--rollout-epochs', str(a.rollout_epochs)]
    return cmd


def train(a: argparse.Namespace, env: dict, bags: Path, out: Path) -> tuple[dict, str]:
    """Step 2 (module doc): :func:`train_command` run, its output kept in ``out/train.log``;
    returns the model's ``metrics.json`` and the tool's stdout."""
    cmd = train_command(a, bags, out)
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    (out / 'train.log').write_text(done.stdout + done.stderr, encoding='utf-8')
    if done.returncode not in (0, NOT_FIT):         # NOT_FIT: settings_file says why
        raise RuntimeError(f'training failed (exit {done.returncode}):\n'
                           f'{done.stderr[-2000:]}')
    return json.loads((out / 'model' / 'metrics.json').read_text()), done.stdout


def settings_file(out: Path, trained: dict) -> Path:
    """The ``params.yaml`` training wrote into ``out/model``; a RuntimeError saying why (from its
    ``metrics.json``, ``trained``) if it wrote none."""
    params = out / 'model' / 'params.yaml'
    if not params.exists():
        why = trained['fitness']['reasons'] or [
            (trained.get('derived_settings') or {}).get('reason') or
            'the model is fit to control, but no controller setting passed the closed-loop '
            'check on it (metrics.json: derived_settings)']
        raise RuntimeError('training wrote no params.yaml: ' + '; '.join(why))
    return params


def move_text(facts: dict) -> str:
    """The checked move of the derived settings' ``facts`` in words."""
    travel = 1e3 * float(facts['travel'])
    if facts.get('path'):
        return f'{travel:.2f} mm along the curve of the model\'s equilibria'
    if facts.get('axis'):
        return f'{travel:.2f} mm along ({", ".join(f"{v:.3f}" for v in facts["axis"])})'
    return f'{travel:.2f} mm travel at {facts["direction"]:.0f}°'


def deploy_laws(a: argparse.Namespace, env: dict, out: Path, params: Path, facts: dict,
                metrics: dict) -> None:
    """Steps 3 and 4 (module doc) for each of ``--laws`` in turn on ``params``, along the move
    the settings were checked for (``facts``, from the training's derived settings): deploy,
    score, print. ``metrics['deploy']`` takes each law's score as it comes."""
    shape = gripper_shape(a.plant)
    bounds = controller_bounds(params, shape.m)
    travel = float(facts['travel'])
    metrics['deploy'] = {'travel': travel, 'direction_deg': facts['direction'],
                         'bounds': bounds.to_record()}
    for i, law in enumerate(a.laws):
        bag, loop = deploy(a, env, out / f'deploy_{law}', params, law, a.seed + 10 + i)
        s = {**score(bag, travel, bounds, shape.d, gripper_bounds(a.plant)), 'loop': loop}
        metrics['deploy'][law] = s
        print(f'{law}: RMSE {s["rmse_mm"]} mm = {s["rmse_pct_of_travel"]} % of the '
              f'{move_text(facts)}; at a bound at rest {100 * s["saturated_at_rest"]:.1f} %; '
              f'{s["outside_bounds"]} of {s["commands"]} commands outside the bounds',
              flush=True)
        print(loop_text(loop), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    problem = argument_problem(a)
    if problem:
        ap.error(problem)
    domain_id, _lock = claim_domain(a.domain_id)
    env = ros_env(domain_id)
    out = a.out
    metrics: dict = {'plant': a.plant, 'setup': SETUPS[a.plant].__dict__, 'fingers': FINGERS}
    bags = a.bags or out / 'bags'
    try:
        if a.bags is None:
            metrics['identification'] = identify(a, env, bags)
        else:
            out.mkdir(parents=True)
            metrics['identification'] = {'bags': str(a.bags)}
        if a.identify_only:
            return 0

        t0 = time.monotonic()
        trained, stdout = train(a, env, bags, out)
        metrics['training'] = {k: trained[k] for k in ('val_r2_labels', 'fitness',
                                                       'derived_settings', 'noise_std',
                                                       'train_samples')}
        metrics['training']['wall_s'] = round(time.monotonic() - t0, 1)
        params = settings_file(out, trained)
        print(stdout.strip().splitlines()[-1], flush=True)
        deploy_laws(a, env, out, params, trained['derived_settings']['facts'], metrics)
    except RuntimeError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    finally:
        if out.exists():
            (out / 'metrics.json').write_text(json.dumps(metrics, indent=2))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
