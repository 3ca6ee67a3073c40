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

Training and tracking one model is one job; the jobs run on ``--workers`` processes of this
machine, or as Ray tasks with ``--ray ADDRESS`` (:mod:`~soft_gripper_sdre.tools.judging.jobs`), with
the same numbers. The demos need DDS on this machine and run here, after the jobs.

Writes ``OUT/<model>/model.pt`` and ``metrics.json`` per model (``seed3``, ``seed3_draw1``),
``OUT/seeds.json`` (every number) and ``OUT/seeds.md`` (the tables), and prints the tables.
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, fields, replace
import hashlib
import json
import math
import os
from pathlib import Path
import shlex
import sys
import tempfile
import time

import numpy as np

from soft_gripper_sdre.tools.judging import jobs

#: the training settings ``--set`` may change (the seed is ``--seeds``', the preset is the default)
SETTABLE = ('epochs', 'lr', 'batch_size', 'cosine', 'scale', 'weight_decay', 'patience', 'hidden',
            'sv_penalty', 'sv_floor', 'sv_box')
DEFAULT_LAWS = ('sdre_ff', 'sdre')
#: the shipped model's row
SHIPPED = 'shipped'


@dataclass(frozen=True)
class ModelJob:
    """Train seed ``seed`` on draw ``draw`` of the data and score it; ``seed`` None scores the
    shipped model."""

    seed: int | None
    draw: int = 0

    @property
    def name(self) -> str:
        if self.seed is None:
            return SHIPPED
        return f'seed{self.seed}' + (f'_draw{self.draw}' if self.draw else '')


@dataclass(frozen=True)
class SweepContext:
    """What every job shares: the labelled data, the training settings, the jitter, the tracking
    runs."""

    data: object                   # tools.learning.train.LabelledData
    settings: object               # learning.train_settings.TrainSettings
    jitter: float
    laws: tuple[str, ...]
    trajectories: tuple[str, ...]
    duration: float | None


@dataclass
class ModelOutcome:
    """One model: its checkpoint (None for the shipped one), its training metrics, the sha256 of its
    weights, and its tracking runs (``evaluate.RunSummary`` as dicts)."""

    name: str
    seed: int | None
    draw: int
    checkpoint: bytes | None
    metrics: dict
    weights_sha256: str
    tracking: list[dict]
    job_seconds: float


def weights_sha256(path: Path) -> str:
    """sha256 over the checkpoint's network weights (every tensor of the state dict, by name)."""
    from soft_gripper_sdre.learning.model import read_checkpoint
    state = read_checkpoint(path)['state_dict']
    h = hashlib.sha256()
    for key in sorted(state):
        a = state[key].detach().cpu().numpy()
        h.update(key.encode())
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def tracking_runs(model, laws, trajectories, duration) -> list[dict]:
    """Every law on every trajectory, in-process, as ``make evaluate`` runs them (RunSummary
    dicts)."""
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.tools.judging.evaluate import run_law
    weights = Weights(**DEFAULT_WEIGHTS)
    out = []
    for trajectory in trajectories:
        for law in laws:
            summary, _ = run_law(law, trajectory, model, weights, duration=duration)
            out.append(asdict(summary))
    return out


def run_model_job(context: SweepContext, job: ModelJob) -> ModelOutcome:
    """Train and score one model (a job of
    :func:`~soft_gripper_sdre.tools.judging.jobs.run_jobs`)."""
    from soft_gripper_sdre.analysis.training_run import fit
    from soft_gripper_sdre.learning.model import DEFAULT_MODEL, SDCModel, set_torch_threads
    set_torch_threads(1)
    start = time.perf_counter()
    if job.seed is None:
        model = SDCModel()
        tracking = tracking_runs(model, context.laws, context.trajectories, context.duration)
        return ModelOutcome(job.name, None, 0, None, dict(model.metrics),
                            weights_sha256(DEFAULT_MODEL), tracking, time.perf_counter() - start)
    settings = replace(context.settings, seed=job.seed)
    jitter = context.jitter if job.draw else 0.0
    with tempfile.TemporaryDirectory(prefix='sgs-seeds-') as tmp:
        path, metrics, _, _ = fit(context.data, settings, Path(tmp) / 'model.pt', jitter, job.draw)
        model = SDCModel(path)
        tracking = tracking_runs(model, context.laws, context.trajectories, context.duration)
        return ModelOutcome(job.name, job.seed, job.draw, path.read_bytes(), metrics,
                            weights_sha256(path), tracking, time.perf_counter() - start)


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


