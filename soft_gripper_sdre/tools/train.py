"""Learn the SDC model from excitation data: derivative estimates, training, validation, figures.

    python -m soft_gripper_sdre.tools.train --data data/excitation --out runs/train [--preset paper]
    python -m soft_gripper_sdre.tools.train --bag DIR [--bag DIR ...] --val-bag DIR
        --out runs/train_bags

With ``--bag`` the data come from rosbag2 recordings of ``tip_positions`` and ``torque_commands``
(the excitation node and a recorder, on the simulator or a robot):
:mod:`soft_gripper_sdre.tools.train_bags`. The rest of this text is about ``--data``.

Writes OUT/model.pt (checkpoint), OUT/metrics.json, OUT/fig2_loss.png (the paper's Figure 2) and
OUT/fig3_accel_u4.png (Figure 3), all together or none (the pipeline both paths share:
:mod:`~soft_gripper_sdre.analysis.training_run`). ``--install`` also copies the checkpoint and
its metrics into the package as the shipped default model. Training labels are the KF + RTS
estimates from the measured tip positions; validation (u4) is scored against the simulator's true
accelerations.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
import json
import logging
from pathlib import Path
import shutil
import sys

import numpy as np
from tqdm import tqdm

from soft_gripper_sdre.analysis import training_run
from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.learning.dataset import DatasetError, Record, load_records
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, set_torch_threads
from soft_gripper_sdre.learning.training import PRESETS, fingerprint, train

#: training signals per data variant; validation is always u4
DATA_VARIANTS = {'paper': ('u1', 'u2', 'u3'), 'identifying': ('u1', 'u2', 'u3', 'x1', 'x2')}
VALIDATION = 'u4'


def states(record: Record, jerk_psd: float) -> dict[str, np.ndarray]:
    """Translated state x = [X−X₀, Y−Y₀, Ẋ, Ẏ], input and acceleration labels from the KF + RTS."""
    pos, vel, acc = derivatives.estimate_kinematics(record.t, record.tip[:, :2], jerk_psd,
                                                    record.noise_std, smooth=True)
    x = np.hstack([pos - record.rest_tip[:2], vel])
    return {'x': x, 'u': record.u, 'acc': acc, 'vel': vel}


def tuned_jerk_psd(record: Record) -> float:
    """The KF/RTS white-jerk intensity picked by likelihood on the first 2 s of ``record`` (the
    first training record: the labels of every model fitted to the same data)."""
    seg = slice(0, min(2000, record.t.size))
    return derivatives.tune_jerk_psd(record.t[seg], record.tip[seg, :2], record.noise_std,
                                     np.logspace(1, 7, 7))


def low_frequency_share(acc: np.ndarray, dt: float, cutoff: float = 10.0) -> list[float]:
    """Share of each column's variance below ``cutoff`` Hz."""
    a = acc - acc.mean(axis=0)
    power = np.abs(np.fft.rfft(a, axis=0)) ** 2
    f = np.fft.rfftfreq(len(a), dt)
    return (power[f < cutoff].sum(axis=0) / power.sum(axis=0)).tolist()


@dataclass
class LabelledData:
    """The ``--data`` records as training sees them: the training arrays of every training signal,
    stacked, and the validation signal, labelled by the KF + RTS (:func:`label_records`)."""

    variant: str
    train_signals: list[str]
    x: np.ndarray                  # (N, 4) translated states
    u: np.ndarray                  # (N, 2) torques
    acc: np.ndarray                # (N, 2) acceleration labels
    val: dict[str, np.ndarray]     # :func:`states` of the validation signal
    # (M, 2) the validation signal's true acceleration (its labels without one)
    acc_true: np.ndarray
    val_dt: float
    jerk_psd: float
    rest_tip: np.ndarray
    dt: float
    noise_std: float
    derivative_errors: dict


