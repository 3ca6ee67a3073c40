"""The spread of the learned model and of the grasp over training seeds and rounding-level changes
of the training data, with the shipped model placed in it.

    python -m soft_gripper_sdre.tools.judging.seeds --data data/excitation --out runs/seeds --demo
        # (make seeds)
    python -m soft_gripper_sdre.tools.judging.seeds --data DIR --out DIR --seeds 2 --draws 0
        --set epochs=3 --duration 0.3
    python -m soft_gripper_sdre.tools.judging.seeds --data DIR --out DIR --ray auto
        # on a Ray cluster

One model per training seed s (0 … ``--seeds`` − 1, ``train --seed``) and data draw d: draw 0 is the
data as collected, draw d ≥ 1 the training states and labels times 1 + J·N(0, 1) drawn with seed d
(J = ``--jitter``, 10⁻⁹ by default: it flips a few per cent of their float32 roundings, as another
CPU's kernels do, and nothing else). ``train --seed s --jitter J --jitter-seed d`` trains the same
model bit for bit. Each model is scored like the shipped one:

* its accuracy: u4 R² X / Y against the simulator's true acceleration, G2 at the origin and the
  directions of its columns (:mod:`~soft_gripper_sdre.tools.learning.train`'s metrics);
* its tracking: ``make evaluate``'s in-process closed loop (lockstep, 0.05 mm of noise, seed 0),
  free-space RMSE of the grasping fingers on the true tip for each law of ``--laws`` (the default
  ``sdre_ff`` and the paper's ``sdre``) on each trajectory of ``--trajectories``;
* with ``--demo``: ``make demo``'s figures, the grasp over the node graph (five processes, lockstep,
  one model after the other on this machine): the grasping and the opening fingers' free-space RMSE
  on the measured and on the true tip, the held-reference error, the cube's displacement.

The shipped model (``models/default.pt``) is scored the same way and placed in the distribution;
with the data of ``make model`` and its pinned kernels (``make seeds`` sets them), seed 0's model on
draw 0 is the shipped one bit for bit.

Training and tracking one model is one job (:mod:`~soft_gripper_sdre.tools.judging.seed_jobs`);
the jobs run on ``--workers`` processes of this machine, or as Ray tasks with ``--ray ADDRESS``
(:mod:`~soft_gripper_sdre.tools.judging.jobs`), with the same numbers. The demos need DDS on this
machine and run here, after the jobs.

Writes ``OUT/<model>/model.pt`` and ``metrics.json`` per model (``seed3``, ``seed3_draw1``),
``OUT/seeds.json`` (every number) and ``OUT/seeds.md`` (the tables,
:mod:`~soft_gripper_sdre.tools.judging.seed_tables`), and prints the tables.
"""
from __future__ import annotations

import argparse
from dataclasses import fields, replace
import json
import math
import os
from pathlib import Path
import shlex
import sys
import time

from soft_gripper_sdre.tools.judging import jobs
from soft_gripper_sdre.tools.judging.seed_jobs import (
    ModelJob,
    ModelOutcome,
    SweepContext,
    run_model_job,
)
from soft_gripper_sdre.tools.judging.seed_tables import write_results

#: the training settings ``--set`` may change (the seed is ``--seeds``', the preset is the default)
SETTABLE = ('epochs', 'lr', 'batch_size', 'cosine', 'scale', 'weight_decay', 'patience', 'hidden',
            'sv_penalty', 'sv_floor', 'sv_box')
DEFAULT_LAWS = ('sdre_ff', 'sdre')


# -- the demo on the node graph -----------------------------------------------------------------
def demo_figures(result: dict) -> dict:
    """``make demo``'s figures of one :func:`~soft_gripper_sdre.tools.graph.demo.run_demo` result:
    the worst finger of each pair (grasping 0 and 2, opening 1 and 3), measured and true tip."""
    from soft_gripper_sdre.nodes.graph import CUBE_FINGERS
    fingers = list(result['fingers'].values())
    grasping = [fingers[i] for i in CUBE_FINGERS]
    opening = [f for i, f in enumerate(fingers) if i not in CUBE_FINGERS]

    def worst(group, key, tip=None):
        values = [(f.get(tip, {}) if tip else f).get(key) for f in group]
        values = [v for v in values if v is not None]
        return max(values) if values else float('nan')
    controller = result.get('controller', {})
    return {'grasping_mm': worst(grasping, 'rmse_mm'), 'opening_mm': worst(opening, 'rmse_mm'),
            'grasping_true_mm': worst(grasping, 'rmse_mm', 'true_tip'),
            'opening_true_mm': worst(opening, 'rmse_mm', 'true_tip'),
            'held_true_mm': worst(fingers, 'held_mm', 'true_tip'),
            'cube_mm': result.get('cube_max_displacement_mm', float('nan')),
            'check_failure_fraction': controller.get('check_failure_fraction', float('nan')),
            'fallback_fraction': controller.get('fallback_fraction', float('nan'))}


