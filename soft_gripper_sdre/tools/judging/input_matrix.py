"""Learned G2 vs the true input matrix J M⁻¹ B, at the rest pose and across the workspace.

    python -m soft_gripper_sdre.tools.judging.input_matrix [--models default paper_data PATH ...]
        [--out DIR]

For each model: the column directions of G2 and of J M⁻¹ B (tip acceleration per N·m, friction
off) at the rest pose and at the static poses held by a 3 × 3 grid of torques (±10 sim units =
±0.025 N·m per input), with direction errors and magnitude ratios; plus the model's own u4
validation R². ``default`` and ``paper_data`` are the two models shipped with the package.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

GRID = np.array([[a, b] for a in (-0.025, 0.0, 0.025) for b in (-0.025, 0.0, 0.025)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.judging.input_matrix',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--models', nargs='+', default=['default', 'paper_data'],
                    help="'default', 'paper_data' or checkpoint paths")
    ap.add_argument('--out', type=Path, default=None, help='also write input_matrix.json here')
    a = ap.parse_args(argv)
    from soft_gripper_sdre.analysis.ground_truth import input_matrix_survey
    from soft_gripper_sdre.analysis.metrics import column_angles
    from soft_gripper_sdre.learning.model import (
        DEFAULT_MODEL,
        PAPER_DATA_MODEL,
        ModelFileError,
        SDCModel,
    )
    named = {'default': DEFAULT_MODEL, 'paper_data': PAPER_DATA_MODEL}
    results = {}
    for name in a.models:
        try:
            model = SDCModel(named.get(name, Path(name)))
        except ModelFileError as exc:
            ap.error(str(exc))
        s = input_matrix_survey(model, GRID)
        rest = int(np.flatnonzero(np.all(GRID == 0, axis=1))[0])
        err = s.angle_error
        results[name] = {
            'data': model.data.get('variant') if isinstance(model.data, dict) else None,
            'u4_r2_true': model.metrics.get('u4_r2_true') if isinstance(model.metrics, dict)
                          else None,
            'rest': {'true_deg': column_angles(s.true[rest]).tolist(),
                     'learned_deg': column_angles(s.learned[rest]).tolist(),
                     'error_deg': err[rest].tolist(),
                     'magnitude_ratio': s.magnitude_ratio[rest].tolist()},
            'workspace': {'torques_Nm': GRID.tolist(), 'tip_mm': (1e3 * s.x[:, :2]).tolist(),
                          'true_deg': column_angles(s.true).tolist(),
                          'learned_deg': column_angles(s.learned).tolist(),
                          'median_error_deg': np.median(err, axis=0).tolist(),
                          'max_error_deg': err.max(axis=0).tolist()},
        }
    print('| model | training data | u4 R² X / Y | G2 columns at rest (learned vs true) '
          '| direction error at rest | median error over the workspace |')
    print('| --- | --- | --- | --- | --- | --- |')
    for name, r in results.items():
        r2 = r['u4_r2_true'] or {}
        lr, tr, e = r['rest']['learned_deg'], r['rest']['true_deg'], r['rest']['error_deg']
        w = r['workspace']['median_error_deg']
        print(f'| {name} | {r["data"]} | '
              f'{r2.get("X", float("nan")):.3f} / {r2.get("Y", float("nan")):.3f} | '
              f'{lr[0]:.1f}°, {lr[1]:.1f}° vs {tr[0]:.1f}°, {tr[1]:.1f}° | '
              f'{e[0]:.1f}°, {e[1]:.1f}° | {w[0]:.1f}°, {w[1]:.1f}° |')
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / 'input_matrix.json').write_text(json.dumps(results, indent=2) + '\n')
        print(f'wrote {a.out / "input_matrix.json"}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
