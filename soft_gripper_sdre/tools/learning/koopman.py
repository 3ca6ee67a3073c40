"""Fit the Koopman baseline (EDMD with inputs) to the excitation data the SDC model learns from.

    python -m soft_gripper_sdre.tools.learning.koopman --data data/excitation --out runs/koopman
        [--install]

Training records u1, u2, u3, x1, x2 (the shipped SDC model's), validation u4; states and labels
are the same KF + RTS estimates from the measured tips that tools.learning.train uses. Writes
OUT/koopman.npz and OUT/metrics.json; ``--install`` copies the model into the package as the
shipped one (:data:`~soft_gripper_sdre.learning.koopman.DEFAULT_KOOPMAN`). Deterministic.

The u4 R² is scored as :func:`soft_gripper_sdre.analysis.ground_truth.score_model` scores the SDC
model: the predicted mean acceleration over a period at the simulator's true state, against the
simulator's, at every 10th step of the first 4 s (399 states). ``--compare-sdc`` also scores the
shipped SDC model both ways (score_model itself, and on the record) to show they agree.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
import shutil
import sys

import numpy as np

from soft_gripper_sdre.analysis.metrics import r2_score
from soft_gripper_sdre.learning.dataset import DatasetError, load_records
from soft_gripper_sdre.learning.koopman import (
    DEFAULT_KOOPMAN,
    KoopmanModel,
    KoopmanSettings,
    fit_koopman,
)
from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION, states_of, tuned_jerk_psd

#: score_model's samples: every 10th step of the first 4 s, from step 10 on
SCORE_EVERY, SCORE_SECONDS = 10, 4.0


def score_rows(dt: float) -> np.ndarray:
    """The record rows :func:`~soft_gripper_sdre.analysis.ground_truth.score_model` samples."""
    return np.arange(SCORE_EVERY, int(round(SCORE_SECONDS / dt)), SCORE_EVERY)


def true_series(path: Path) -> dict[str, np.ndarray]:
    """A record's true translated tip positions, velocities, accelerations (N, 2) and inputs."""
    with np.load(path, allow_pickle=False) as f:
        missing = {'tip_true', 'vel_true', 'acc_true'} - set(f.files)
        if missing:
            raise DatasetError(f'{path}: has no simulator truth ({sorted(missing)}); collect it '
                               'with tools.learning.collect')
        rest = f['rest_tip'][:2]
        return dict(pos=f['tip_true'][:, :2] - rest, vel=f['vel_true'][:, :2],
                    acc=f['acc_true'][:, :2], u=f['u'], dt=float(f['dt']))


def koopman_r2(model: KoopmanModel, truth: dict, rows: np.ndarray | None = None) -> list[float]:
    """R² (X, Y) of the model's one-period acceleration against the simulator's at ``rows``
    (default: score_model's samples) along the record ``truth`` (:func:`true_series`)."""
    rows = score_rows(truth['dt']) if rows is None else rows
    acc = model.predict_acceleration(truth['pos'], truth['vel'], truth['u'])
    return r2_score(truth['acc'][rows], acc[rows]).tolist()


def sdc_r2(sdc, truth: dict) -> list[float]:
    """The SDC model's R² on the same rows, ẍ = A(x)x + G(x)u at the true state."""
    rows = score_rows(truth['dt'])
    x = np.hstack([truth['pos'], truth['vel']])[rows]
    return r2_score(truth['acc'][rows], sdc.xdot(x, truth['u'][rows])[:, 2:]).tolist()