def run_demos(models: dict[str, Path], out: Path, domain_id: int | None,
              progress: bool) -> dict[str, dict]:
    """The grasp demo with each model (name → checkpoint; None: the shipped one), one after the
    other: name → :func:`demo_figures`."""
    from soft_gripper_sdre.tools.graph.demo import DemoGraph, run_demo
    figures = {}
    for i, (name, path) in enumerate(models.items()):
        if progress:
            print(f'demo {i + 1}/{len(models)}: {name}', file=sys.stderr, flush=True)
        result = run_demo(out / name / 'demo', 6.0, DemoGraph(model=path), domain_id=domain_id,
                          progress=False)
        figures[name] = demo_figures(result)
    return figures


# -- the command line ---------------------------------------------------------------------------
def _settings_from(parser, assignments: list[str]):
    """The default preset with ``--set KEY=VALUE`` applied; a bad one is a usage error."""
    from soft_gripper_sdre.learning.train_settings import PRESETS
    settings = PRESETS['default']
    types = {f.name: type(getattr(settings, f.name)) for f in fields(settings)}
    changes = {}
    for item in assignments:
        key, sep, text = item.partition('=')
        if not sep or key not in SETTABLE:
            parser.error(f'--set takes KEY=VALUE with KEY one of {", ".join(SETTABLE)}, '
                         f'got {item!r}')
        try:
            if key == 'patience':
                value = None if text.lower() == 'none' else int(text)
            elif types[key] is bool:
                if text.lower() not in ('true', 'false'):
                    raise ValueError('not true or false')
                value = text.lower() == 'true'
            else:
                value = types[key](text)
        except ValueError as exc:
            parser.error(f'--set {key}: {text!r} is not a {types[key].__name__} ({exc})')
        if isinstance(value, float) and not math.isfinite(value):
            parser.error(f'--set {key} must be finite, got {text}')
        if key in ('epochs', 'batch_size', 'hidden') and value < 1:
            parser.error(f'--set {key} must be >= 1, got {value}')
        if key in ('lr',) and not value > 0:
            parser.error(f'--set {key} must be > 0, got {value}')
        if key in ('weight_decay',) and value < 0:
            parser.error(f'--set {key} must be >= 0, got {value}')
        changes[key] = value
    try:
        return replace(settings, **changes)
    except ValueError as exc:
        parser.error(f'--set: {exc}')


def _parser() -> argparse.ArgumentParser:
    from soft_gripper_sdre.tools.judging.evaluation_runs import LAW_SPECS, TRAJECTORIES
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.judging.seeds',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', type=Path, default=Path('data/excitation'),
                    help='directory with the <signal>.npz files of tools.learning.collect '
                         '(default %(default)s)')
    ap.add_argument('--out', type=Path, default=Path('runs/seeds'),
                    help='output directory (default %(default)s)')
    ap.add_argument('--seeds', type=int, default=5,
                    help='training seeds 0 … N−1 (default %(default)s)')
    ap.add_argument('--draws', type=int, default=2,
                    help='jittered draws of the data per seed, besides the data as collected '
                         '(default %(default)s)')
    ap.add_argument('--jitter', type=float, default=1e-9,
                    help='relative size of a draw\'s perturbation, as train --jitter '
                         '(default %(default)g)')
    ap.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                    help='change a training setting of the default preset '
                         f'({", ".join(SETTABLE)}), e.g. --set weight_decay=1e-4; repeatable')
    ap.add_argument('--laws', nargs='*', default=list(DEFAULT_LAWS), choices=list(LAW_SPECS),
                    metavar='LAW', help='make evaluate\'s laws to track with (default: '
                                        f'{" ".join(DEFAULT_LAWS)}; --laws alone: no tracking)')
    ap.add_argument('--trajectories', nargs='+', default=list(TRAJECTORIES),
                    choices=list(TRAJECTORIES))
    ap.add_argument('--duration', type=float, default=None,
                    help='override every tracking run\'s duration [s]')
    ap.add_argument('--demo', action='store_true',
                    help='also run the grasp demo over the node graph with every model')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID of the demos (default: env or random)')
    ap.add_argument('--no-progress', action='store_true', help='no progress bars')
    jobs.add_arguments(ap)
    return ap