def label_records(records: dict[str, Record], variant: str, jerk_psd: float | None = None,
                  progress: bool = True) -> LabelledData:
    """Label ``records`` (``DATA_VARIANTS[variant]`` and the validation signal) with the KF + RTS at
    ``jerk_psd`` (None: :func:`tuned_jerk_psd` on the first training record)."""
    names = list(DATA_VARIANTS[variant]) + [VALIDATION]
    first = records[names[0]]
    jerk = jerk_psd if jerk_psd is not None else tuned_jerk_psd(first)
    est = {}
    deriv_err = {}
    for name in tqdm(names, desc='KF + RTS', unit='signal', disable=not progress):
        est[name] = states(records[name], jerk)
        r = records[name]
        if r.acc_true is not None:
            deriv_err[name] = derivatives.estimate_errors(est[name]['vel'], est[name]['acc'],
                                                          r.vel_true[:, :2], r.acc_true[:, :2])
    train_names = names[:-1]
    val, v_rec = est[VALIDATION], records[VALIDATION]
    return LabelledData(
        variant=variant, train_signals=train_names,
        x=np.vstack([est[n]['x'] for n in train_names]),
        u=np.vstack([est[n]['u'] for n in train_names]),
        acc=np.vstack([est[n]['acc'] for n in train_names]), val=val,
        acc_true=v_rec.acc_true[:, :2] if v_rec.acc_true is not None else val['acc'],
        val_dt=v_rec.dt, jerk_psd=float(jerk), rest_tip=first.rest_tip, dt=first.dt,
        noise_std=float(first.noise_std), derivative_errors=deriv_err)


