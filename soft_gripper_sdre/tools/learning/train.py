"""Learn the SDC model from excitation data: derivative estimates, training, validation, figures.

    python -m soft_gripper_sdre.tools.learning.train --data data/excitation --out runs/train
        [--preset paper]
    python -m soft_gripper_sdre.tools.learning.train --bag DIR [--bag DIR ...] --val-bag DIR
        --out runs/train_bags

With ``--bag`` the data come from rosbag2 recordings of ``tip_positions`` and ``torque_commands``
(the excitation node and a recorder, on the simulator or a robot):
:mod:`soft_gripper_sdre.tools.learning.train_bags`. A finger of any shape is learned that way: its
m inputs (1 to 4) are the command's names ``<finger>/ax<k>``, ``--task-dim`` says whether the tip
has 2 coordinates (x, y; the default) or 3 (x, y, z; ``auto``: 3 when a tip's z moves), and
``--input-lower``/``--input-upper`` give each input's bounds for the checkpoint (default: the
range the commands spanned, widened to hold 0). The rest of this text is about ``--data``, the
hand's records (a planar tip, two torques).

Writes OUT/model.pt (checkpoint), OUT/metrics.json, OUT/fig2_loss.png (the paper's Figure 2) and
OUT/fig3_accel_u4.png (Figure 3), all together or none (the pipeline both paths share:
:mod:`~soft_gripper_sdre.analysis.training_run`). ``--install`` also copies the checkpoint and
its metrics into the package as the shipped default model. Training labels are the KF + RTS
estimates from the measured tip positions; validation (u4) is scored against the simulator's true
accelerations.

Exit status: 0 when done (with ``--bag``: the model fit to control and ``OUT/params.yaml``
written), 2 for bad arguments or unusable bags (nothing written), 3 with ``--bag`` when the
model was trained and written but judged not fit to control, or no controller setting passed
its checks: the reason is printed and ``params.yaml`` is not written, so a script's
``train … && deploy …`` stops here.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import logging
from pathlib import Path
import shutil
import sys

import numpy as np
from tqdm import tqdm

from soft_gripper_sdre.analysis import training_run
from soft_gripper_sdre.analysis.training_run import fit
from soft_gripper_sdre.learning.dataset import DatasetError, load_records
from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION, label_records
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, set_blas_threads, set_torch_threads
from soft_gripper_sdre.learning.train_settings import PRESETS, TrainSettings
from soft_gripper_sdre.tools.learning import NOT_FIT


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.learning.train',
                                     description=__doc__.split('\n\n')[0],
                                     epilog='exit status: 0 done (--bag: params.yaml written); '
                                     '2 bad arguments or bags, nothing written; 3 (--bag) the '
                                     'model was written but judged not fit to control, or no '
                                     'controller setting passed its checks: no params.yaml')
    parser.add_argument('--data', type=Path,
                        help='directory with <signal>.npz files (tools.learning.collect)')
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
    bags.add_argument('--task-dim', choices=('auto', '2', '3'), default=None,
                      help='coordinates of the tip the model learns: 2 (x, y) or 3 (x, y, z); '
                           "auto: 3 when a tip's z moves in the training bags (planar drivers "
                           "publish z = 0), else 2. Default 2: this package's hand is learned "
                           "in x, y though its simulated tips' z moves")
    bags.add_argument('--input-lower', type=float, nargs='+', metavar='U',
                      help='lower bound of each input, one value per input in the SI unit of its '
                           'command (N·m, N, Pa), recorded in the checkpoint; with '
                           '--input-upper (default: the range the recorded commands spanned)')
    bags.add_argument('--input-upper', type=float, nargs='+', metavar='U',
                      help='upper bound of each input, one value per input (see --input-lower)')
    bags.add_argument('--tries', type=int, default=None,
                      help='trainings at most, seeds --seed, +1, ...: another while the model is '
                           'not fit to control, no setting passed its checks, the fingers\' own '
                           'fits (where they found an input lag) expect the grasp to miss 5 %% of '
                           'its travel, or, with no such fit, the settings score over 10 %% on the '
                           'model (the input gain halved among its checks); the best is kept '
                           '(default 3; 1: one training)')
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
                             "(default: the preset's; every preset runs every epoch)")
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
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(message)s')
    set_torch_threads(1)
    set_blas_threads(1)
    settings = _settings(parser, args)
    if args.bag or args.val_bag:
        if not _main_bags(parser, args, settings):
            return NOT_FIT
    else:
        _main_data(parser, args, settings)
    if args.install:
        DEFAULT_MODEL.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(args.out / 'model.pt', DEFAULT_MODEL)
        shutil.copyfile(args.out / 'metrics.json', DEFAULT_MODEL.with_suffix('.json'))
        print(f'installed as {DEFAULT_MODEL}')
    return 0


def _settings(parser: argparse.ArgumentParser, args: argparse.Namespace) -> TrainSettings:
    """The preset with the command line's overrides (``args.preset`` set to the one used)."""
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
    return settings