def parse_args(argv=None):
    ap = _parser()
    args = ap.parse_args(argv)
    if not 1 <= args.seeds <= 1000:
        ap.error(f'--seeds must be in [1, 1000], got {args.seeds}')
    if not 0 <= args.draws <= 1000:
        ap.error(f'--draws must be in [0, 1000], got {args.draws}')
    if not (math.isfinite(args.jitter) and 0 < args.jitter < 1e-3):
        ap.error(f'--jitter must be in (0, 1e-3), got {args.jitter}')
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f'--duration must be > 0 s, got {args.duration}')
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        ap.error(f'--domain-id must be a ROS domain ID in [0, 232], got {args.domain_id}')
    if args.out.exists() and not args.out.is_dir():
        ap.error(f'--out {args.out} exists and is not a directory')
    settings = _settings_from(ap, args.set)
    runner = jobs.runner_from_args(ap, args)
    from soft_gripper_sdre.learning.dataset import DatasetError, load_records
    from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION
    try:
        records = load_records(args.data, list(DATA_VARIANTS['identifying']) + [VALIDATION])
    except DatasetError as exc:
        ap.error(str(exc))
    return ap, args, settings, runner, records


def _note_unpinned_kernels() -> None:
    """Say on stderr when the math kernels are not pinned as ``make model`` pins them."""
    from soft_gripper_sdre.tools.graph.procs import pinned_kernels
    unpinned = pinned_kernels(os.environ)
    if unpinned:
        print('note: the math kernels are not pinned as make model pins them (' +
              ' '.join(f'{k}={v}' for k, v in unpinned.items()) + '; make seeds sets them): on '
              'this CPU the models may differ from the shipped one at rounding level',
              file=sys.stderr)


def _save_models(out: Path, outcomes: list[ModelOutcome]) -> dict[str, Path | None]:
    """Each trained model's ``model.pt`` and ``metrics.json`` under ``out/<name>``: name → its
    checkpoint (None: the shipped model)."""
    paths: dict[str, Path | None] = {}
    for o in outcomes:
        paths[o.name] = None
        if o.checkpoint is not None:
            (out / o.name).mkdir(parents=True, exist_ok=True)
            paths[o.name] = out / o.name / 'model.pt'
            paths[o.name].write_bytes(o.checkpoint)
            (out / o.name / 'metrics.json').write_text(json.dumps(o.metrics, indent=2))
    return paths


def _sweep_facts(args, outcomes: list[ModelOutcome], data, runner: jobs.Runner,
                 wall: float) -> dict:
    """How the models were made, for the head of the tables."""
    from soft_gripper_sdre.learning.training import fingerprint
    return {'models': len(outcomes) - 1, 'seeds': f'0–{args.seeds - 1}', 'draws': args.draws,
            'jitter': args.jitter,
            'settings': 'default preset' + (' with ' + ', '.join(args.set) if args.set else ''),
            'fingerprint': fingerprint(data.x, data.u, data.acc), 'runner': runner.describe(),
            'wall_s': wall,
            'kernels': ' '.join(f'{k}={os.environ[k]}' for k in jobs.KERNEL_ENV if k in os.environ)
                       or 'as detected'}


def main(argv=None) -> int:
    ap, args, settings, runner, records = parse_args(argv)
    command = 'python -m soft_gripper_sdre.tools.judging.seeds ' + ' '.join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    from soft_gripper_sdre.learning.labels import label_records
    progress = not args.no_progress
    _note_unpinned_kernels()
    try:
        with jobs.session(runner):
            from soft_gripper_sdre.control.kernels import warm_up
            warm_up()  # the kernels into numba's cache once, before the workers load them
            data = label_records(records, 'identifying')
            context = SweepContext(data, settings, args.jitter, tuple(args.laws),
                                   tuple(args.trajectories), args.duration)
            todo = [ModelJob(None)] + [ModelJob(s, d) for s in range(args.seeds)
                                       for d in range(args.draws + 1)]
            start = time.monotonic()
            outcomes = jobs.run_jobs(run_model_job, todo, context, runner, desc='seeds',
                                     progress=progress)
            wall = time.monotonic() - start
    except jobs.JobsError as exc:
        ap.error(f'--ray: {exc}')
    args.out.mkdir(parents=True, exist_ok=True)
    paths = _save_models(args.out, outcomes)
    facts = _sweep_facts(args, outcomes, data, runner, wall)
    text = write_results(args.out, outcomes, {}, args, command, facts)
    if args.demo:
        try:
            demos = run_demos(paths, args.out, args.domain_id, progress)
        except RuntimeError as exc:
            print(f'{text}\nthe demos failed, the tables above are without them: {exc}',
                  file=sys.stderr)
            return 1
        text = write_results(args.out, outcomes, demos, args, command, facts)
    print(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