def fit_from_directory(data: Path, settings: KoopmanSettings = KoopmanSettings(),
                       names: tuple[str, ...] = DATA_VARIANTS['identifying']
                       ) -> tuple[KoopmanModel, dict]:
    """Fit on ``names`` in ``data`` (KF + RTS states as tools.learning.train) and score on u4:
    (model, metrics).

    Raises:
        DatasetError: a record is missing or unusable.
    """
    records = load_records(data, list(names) + [VALIDATION])
    first = records[names[0]]
    jerk = tuned_jerk_psd(first)
    est = dict(zip(names, states_of([records[n] for n in names], jerk)))
    series = [(est[n]['x'][:, :2], est[n]['x'][:, 2:], est[n]['u']) for n in names]
    info = dict(train_signals=list(names), validation=VALIDATION, jerk_psd=jerk,
                noise_std=float(first.noise_std))
    model = fit_koopman(series, first.rest_tip, first.dt, settings, info)
    train_acc = np.vstack([model.predict_acceleration(*s)[:-1] for s in series])
    label_acc = np.vstack([est[n]['acc'][:-1] for n in names])
    truth = true_series(Path(data) / f'{VALIDATION}.npz')
    metrics = dict(
        observables=dict(delays_periods=list(settings.delays), degree=settings.degree,
                         n_z=model.n_z),
        ridge=settings.ridge,
        train_r2_vs_labels=r2_score(label_acc, train_acc).tolist(),
        u4_r2_true=koopman_r2(model, truth),
        u4_r2_true_whole_record=koopman_r2(model, truth,
                                           np.arange(model.max_delay, len(truth['u']))),
        max_abs_eigenvalue=float(np.abs(np.linalg.eigvals(model.A)).max()))
    model.info['metrics'] = metrics
    return model, metrics


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.learning.koopman',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', required=True, type=Path, help='directory with <signal>.npz files')
    ap.add_argument('--out', required=True, type=Path, help='output directory')
    ap.add_argument('--install', action='store_true', help=f'copy the model to {DEFAULT_KOOPMAN}')
    ap.add_argument('--compare-sdc', action='store_true',
                    help='also score the shipped SDC model (score_model and on the record)')
    ap.add_argument('--delays', type=int, nargs='*', default=list(KoopmanSettings.delays),
                    help='delay coordinates of the position [control periods] '
                         '(default: %(default)s)')
    ap.add_argument('--degree', type=int, default=KoopmanSettings.degree,
                    help='highest degree of the state monomials, 1 = none (default: %(default)s)')
    ap.add_argument('--ridge', type=float, default=KoopmanSettings.ridge,
                    help='ridge α per sample on standardised columns (default: %(default)s)')
    args = ap.parse_args(argv)
    try:
        settings = KoopmanSettings(tuple(args.delays), args.degree, args.ridge)
    except ValueError as exc:
        ap.error(str(exc))
    try:
        model, metrics = fit_from_directory(args.data, settings)
    except DatasetError as exc:
        ap.error(str(exc))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        ap.error(f'cannot create output directory {args.out}: {exc.strerror}')
    if args.compare_sdc:
        from soft_gripper_sdre.analysis.ground_truth import score_model
        from soft_gripper_sdre.learning.model import SDCModel
        sdc = SDCModel()
        metrics['sdc_u4_r2_true_on_record'] = sdc_r2(sdc,
                                                     true_series(args.data / f'{VALIDATION}.npz'))
        metrics['sdc_u4_r2_score_model'] = score_model(sdc)['stats']['r2_learned_vs_sim']
    path = model.save(args.out / 'koopman.npz')
    (args.out / 'metrics.json').write_text(json.dumps(metrics, indent=2))
    r2 = metrics['u4_r2_true']
    print(f'Koopman model: {model.n_z} observables (delays {list(model.settings.delays)} periods, '
          f'degree {model.settings.degree}), ridge {model.settings.ridge:g}')
    print(f'u4 R² vs the simulator\'s acceleration (score_model\'s samples): '
          f'X {r2[0]:.3f}  Y {r2[1]:.3f}')
    if args.compare_sdc:
        s = metrics['sdc_u4_r2_score_model']
        print(f'shipped SDC model, same samples: X {s[0]:.3f}  Y {s[1]:.3f}')
    print(f'wrote {path}')
    if args.install:
        shutil.copyfile(path, DEFAULT_KOOPMAN)
        print(f'installed as {DEFAULT_KOOPMAN}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
