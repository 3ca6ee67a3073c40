"""The seed sweep's results (:mod:`~soft_gripper_sdre.tools.judging.seeds`): one row of figures per
model, their spread (:mod:`~soft_gripper_sdre.analysis.seed_spread`), and the files that hold them,
``seeds.json`` (every number) and ``seeds.md`` (the tables the tool prints)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from soft_gripper_sdre.analysis.seed_spread import summarise
from soft_gripper_sdre.tools.judging.seed_jobs import ModelOutcome

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


def figure_keys(rows: list[dict], laws, trajectories) -> list[tuple[str, str, str]]:
    """The figures of the tables, (key, label, format): the accuracy, each tracking run's RMSE, and
    the demo's figures when a row has them."""
    keys = list(ACCURACY)
    for trajectory in trajectories:
        for law in laws:
            keys.append((f'{law}_{trajectory}_rmse_mm',
                         f'`{law}` on the {trajectory}: RMSE grasping fingers [mm]', '.4f'))
    keys += [k for k in DEMO if any(k[0] in r for r in rows)]
    return keys


def _finer(fmt: str) -> str:
    """The format of a spread: one decimal more than its figure's (``.3f`` → ``.4f``)."""
    return f'.{int(fmt[1:-1]) + 1}f' if fmt.endswith('f') and fmt[1:-1].isdigit() else fmt


def _f(value, fmt) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '–'
    return format(value, fmt)


def markdown(rows: list[dict], summary: dict, keys, command: str, facts: dict) -> str:
    """``seeds.md``: how the models were made, the spread of each figure, and every model's row."""
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