# -- statistics and tables ----------------------------------------------------------------------
def spread(values) -> dict:
    """n, mean, sample standard deviation (ddof 1; NaN for fewer than two), min and max of the
    finite ``values``."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return dict(n=0, mean=float('nan'), sd=float('nan'), min=float('nan'), max=float('nan'))
    return dict(n=int(v.size), mean=float(v.mean()),
                sd=float(v.std(ddof=1)) if v.size > 1 else float('nan'),
                min=float(v.min()), max=float(v.max()))


def within_seed_sd(rows: list[dict], key: str) -> float:
    """The pooled standard deviation over the draws of each seed (the rounding-level spread alone):
    sqrt(Σ_s Σ_d (v − mean_s)² / Σ_s (n_s − 1)); NaN without a seed of two draws."""
    by_seed: dict[int, list[float]] = {}
    for r in rows:
        v = r.get(key)
        if r['seed'] is not None and v is not None and math.isfinite(v):
            by_seed.setdefault(r['seed'], []).append(v)
    ss = sum(float(np.sum((np.asarray(v) - np.mean(v)) ** 2)) for v in by_seed.values())
    dof = sum(len(v) - 1 for v in by_seed.values())
    return math.sqrt(ss / dof) if dof > 0 else float('nan')


def model_row(outcome: ModelOutcome, demo: dict | None) -> dict:
    """The flat figures of one model."""
    m = outcome.metrics
    g2 = np.asarray(m['G2_at_origin'], dtype=float)
    row = {'name': outcome.name, 'seed': outcome.seed, 'draw': outcome.draw,
           'r2_x': m['u4_r2_true']['X'], 'r2_y': m['u4_r2_true']['Y'],
           'g2_00': g2[0, 0], 'g2_01': g2[0, 1], 'g2_10': g2[1, 0], 'g2_11': g2[1, 1],
           'angle_0': m['G2_column_angles_deg'][0], 'angle_1': m['G2_column_angles_deg'][1],
           'best_epoch': m['best_epoch'], 'epochs_run': m['epochs_run'],
           'best_val_loss': m['best_val_loss'], 'weights_sha256': outcome.weights_sha256}
    for run in outcome.tracking:
        prefix = f'{run["law"]}_{run["trajectory"]}'
        row[f'{prefix}_rmse_mm'] = run['rmse_mm_grasp']
        row[f'{prefix}_held_mm'] = run['held_mm']
        row[f'{prefix}_cube_mm'] = run['cube_mm']
        row[f'{prefix}_grasp'] = run['grasp_success']
        row[f'{prefix}_check_fail_pct'] = run['check_fail_pct']
    for key, value in (demo or {}).items():
        row[f'demo_{key}'] = value
    return row


#: the figures summarised, with their labels and formats (the tracking keys are added per law and
#: trajectory)
ACCURACY = [('r2_x', 'u4 R² X', '.4f'), ('r2_y', 'u4 R² Y', '.4f'), ('g2_00', 'G2[0][0]', '.1f'),
            ('g2_01', 'G2[0][1]', '.1f'), ('g2_10', 'G2[1][0]', '.1f'),
            ('g2_11', 'G2[1][1]', '.1f'), ('angle_0', 'G2 column 0 angle [°]', '.2f'),
            ('angle_1', 'G2 column 1 angle [°]', '.2f'), ('best_epoch', 'best epoch', '.0f')]
DEMO = [('demo_grasping_mm', 'demo: grasping fingers, measured tip [mm]', '.3f'),
        ('demo_opening_mm', 'demo: opening fingers, measured tip [mm]', '.3f'),
        ('demo_grasping_true_mm', 'demo: grasping fingers, true tip [mm]', '.3f'),
        ('demo_opening_true_mm', 'demo: opening fingers, true tip [mm]', '.3f'),
        ('demo_held_true_mm', 'demo: held-reference error, worst finger [mm]', '.3f'),
        ('demo_cube_mm', 'demo: cube moved [mm]', '.2f')]


def figure_keys(rows: list[dict], laws, trajectories) -> list[tuple[str, str, str]]:
    keys = list(ACCURACY)
    for trajectory in trajectories:
        for law in laws:
            keys.append((f'{law}_{trajectory}_rmse_mm',
                         f'`{law}` on the {trajectory}: RMSE grasping fingers [mm]', '.4f'))
    keys += [k for k in DEMO if any(k[0] in r for r in rows)]
    return keys


def summarise(rows: list[dict], keys) -> dict:
    """Per figure: the spread over seeds on the collected data (draw 0), the pooled spread over the
    draws of one seed, the spread over every trained model, and the shipped model's value with its
    place among the trained models (z-score against all, and how many lie below it)."""
    trained = [r for r in rows if r['seed'] is not None]
    draw0 = [r for r in trained if r['draw'] == 0]
    shipped = next((r for r in rows if r['seed'] is None), None)
    out = {}
    for key, _, _ in keys:
        every = spread(r.get(key) for r in trained)
        entry = {'seeds': spread(r.get(key) for r in draw0),
                 'draws_sd': within_seed_sd(trained, key), 'all': every}
        if shipped is not None and shipped.get(key) is not None:
            v = shipped[key]
            values = [r[key] for r in trained if r.get(key) is not None and math.isfinite(r[key])]
            entry['shipped'] = {'value': v,
                                'z': (v - every['mean']) / every['sd']
                                     if every['sd'] and every['sd'] > 0 else float('nan'),
                                'below': sum(x < v for x in values), 'of': len(values)}
        out[key] = entry
    return out


def _finer(fmt: str) -> str:
    """The format of a spread: one decimal more than its figure's (``.3f`` → ``.4f``)."""
    return f'.{int(fmt[1:-1]) + 1}f' if fmt.endswith('f') and fmt[1:-1].isdigit() else fmt


