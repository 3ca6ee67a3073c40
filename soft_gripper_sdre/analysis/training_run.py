"""One training run from its result to the files a user keeps, for both of
``tools.learning.train``'s paths (``.npz`` records and rosbag2 recordings) and the seed sweep
(:func:`fit`: the ``.npz`` records' labels to a scored checkpoint).

:func:`checkpoint` writes the checkpoint, loads it back as the controller will, scores it
(:func:`score`: R² of the predicted accelerations, the cubic least-squares baseline on the same
data, the input map at rest) and writes it again with the metrics the caller builds from those
scores. :func:`write_report` adds ``metrics.json`` and the loss and validation figures, and
:func:`staged` makes a run's files appear in the output directory together or not at all;
:class:`Stages` times the run's stages.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
import json
import os
from pathlib import Path
import shutil
import tempfile
import time
from typing import Callable, Iterator

import numpy as np

from soft_gripper_sdre.analysis.metrics import column_angles, poly_features, r2_score
from soft_gripper_sdre.analysis.plots import plot_accel, plot_loss
from soft_gripper_sdre.learning.labels import (
    VALIDATION,
    LabelledData,
    jittered,
    low_frequency_share,
)
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.learning.train_settings import TrainSettings
from soft_gripper_sdre.learning.training import TrainResult, fingerprint, save_checkpoint, train
from soft_gripper_sdre.sim.shape import AXIS_NAMES, InputBounds


class Stages:
    """Wall time per stage of a run [s] (``metrics.json``'s ``timings``), each lap the time since
    the previous one; a stage lapped again adds to its time."""

    #: the stages in the order they run, as ``metrics.json``'s ``timings`` names them: reading
    #: and checking the records or bags, the KF + RTS labels, training (of which
    #: ``label_stage`` and ``simulation_stage``), writing and scoring the checkpoint, the
    #: fitness verdict, the fingers' own linear fits and the closed-loop checks of the candidate
    #: settings (the bag path), the report (the figures and files; printed, not in
    #: ``metrics.json``, which it writes)
    ORDER = ('read', 'labels', 'training', 'label_stage', 'simulation_stage', 'checkpoint',
             'fitness', 'finger_fits', 'loop_settings', 'report')

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self.last
        self.last = now

    def record(self) -> dict[str, float]:
        """Each stage's seconds (rounded to ms) in :data:`ORDER`, and ``total`` since the start."""
        out = {k: round(self.seconds[k], 3) for k in self.ORDER if k in self.seconds}
        out['total'] = round(time.perf_counter() - self.start, 3)
        return out

    def line(self) -> str:
        """What the tool prints of them: ``training``'s own stages in brackets after it."""
        rec = self.record()
        total = rec.pop('total')
        inner = [f'{k} {rec.pop(k):.1f}' for k in ('label_stage', 'simulation_stage') if k in rec]
        parts = [f'{k} {v:.1f}' + (f' ({", ".join(inner)})' if k == 'training' and inner else '')
                 for k, v in rec.items()]
        return f'stages [s], {total:.1f} in all: ' + ', '.join(parts)


@dataclass
class Scores:
    """How a trained model fits: its predicted accelerations on the validation states
    (``pred``, (N, d)), their R² against the reference accelerations per axis (``r2``, d), the
    same for the cubic least-squares baseline fitted on the training data (``r2_ls``), and G₂ at
    rest (d, m)."""

    pred: np.ndarray
    r2: list[float]
    r2_ls: list[float]
    G2: np.ndarray

    def common_metrics(self, settings: TrainSettings, result: TrainResult) -> dict:
        """The metrics every path reports the same way."""
        return {'preset': settings.preset, 'seed': settings.seed,
                'epochs_run': len(result.train_loss), 'best_epoch': result.best_epoch,
                'train_seconds': round(result.seconds, 1), 'G2_at_origin': self.G2.tolist(),
                'G2_column_angles_deg': column_angles(self.G2).tolist(),
                'final_train_loss': result.train_loss[-1], 'best_val_loss': min(result.val_loss)}

    def lines(self, against: str) -> list[str]:
        """What training prints of them; ``against`` names the reference accelerations."""
        axes = AXIS_NAMES[:len(self.r2)]
        unit = 'N·m' if self.G2.shape == (2, 2) else 'unit of input'   # two torques: the hand
        model = '  '.join(f'{a} {v:.3f}' for a, v in zip(axes, self.r2))
        baseline = '  '.join(f'{a} {v:.3f}' for a, v in zip(axes, self.r2_ls))
        return [f'{against}: {model}   (3rd-order least squares: {baseline})',
                f'G2 at the origin [m/s² per {unit}]: '
                + '[' + ', '.join('[' + ', '.join(f'{v:.3g}' for v in row) + ']'
                                  for row in self.G2) + ']']


def score(model: SDCModel, train: tuple[np.ndarray, ...], val: tuple[np.ndarray, np.ndarray],
          acc_ref: np.ndarray) -> Scores:
    """:class:`Scores` of ``model``: ``train`` = (x, u, acc) the baseline is fitted on, ``val`` =
    (x, u) of the validation states, ``acc_ref`` their reference accelerations (the simulator's
    true ones, or the validation labels)."""
    x, u, acc = train
    d = model.shape.d
    pred = model.xdot(*val)[:, d:]
    coef, *_ = np.linalg.lstsq(poly_features(x, u), acc, rcond=None)
    return Scores(pred, r2_score(acc_ref, pred).tolist(),
                  r2_score(acc_ref, poly_features(*val) @ coef).tolist(),
                  model.AG(np.zeros(model.shape.n_state))[1][0, d:, :])


def checkpoint(path: Path, result: TrainResult, settings: TrainSettings, *,
               rest_tip: np.ndarray, dt: float, data: dict, train: tuple[np.ndarray, ...],
               val: tuple[np.ndarray, np.ndarray], acc_ref: np.ndarray,
               describe: Callable[[SDCModel, Scores], dict],
               input_bounds: InputBounds | None = None) -> tuple[SDCModel, Scores, dict]:
    """Write ``result`` to ``path`` (with ``input_bounds``, the bounds the data were recorded
    under, None when not known), load it back, :func:`score` it, and write it again with
    ``describe(model, scores)`` as its metrics; returns (model, scores, metrics)."""
    path = save_checkpoint(path, result, rest_tip=rest_tip, dt=dt, settings=settings, data=data,
                           input_bounds=input_bounds)
    model = SDCModel(path)
    scores = score(model, train, val, acc_ref)
    metrics = describe(model, scores)
    save_checkpoint(path, result, rest_tip=rest_tip, dt=dt, settings=settings, data=data,
                    metrics=metrics, input_bounds=input_bounds)
    return model, scores, metrics


def write_report(directory: Path, result: TrainResult, metrics: dict, scores: Scores,
                 t_val: np.ndarray, acc_ref: np.ndarray, *, loss_title: str, accel_file: str,
                 accel_title: str) -> None:
    """``metrics.json``, ``fig2_loss.png`` (training and validation loss per epoch) and the
    validation signal's predicted against reference accelerations (``accel_file``)."""
    directory = Path(directory)
    (directory / 'metrics.json').write_text(json.dumps(metrics, indent=2))
    plot_loss(result.train_loss, result.val_loss, directory / 'fig2_loss.png', title=loss_title)
    plot_accel(t_val, acc_ref, scores.pred, directory / accel_file, r2=scores.r2, title=accel_title)


def fit(data: LabelledData, settings: TrainSettings, path: Path, jitter: float = 0.0,
        jitter_seed: int = 0, on_epoch=None) -> tuple[Path, dict, TrainResult, Scores]:
    """Train on ``data`` (jittered by ``jitter`` when > 0,
    :func:`~soft_gripper_sdre.learning.labels.jittered`), write the checkpoint with its metrics to
    ``path`` and score it against the simulator's true accelerations of the validation signal:
    (path, metrics, the TrainResult, the scores)."""
    x, u, acc = data.x, data.u, data.acc
    if jitter > 0:
        x, acc = jittered(x, acc, jitter, jitter_seed)
    val = data.val
    result = train(x, u, acc, val['x'], val['u'], val['acc'], settings, on_epoch)
    data_info = {'variant': data.variant, 'train_signals': data.train_signals,
                 'validation': VALIDATION, 'fingerprint': fingerprint(x, u, acc),
                 'jerk_psd': data.jerk_psd, 'noise_std': data.noise_std}
    if jitter > 0:
        data_info['jitter'] = {'relative': jitter, 'seed': jitter_seed}

    def describe(model, scores: Scores) -> dict:
        return {**scores.common_metrics(settings, result), 'variant': data.variant,
                'u4_r2_true': dict(zip('XY', scores.r2)),
                'u4_r2_ls_baseline': dict(zip('XY', scores.r2_ls)),
                'u4_true_variance_below_10hz': dict(zip('XY', low_frequency_share(data.acc_true,
                                                                                  data.val_dt))),
                'derivative_errors': data.derivative_errors}
    _, scores, metrics = checkpoint(
        path, result, settings, rest_tip=data.rest_tip, dt=data.dt, data=data_info,
        train=(x, u, acc), val=(val['x'], val['u']), acc_ref=data.acc_true, describe=describe)
    return Path(path), metrics, result, scores


@contextmanager
def staged(out: Path, stale: tuple[str, ...] = ()) -> Iterator[Path]:
    """A directory beside ``out`` to write a run's files into; when the block ends without an
    error, every file in it replaces its namesake in ``out`` (created if need be), after the
    files named in ``stale`` are removed from ``out`` (no file of an older run is left beside the
    new ones). On an error ``out`` is left as it was."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f'.{out.name}.partial-', dir=out.parent))
    try:
        yield stage
        out.mkdir(parents=True, exist_ok=True)
        for name in stale:
            (out / name).unlink(missing_ok=True)
        for item in sorted(stage.iterdir()):
            os.replace(item, out / item.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