def jittered(x: np.ndarray, acc: np.ndarray, jitter: float,
             seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, acc) times 1 + ``jitter``·N(0, 1) elementwise (labels first, then states, from one
    generator seeded with ``seed``): the same data, other float roundings."""
    rng = np.random.default_rng(seed)
    acc = acc * (1.0 + jitter * rng.standard_normal(acc.shape))
    x = x * (1.0 + jitter * rng.standard_normal(x.shape))
    return x, acc


def fit(data: LabelledData, settings, path: Path, jitter: float = 0.0, jitter_seed: int = 0,
        on_epoch=None) -> tuple[Path, dict, object, training_run.Scores]:
    """Train on ``data`` (jittered by ``jitter`` when > 0, :func:`jittered`), write the checkpoint
    with its metrics to ``path`` and score it against the simulator's true accelerations of the
    validation signal: (path, metrics, the TrainResult, the scores)."""
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

    def describe(model, scores: training_run.Scores) -> dict:
        return {**scores.common_metrics(settings, result), 'variant': data.variant,
                'u4_r2_true': dict(zip('XY', scores.r2)),
                'u4_r2_ls_baseline': dict(zip('XY', scores.r2_ls)),
                'u4_true_variance_below_10hz': dict(zip('XY', low_frequency_share(data.acc_true,
                                                                                  data.val_dt))),
                'derivative_errors': data.derivative_errors}
    _, scores, metrics = training_run.checkpoint(
        path, result, settings, rest_tip=data.rest_tip, dt=data.dt, data=data_info,
        train=(x, u, acc), val=(val['x'], val['u']), acc_ref=data.acc_true, describe=describe)
    return Path(path), metrics, result, scores


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.train',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--data', type=Path,
                        help='directory with <signal>.npz files (tools.collect)')
    parser.add_argument('--out', required=True, type=Path, help='output directory')
    bags = parser.add_argument_group('training from rosbag2 recordings (instead of --data)')
    bags.add_argument('--bag', type=Path, action='append', metavar='DIR',
                      help='a rosbag2 directory, or a directory of them (repeatable): '
                           'training data')
    bags.add_argument('--val-bag', type=Path, action='append', metavar='DIR',
                      help='a rosbag2 directory, or a directory of them (repeatable): '
                           'validation data')
    bags.add_argument('--tips-topic', default='tip_positions',
                      help='PoseArray topic (default %(default)s)')
    bags.add_argument('--torques-topic', default='torque_commands',
                      help='JointState topic (default %(default)s)')
    bags.add_argument('--finger', type=int, default=None,
                      help='learn from this finger only (default: every finger that was excited)')
    bags.add_argument('--meas-std', type=float, default=None,
                      help='tip measurement noise σ [m] for the KF/RTS and the derived estimator '
                           '(default: estimated from the settle phase at zero torque; a bag '
                           'without one is refused)')
    bags.add_argument('--min-duration', type=float, default=1.0,
                      help='refuse a bag with less commanded time than this [s] '
                           '(default %(default)s)')
    parser.add_argument('--preset', choices=sorted(PRESETS), default=None,
                        help='training preset (default: gripper with --bag, labels then the '
                             'simulation error, docs/own_gripper.md; default with --data)')
    parser.add_argument('--variant', choices=sorted(DATA_VARIANTS), default=None,
                        help='training signals: identifying (default preset) or paper (u1..u3)')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the initial weights and the batch shuffles '
                             '(the shipped models use 0)')
    parser.add_argument('--epochs', type=int, default=None, help='override the preset')
    parser.add_argument('--rollout-epochs', type=int, default=None,
                        help="override the preset's simulation-stage epochs (--bag only; 0 = off)")
    parser.add_argument('--patience', type=int, default=None,
                        help="stop after this many epochs without a new best validation loss "
                             "(default: the preset's; both presets run every epoch)")
    parser.add_argument('--jitter', type=float, default=0.0,
                        help='robustness check: multiply every training state and label by '
                             '1 + JITTER·N(0, 1), e.g. 1e-9 to flip float32 roundings (0 = off)')
    parser.add_argument('--jitter-seed', type=int, default=0, help='seed of the --jitter draws')
    parser.add_argument('--jerk-psd', type=float, default=None,
                        help='KF/RTS white-jerk intensity; '
                             'default: tuned by likelihood on the data')
    parser.add_argument('--sv-penalty', type=float, default=0.0,
                        help='weight of the penalty on G2\'s smallest singular value (0 = off)')
    parser.add_argument('--sv-floor', type=float, default=0.3,
                        help='singular-value floor (scaled units)')
    parser.add_argument('--install', action='store_true',
                        help=f'copy the checkpoint to the package as the shipped model '
                             f'({DEFAULT_MODEL.name})')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(message)s')
    set_torch_threads(1)

    bags = bool(args.bag or args.val_bag)
    args.preset = args.preset or ('gripper' if bags else 'default')
    settings = replace(PRESETS[args.preset], seed=args.seed)
    if args.rollout_epochs is not None:
        if not bags or args.rollout_epochs < 0:
            parser.error('--rollout-epochs takes an int >= 0 and needs --bag (the '
                                 'simulation stage trains on contiguous records)')
        settings = replace(settings, rollout_epochs=args.rollout_epochs)
    elif settings.rollout_epochs and not bags:
        parser.error(f'the {args.preset} preset trains on contiguous records: give --bag')
    if args.epochs is not None:
        if args.epochs < 1:
            parser.error('--epochs must be >= 1')
        settings = replace(settings, epochs=args.epochs)
    if args.patience is not None:
        try:
            settings = replace(settings, patience=args.patience)
        except ValueError as exc:
            parser.error(f'--patience: {exc}')
    if not (np.isfinite(args.jitter) and 0.0 <= args.jitter < 1e-3):
        parser.error(f'--jitter must be in [0, 1e-3), got {args.jitter}')
    if args.sv_penalty != 0:
        try:
            settings = replace(settings, sv_penalty=args.sv_penalty, sv_floor=args.sv_floor)
        except ValueError as exc:
            parser.error(f'--sv-penalty/--sv-floor: {exc}')
    if args.bag or args.val_bag:
        return _main_bags(parser, args, settings)
    if args.data is None:
        parser.error('give --data DIR (.npz files) or --bag DIR ... --val-bag DIR (rosbag2)')
    variant = args.variant or ('paper' if args.preset == 'paper' else 'identifying')
    names = list(DATA_VARIANTS[variant]) + [VALIDATION]
    try:
        records = load_records(args.data, names)
    except DatasetError as exc:
        parser.error(str(exc))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parser.error(f'cannot create output directory {args.out}: {exc.strerror}')

    data = label_records(records, variant, args.jerk_psd)
    print(f'KF/RTS white-jerk intensity q = {data.jerk_psd:g} (m/s³)²/Hz')
    bar = tqdm(total=settings.epochs, desc=f'train ({args.preset})', unit='epoch')

    def on_epoch(epoch, tl, vl):
        bar.update(1)
        bar.set_postfix(train=f'{tl:.3g}', val=f'{vl:.3g}')

    with training_run.staged(args.out) as stage:
        _, metrics, result, scores = fit(data, settings, stage / 'model.pt', args.jitter,
                                         args.jitter_seed, on_epoch)
        bar.close()
        training_run.write_report(
            stage, result, metrics, scores, records[VALIDATION].t, data.acc_true,
            loss_title=f'Training loss, {args.preset} preset ({variant} data)',
            accel_file='fig3_accel_u4.png',
            accel_title=f'u4 validation, {args.preset} preset: predicted (dashed) vs true (solid)')
    ckpt_path = args.out / 'model.pt'
    print('\n'.join(scores.lines('u4 R² vs true acceleration')))
    print(f'training: {len(result.train_loss)} epochs in {result.seconds:.1f} s; wrote {args.out}')
    if args.install:
        DEFAULT_MODEL.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(ckpt_path, DEFAULT_MODEL)
        DEFAULT_MODEL.with_suffix('.json').write_text(json.dumps(metrics, indent=2))
        print(f'installed as {DEFAULT_MODEL}')
    return 0


def _main_bags(parser: argparse.ArgumentParser, args: argparse.Namespace, settings) -> int:
    """The ``--bag`` path: arguments checked, then
    :func:`~soft_gripper_sdre.tools.train_bags.train_from_bags`."""
    from soft_gripper_sdre.analysis.bag_dataset import BagDataError
    from soft_gripper_sdre.tools.train_bags import train_from_bags

    if args.data is not None:
        parser.error('--data and --bag exclude each other')
    if not args.bag or not args.val_bag:
        parser.error('--bag needs --val-bag (the validation recording) and the other way round')
    if args.variant is not None or args.jitter > 0:
        parser.error('--variant and --jitter apply to --data only')
    if args.meas_std is not None and not (np.isfinite(args.meas_std) and 0 <= args.meas_std < 0.01):
        parser.error(f'--meas-std must be in [0, 0.01) m, got {args.meas_std}')
    if not (np.isfinite(args.min_duration) and args.min_duration > 0):
        parser.error(f'--min-duration must be > 0 s, got {args.min_duration}')
    if args.finger is not None and not 0 <= args.finger < 4:
        parser.error(f'--finger must be in [0, 3], got {args.finger}')
    if args.jerk_psd is not None and not (np.isfinite(args.jerk_psd) and args.jerk_psd > 0):
        parser.error(f'--jerk-psd must be > 0, got {args.jerk_psd}')
    if args.out.exists() and not args.out.is_dir():
        parser.error(f'--out {args.out} exists and is not a directory')
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parser.error(f'cannot create the parent of {args.out}: {exc.strerror}')
    try:
        train_from_bags(args.bag, args.val_bag, args.out, settings, tips_topic=args.tips_topic,
                        torques_topic=args.torques_topic, min_duration=args.min_duration,
                        finger=args.finger, meas_std=args.meas_std, jerk_psd=args.jerk_psd)
    except BagDataError as exc:
        parser.error(str(exc))
    if args.install:
        DEFAULT_MODEL.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(args.out / 'model.pt', DEFAULT_MODEL)
        shutil.copyfile(args.out / 'metrics.json', DEFAULT_MODEL.with_suffix('.json'))
        print(f'installed as {DEFAULT_MODEL}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