def _f(value, fmt) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '–'
    return format(value, fmt)


def markdown(rows: list[dict], summary: dict, keys, command: str, facts: dict) -> str:
    lines = ['# The model and the grasp over training seeds and data draws', '',
             f'Command: `{command}`', '',
             f'{facts["models"]} trained models: seeds {facts["seeds"]}, draws 0–{facts["draws"]} '
             '(draw 0: the data as collected; draw d: states and labels × '
             f'(1 + {facts["jitter"]:g}·N(0, 1)), seed d); training '
             f'settings {facts["settings"]}; data fingerprint {facts["fingerprint"][:12]}; '
             f'jobs on {facts["runner"]}, {facts["wall_s"]:.0f} s wall; '
             f'kernels {facts["kernels"]}.', '',
             '## Spread', '',
             '| figure | over seeds (draw 0): mean ± sd | min – max | over draws of a seed: sd '
             '| every model: mean ± sd | min – max | shipped | shipped: z, models below it |',
             '| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |']
    for key, label, fmt in keys:
        e = summary[key]
        s, a = e['seeds'], e['all']
        shipped = e.get('shipped')
        place = (f'{_f(shipped["z"], "+.2f")}, {shipped["below"]}/{shipped["of"]}' if shipped
                 else '–')
        fine = _finer(fmt)
        lines.append(f'| {label} | {_f(s["mean"], fmt)} ± {_f(s["sd"], fine)} '
                     f'| {_f(s["min"], fmt)} – {_f(s["max"], fmt)} '
                     f'| {_f(e["draws_sd"], fine)} | {_f(a["mean"], fmt)} ± {_f(a["sd"], fine)} '
                     f'| {_f(a["min"], fmt)} – {_f(a["max"], fmt)} '
                     f'| {_f(shipped["value"], fmt) if shipped else "–"} | {place} |')
    lines += ['', '## Every model', '',
              '| model | ' + ' | '.join(label for _, label, _ in keys) + ' |',
              '| --- |' + ' ---: |' * len(keys)]
    for r in rows:
        lines.append(f'| {r["name"]} | ' +
                     ' | '.join(_f(r.get(key), fmt) for key, _, fmt in keys) + ' |')
    same = facts.get('seed0_is_shipped')
    if same is not None:
        lines += ['', f'Seed 0 on draw 0 {"is" if same else "is NOT"} the shipped model bit for '
                      'bit (sha256 of the network weights).']
    return '\n'.join(lines) + '\n'


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
    from soft_gripper_sdre.tools.judging.evaluate import LAW_SPECS, TRAJECTORIES
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