def _main_data(parser: argparse.ArgumentParser, args: argparse.Namespace,
               settings: TrainSettings) -> None:
    """The ``--data`` path: the records read and labelled, the model trained and written."""
    if args.data is None:
        parser.error('give --data DIR (.npz files) or --bag DIR ... --val-bag DIR (rosbag2)')
    if args.task_dim is not None or args.input_lower is not None or args.input_upper is not None:
        parser.error('--task-dim, --input-lower and --input-upper apply to --bag only (the .npz '
                     "records are the hand's: a planar tip, two torques)")
    if args.tries is not None:
        parser.error('--tries applies to --bag only (the .npz records train the hand\'s model '
                     'once, with --seed)')
    variant = args.variant or ('paper' if args.preset == 'paper' else 'identifying')
    names = list(DATA_VARIANTS[variant]) + [VALIDATION]
    clock = training_run.Stages()
    try:
        records = load_records(args.data, names)
    except DatasetError as exc:
        parser.error(str(exc))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parser.error(f'cannot create output directory {args.out}: {exc.strerror}')

    clock.lap('read')
    data = label_records(records, variant, args.jerk_psd)
    clock.lap('labels')
    print(f'KF/RTS white-jerk intensity q = {data.jerk_psd:g} (m/s³)²/Hz')
    bar = tqdm(total=settings.epochs, desc=f'train ({args.preset})', unit='epoch')

    def on_epoch(epoch, tl, vl):
        bar.update(1)
        bar.set_postfix(train=f'{tl:.3g}', val=f'{vl:.3g}')

    with training_run.staged(args.out) as stage:
        _, metrics, result, scores = fit(data, settings, stage / 'model.pt', args.jitter,
                                         args.jitter_seed, on_epoch)
        bar.close()
        clock.seconds.update(training=result.seconds, **result.timings)
        clock.lap('checkpoint')
        clock.seconds['checkpoint'] -= result.seconds
        metrics['timings'] = clock.record()
        training_run.write_report(
            stage, result, metrics, scores, records[VALIDATION].t, data.acc_true,
            loss_title=f'Training loss, {args.preset} preset ({variant} data)',
            accel_file='fig3_accel_u4.png',
            accel_title=f'u4 validation, {args.preset} preset: predicted (dashed) vs true (solid)')
    print('\n'.join(scores.lines('u4 R² vs true acceleration')))
    print(f'training: {len(result.train_loss)} epochs in {result.seconds:.1f} s; wrote {args.out}')
    clock.lap('report')
    print(clock.line())


def _main_bags(parser: argparse.ArgumentParser, args: argparse.Namespace,
               settings: TrainSettings) -> bool:
    """The ``--bag`` path: arguments checked, then
    :func:`~soft_gripper_sdre.tools.learning.train_bags.train_from_bags`; whether it wrote the
    loop's settings (``params.yaml``: the model is fit to control and a setting passed its
    checks)."""
    from soft_gripper_sdre.analysis.bag_dataset import BagDataError
    from soft_gripper_sdre.sim.shape import ShapeError
    from soft_gripper_sdre.tools.learning.train_bags import PARAMS_FILE, train_from_bags

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
    if args.tries is not None and not 1 <= args.tries <= 10:
        parser.error(f'--tries must be in [1, 10], got {args.tries}')
    if (args.input_lower is None) != (args.input_upper is None):
        parser.error('--input-lower and --input-upper go together: one value per input each '
                     '(or neither: the range the recorded commands spanned)')
    if args.out.exists() and not args.out.is_dir():
        parser.error(f'--out {args.out} exists and is not a directory')
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parser.error(f'cannot create the parent of {args.out}: {exc.strerror}')
    try:
        train_from_bags(args.bag, args.val_bag, args.out, settings, tips_topic=args.tips_topic,
                        torques_topic=args.torques_topic, min_duration=args.min_duration,
                        finger=args.finger, meas_std=args.meas_std, jerk_psd=args.jerk_psd,
                        task_dim=('auto' if args.task_dim == 'auto' else int(args.task_dim or 2)),
                        input_lower=args.input_lower, input_upper=args.input_upper,
                        **({} if args.tries is None else {'draws': args.tries}))
    except (BagDataError, ShapeError) as exc:
        parser.error(str(exc))
    return (args.out / PARAMS_FILE).is_file()


if __name__ == '__main__':
    sys.exit(main())