def main(argv=None) -> int:
    ap, args, settings, runner, records = parse_args(argv)
    command = 'python -m soft_gripper_sdre.tools.judging.seeds ' + ' '.join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    from soft_gripper_sdre.learning.labels import label_records
    from soft_gripper_sdre.learning.training import fingerprint
    from soft_gripper_sdre.tools.graph.procs import pinned_kernels
    progress = not args.no_progress
    unpinned = pinned_kernels(os.environ)
    if unpinned:
        print('note: the math kernels are not pinned as make model pins them (' +
              ' '.join(f'{k}={v}' for k, v in unpinned.items()) + '; make seeds sets them): on '
              'this CPU the models may differ from the shipped one at rounding level',
              file=sys.stderr)
    try:
        with jobs.session(runner):
            from soft_gripper_sdre.control.compiled import warm_up
            warm_up()  # the kernels into numba's cache once, before the workers load them
            data = label_records(records, 'identifying', progress=progress)
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
    paths: dict[str, Path | None] = {}
    for o in outcomes:
        paths[o.name] = None
        if o.checkpoint is not None:
            (args.out / o.name).mkdir(parents=True, exist_ok=True)
            paths[o.name] = args.out / o.name / 'model.pt'
            paths[o.name].write_bytes(o.checkpoint)
            (args.out / o.name / 'metrics.json').write_text(json.dumps(o.metrics, indent=2))
    facts = {'models': len(outcomes) - 1, 'seeds': f'0–{args.seeds - 1}', 'draws': args.draws,
             'jitter': args.jitter,
             'settings': 'default preset' + (' with ' + ', '.join(args.set) if args.set else ''),
             'fingerprint': fingerprint(data.x, data.u, data.acc), 'runner': runner.describe(),
             'wall_s': wall,
             'kernels': ' '.join(f'{k}={os.environ[k]}' for k in jobs.KERNEL_ENV if k in os.environ)
                        or 'as detected'}
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


def write_results(out: Path, outcomes: list[ModelOutcome], demos: dict, args, command: str,
                  facts: dict) -> str:
    """seeds.json and seeds.md in ``out`` from the jobs' outcomes and the demos' figures; the
    tables."""
    rows = [model_row(o, demos.get(o.name)) for o in outcomes]
    keys = figure_keys(rows, args.laws, args.trajectories)
    summary = summarise(rows, keys)
    shipped = next(r for r in rows if r['seed'] is None)
    seed0 = next((r for r in rows if r['seed'] == 0 and r['draw'] == 0), None)
    facts = dict(facts, seed0_is_shipped=None if seed0 is None
                 else seed0['weights_sha256'] == shipped['weights_sha256'])
    text = markdown(rows, summary, keys, command, facts)
    (out / 'seeds.json').write_text(json.dumps(
        dict(command=command, facts=facts, summary=summary, models=rows,
             tracking={o.name: o.tracking for o in outcomes},
             job_seconds={o.name: round(o.job_seconds, 1) for o in outcomes}),
        indent=2, default=float))
    (out / 'seeds.md').write_text(text)
    return text


if __name__ == '__main__':
    raise SystemExit(main())
