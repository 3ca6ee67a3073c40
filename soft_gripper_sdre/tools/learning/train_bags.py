"""Training from rosbag2 recordings: the ``--bag`` path of ``tools.learning.train``.

    python -m soft_gripper_sdre.tools.learning.train --bag runs/bags/train
        --val-bag runs/bags/val/u4 --out runs/train_bags

Every ``--bag`` (a rosbag2 directory, or a directory of them) is read and checked first
(:mod:`soft_gripper_sdre.analysis.bag_dataset`); a bad one ends the tool with exit status 2 and a
message naming it before anything is written. The finger's shape comes from the bags: m inputs
from the command's names ``<finger>/ax<k>`` (the same m in every bag), the task dimension d from
``task_dim`` (2 by default; auto: 3 when a tip's z moves, else 2); the input bounds the
checkpoint records are the given ones, which every recorded command must respect, or the range
the commands spanned, widened to hold 0 (the rest input).
Each excited finger of each bag gives training samples: KF + RTS states and acceleration labels
on the tip stamps (or on a uniform grid when the stamps jitter), the command held onto them, the
state translated by that finger's rest pose.
The checkpoint's ``data`` records the provenance: every bag with its topics, types, message
counts, rates, jitter, gaps, durations, fingers, rest poses, noise levels and sample counts.

A training is one draw (one seed) of a nonconvex fit. Another is drawn with the next seed, up to
``draws`` in all, while the last one asks for it (:class:`Draw`): the model is not fit to control;
a model fit to control gave no setting that passed its checks; the fingers' own fits with an
input lag expect the grasp to miss
:data:`~soft_gripper_sdre.analysis.loop_settings.KEEP_NOMINAL` of the travel; or, where no such
fit judges the settings, their score on the model is over :data:`RETRY_SCORE`. The best draw is
kept; each is printed and listed in the metrics (``draws``).

The outputs are written to a temporary directory beside ``--out`` and moved into it only when
all are complete, so a failed run leaves nothing half-written there. Validation R² is scored
against the validation bags' own KF + RTS labels (a recording has no true acceleration).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm
import yaml

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.analysis import finger_fits, loop_settings, model_fitness, training_run
from soft_gripper_sdre.analysis.bag_dataset import (
    DEFAULT_GAP_PERIODS,
    MIN_SAMPLES,
    BagDataError,
    FingerSamples,
    Recording,
    check_within,
    excited_fingers,
    first_torque_ns,
    label_finger,
    read_recording,
    recorded_bounds,
    settle_estimates,
    settle_noise,
    task_dimension,
    tip_stretches,
)
from soft_gripper_sdre.analysis.data_facts import data_facts
from soft_gripper_sdre.control.tracking import roll_off_corner_hz
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.learning.rollout import Run
from soft_gripper_sdre.learning.train_settings import TrainSettings
from soft_gripper_sdre.learning.training import TrainResult, fingerprint, train
from soft_gripper_sdre.sim.shape import INPUT_GAIN_RANGE, FingerShape, InputBounds, ShapeError

#: samples of a recording's first stretch its jerk intensity is tuned on
TUNE_SAMPLES = 2000
#: white-jerk intensities tried [(m/s³)²/Hz]: from a slow, soft finger's to a fast, stiff one's
JERK_GRID = np.logspace(-3, 7, 11)
#: written only for a model fit to control whose settings passed their closed-loop check
PARAMS_FILE = 'params.yaml'
#: trainings of one recipe at most by default (``--tries``; seeds ``--seed``, +1, …; module doc)
MAX_DRAWS = 3
#: where no fit of a finger with an input lag judges the chosen settings, another draw is made
#: while their score on the model (``Derivation.score`` of
#: :mod:`~soft_gripper_sdre.analysis.loop_settings`: chiefly the move with the model's input gain
#: halved, the loop's reliance on what the model says of the finger's statics) is over this
#: share of the travel (docs/own_gripper.md, "Draws")
RETRY_SCORE = 0.10


def expand_bag_paths(paths: list[Path]) -> list[Path]:
    """Each path as given if it is a rosbag2 directory (or anything else: reading it will say
    what is wrong), or the bags directly inside it, in name order."""
    out = []
    for path in paths:
        path = Path(path)
        inner = sorted(p for p in path.iterdir() if (p / 'metadata.yaml').is_file()) \
            if path.is_dir() and not (path / 'metadata.yaml').is_file() else []
        out.extend(inner or [path])
    return out


def load_bags(paths: list[Path], tips_topic: str, torques_topic: str, min_duration: float,
              finger: int | None) -> list[tuple[Recording, list[int]]]:
    """Every bag read and checked, with the fingers to learn from (``finger``, or every excited
    one).

    Raises:
        BagDataError: a bag cannot be used (named), or no finger of it was excited.
    """
    loaded = []
    for path in expand_bag_paths(paths):
        rec = read_recording(path, tips_topic, torques_topic, min_duration)
        excited = excited_fingers(rec)
        if finger is not None:
            if finger >= rec.n_fingers:
                raise BagDataError(f'bag {path}: --finger {finger}, but {rec.tips_topic} holds '
                                   f'{rec.n_fingers} finger(s)')
            if finger not in excited:
                raise BagDataError(f'bag {path}: finger {finger} received only zero torque')
            excited = [finger]
        if not excited:
            raise BagDataError(f'bag {path}: every torque in {rec.torques_topic} is zero '
                               '(nothing was excited)')
        loaded.append((rec, excited))
    return loaded


def tune_jerk(rec: Recording, finger: int, meas_std: float, dims: int = 2) -> float:
    """The KF/RTS jerk intensity of ``finger`` tuned by likelihood on its first excited tips
    (:func:`tuning_stretch`), their first ``dims`` coordinates."""
    t, xy = tuning_stretch(rec, finger, dims)
    if derivatives.is_uniform(t):
        return derivatives.tune_jerk_psd(t, xy, meas_std, JERK_GRID, compiled=True)
    return derivatives.tune_jerk_psd_irregular(t, xy, meas_std, JERK_GRID, compiled=True)


def _plain(value):
    """``value`` with numpy scalars and arrays as Python numbers and lists (a checkpoint holds
    plain data only)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _finger_name(rec: Recording, finger: int) -> str:
    """The name the bag gives finger ``finger`` (its torque names), else the default name."""
    return rec.finger_names[finger] if finger < len(rec.finger_names) else FINGER_NAMES[finger]


def label_bags(loaded: list[tuple[Recording, list[int]]], jerk: float | None,
               meas_std: float | None, gap_periods: float = DEFAULT_GAP_PERIODS, dims: int = 2
               ) -> tuple[list[FingerSamples], list[dict], np.ndarray]:
    """Samples of every (bag, finger) for the task dimension ``dims``, the provenance of each
    bag, and the first rest tip (3,).

    ``jerk`` None: the KF/RTS jerk intensity of each (bag, finger) tuned by likelihood on its own
    tips (:func:`tune_jerk`): a slow signal's labels want a smoother filter than a fast one's,
    and one intensity for every signal leaves one of them with labels that are mostly noise.
    ``meas_std`` None: each finger's noise level from its settle phase (a bag without one is
    refused, :func:`~soft_gripper_sdre.analysis.bag_dataset.settle_noise`)."""
    samples, provenance, first_rest = [], [], None
    for rec, fingers in loaded:
        info = rec.describe()
        info['fingers'] = {}
        for f in fingers:
            rest, sigma, n_settle = (settle_estimates if meas_std is not None
                                     else settle_noise)(rec, f, dims)
            used = meas_std if meas_std is not None else sigma
            q = jerk if jerk is not None else tune_jerk(rec, f, used, dims)
            got = label_finger(rec, f, q, used, rest, gap_periods, dims)
            samples += got
            first_rest = rest if first_rest is None else first_rest
            info['fingers'][_finger_name(rec, f)] = {
                'rest_tip': rest, 'settle_samples': n_settle, 'noise_std_settle': sigma,
                'noise_std_used': used, 'jerk_psd': q, 'stretches': [s.info for s in got],
                'samples': int(sum(len(s.t) for s in got))}
        provenance.append(info)
    return samples, _plain(provenance), first_rest


def _stack(samples: list[FingerSamples]) -> tuple[np.ndarray, ...]:
    return tuple(np.concatenate([getattr(s, k) for s in samples]) for k in ('t', 'x', 'u', 'acc'))


def validation_segments(samples: list[FingerSamples]) -> list[tuple[np.ndarray, ...]]:
    """(t, x, u) of every stretch of samples, cut where samples were left out (a hole in the
    grid), for the free-run check and the simulation stage of training."""
    out = []
    for smp in samples:
        d = np.diff(smp.t)
        cuts = np.flatnonzero(d > 1.5 * np.median(d)) + 1
        for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), len(smp.t)]):
            if b - a >= 2:
                out.append((smp.t[a:b], smp.x[a:b], smp.u[a:b]))
    return out


def runs(samples: list[FingerSamples]) -> list[Run]:
    """The contiguous stretches of ``samples`` as the simulation stage of training takes them."""
    return [Run(x, u, float(np.median(np.diff(t)))) for t, x, u in validation_segments(samples)]


def tuning_stretch(rec: Recording, finger: int, dims: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(t [s], tips (N, dims)) of ``finger``'s first :data:`TUNE_SAMPLES` excited tips: from its
    first non-zero torque on, within the stretch of tips (no long gap) that holds it; the whole
    first stretch when it has no tips from then on. The tips at rest before it (a driver's idle
    time, the settle phase) would tune the estimator to a finger that does not move."""
    idx = _tuning_index(rec, finger)
    ns = rec.tip_ns[idx]
    return (ns - ns[0]) / 1e9, rec.tips[idx, finger, :dims]


def _tuning_index(rec: Recording, finger: int) -> np.ndarray:
    """The tip indices of :func:`tuning_stretch`."""
    onset = first_torque_ns(rec, finger)
    onset = rec.tip_ns[0] if onset is None else onset
    stretches = tip_stretches(rec)
    chosen = next((s for s in stretches if rec.tip_ns[s.stop - 1] >= onset), stretches[0])
    idx = np.arange(chosen.start, chosen.stop)
    moving = idx[rec.tip_ns[idx] >= onset]
    return (moving if len(moving) >= MIN_SAMPLES else idx)[:TUNE_SAMPLES]


def excitation_stretch(rec: Recording, finger: int, dims: int = 2,
                       rest: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray,
                                                                np.ndarray]:
    """(t [s], inputs (N, m), tips (N, dims)) of :func:`tuning_stretch`'s tips with the command
    in force at each (the last one stamped at or before it; ``rest`` (m,), zeros by default,
    before the first), for :func:`~soft_gripper_sdre.analysis.loop_settings.unmodelled_delay`."""
    idx = _tuning_index(rec, finger)
    ns = rec.tip_ns[idx]
    at = np.searchsorted(rec.cmd_ns, ns, side='right') - 1
    before = np.zeros(rec.n_inputs) if rest is None else np.asarray(rest, dtype=float)
    u = np.where((at >= 0)[:, None], rec.torques[np.maximum(at, 0), finger, :], before)
    return (ns - ns[0]) / 1e9, u, rec.tips[idx, finger, :dims]


def params_yaml(derived: loop_settings.Derivation, model_path: Path, finger_names: list[str],
                source: str) -> str:
    """The parameter file of the estimator, the controller and the trajectory node's checked move
    for ``derived`` settings (:meth:`~soft_gripper_sdre.analysis.loop_settings.Derivation.params`
    with the controller's ``model_path``)."""
    from soft_gripper_sdre.nodes.params import params_file_key
    d, facts = derived.settings, derived.facts
    nodes = derived.params(finger_names)
    nodes['controller'] = {'model_path': str(model_path.resolve()), **nodes['controller']}
    # the trajectory node's fingers and plan (every finger grasps; the plan's length is the sum
    # of its times), which tools.graph.deploy reads
    plan = GraspProfile()
    nodes['trajectory'] = {'finger_names': list(finger_names),
                           'grasp_fingers': list(range(len(finger_names))), 'others': 'hold',
                           't_start': plan.t_start, 't_close': plan.t_close,
                           't_hold': plan.t_hold, 't_open': plan.t_open, **nodes['trajectory']}
    body = {params_file_key(node): {'ros__parameters': _plain(values)}
            for node, values in nodes.items()}
    if facts.d == 2 and facts.path is None:
        move = (f'# {1e3 * facts.travel:.3g} mm at {facts.direction:.0f}° from +X '
                'toward +Y (trajectory: close_distance, side_distance;\n')
    else:
        move = (f'# {derived.move_text()}\n# (trajectory: '
                + ('close_path, waypoints relative to rest' if facts.path is not None else
                   'direction and close_distance') + ';\n')
    head = (f'# Estimator and controller settings derived from {source} by tools.learning.train\n'
            f'# (closed-loop bandwidth {d.bandwidth_hz:g} Hz), and the move they were checked on:\n'
            + move +
            '# contact_distance = close_distance: the whole move scored as free space). How they '
            'are\n'
            '# derived and checked: docs/own_gripper.md. Use: --ros-args --params-file '
            '<this file>\n')
    return head + yaml.safe_dump(body, sort_keys=False)


def train_from_bags(train_paths: list[Path], val_paths: list[Path], out: Path,
                    settings: TrainSettings, *,
                    tips_topic: str, torques_topic: str, min_duration: float, finger: int | None,
                    meas_std: float | None, jerk_psd: float | None, task_dim: str | int = 2,
                    input_lower: list[float] | None = None,
                    input_upper: list[float] | None = None, draws: int = MAX_DRAWS) -> dict:
    """Read, label, train, validate, judge, derive the loop's settings and write (module doc);
    returns the metrics.

    Args:
        task_dim: 2, 3 or 'auto' (:func:`~soft_gripper_sdre.analysis.bag_dataset.task_dimension`
            on the training bags); 2 with a tip whose z moves prints a note saying so.
        input_lower, input_upper: one bound per input (both or neither): the bounds the
            actuators deliver, which the checkpoint records and the derived loop stays within;
            None: the range the training bags' commands spanned.
        draws: trainings at most (seeds ``settings.seed``, +1, …): another while the last
            :class:`Draw` asks for a retry; the best by :meth:`Draw.rank` is kept (module doc).

    Raises:
        BagDataError: a bag cannot be used, the bags disagree on the number of inputs, the task
            dimension does not fit them, or a command lies outside the given bounds (before
            anything is written).
        ShapeError: input bounds that cannot be used (naming ``--input-lower/--input-upper``).
    """
    clock = training_run.Stages()
    train_set = load_bags(train_paths, tips_topic, torques_topic, min_duration, finger)
    val_set = load_bags(val_paths, tips_topic, torques_topic, min_duration, finger)
    shape, bounds = finger_shape(train_set, val_set, task_dim, input_lower, input_upper)
    clock.lap('read')
    data = _label_sets(train_set, val_set, jerk_psd, meas_std, shape, bounds,
                       bounds_given=input_lower is not None)
    clock.lap('labels')
    # never a params.yaml from another model beside this one
    with training_run.staged(out, stale=(PARAMS_FILE,)) as stage:
        tried: list[_Trained] = []
        for k in range(draws):
            t = _draw(data, replace(settings, seed=settings.seed + k), clock,
                      stage / ('model.pt' if k == 0 else f'draw{k}.pt'), bounds, tips_topic,
                      torques_topic)
            tried.append(t)
            more = k + 1 < draws and t.draw.retry
            print(f'draw {k + 1} (seed {t.draw.seed}): {t.draw.text()}'
                  + (f'; another draw (seed {t.draw.seed + 1})' if more else ''), flush=True)
            if not more:
                break
        kept = min(tried, key=lambda t: t.draw.rank())
        for t in tried:
            if t is not kept:
                t.path.unlink()
        kept.path.replace(stage / 'model.pt')
        if len(tried) > 1:
            print(f'kept draw {tried.index(kept) + 1} (seed {kept.draw.seed})', flush=True)
        result, verdict, scores, metrics = kept.result, kept.verdict, kept.scores, kept.metrics
        metrics['draws'] = [t.draw.summary() for t in tried]
        clock.lap('checkpoint')
        metrics['timings'] = clock.record()
        training_run.write_report(
            stage, result, metrics, scores, data.t_val, data.acc_val,
            loss_title=f'Training loss from bags, {settings.preset} preset',
            accel_file='fig3_accel_val.png',
            accel_title='validation bags: predicted (dashed) vs KF + RTS labels (solid)')
        derived = verdict.derived
        if derived is not None and derived.settings is not None:
            (stage / PARAMS_FILE).write_text(params_yaml(
                derived, out / 'model.pt', list(train_set[0][0].finger_names),
                ', '.join(str(p) for p in train_paths)))
    clock.lap('report')
    print(f'finger shape: {shape.m} input(s) ({bounds}), a tip of {shape.d} coordinates '
          f'({", ".join(shape.axes)})')
    print('\n'.join(scores.lines('validation R² vs the KF + RTS labels')))
    if min(scores.r2 + scores.r2_ls) < 0.0:
        print('  (below 0: the validation labels vary less than the predictions miss them. Where '
              'the baseline is below 0 too, the labels are mostly noise or smoothed flat at this '
              'signal\'s speed; the free run below judges the model on the recorded positions '
              'instead)')
    print(f'training: {len(result.train_loss)} + {len(result.rollout_loss)} epochs (label and '
          f'simulation stages) on {len(data.x)} samples from '
          f'{len(data.provenance)} bag(s) in {result.seconds:.1f} s; wrote {out}')
    report_fitness(verdict.fitness, derived, out)
    print(clock.line())
    return metrics


def finger_shape(train_set: list[tuple[Recording, list[int]]],
                 val_set: list[tuple[Recording, list[int]]], task_dim: str | int = 2,
                 input_lower: list[float] | None = None,
                 input_upper: list[float] | None = None) -> tuple[FingerShape, InputBounds]:
    """The shape of the finger the bags recorded and the bounds of its inputs.

    m is the number of inputs every bag's command names per finger; d is
    :func:`~soft_gripper_sdre.analysis.bag_dataset.task_dimension` of the training bags; the
    bounds are ``input_lower``/``input_upper`` (one value per input), which every command of
    every bag must respect, or the range the training bags' commands spanned
    (:func:`~soft_gripper_sdre.analysis.bag_dataset.recorded_bounds`).

    Raises:
        BagDataError: bags with different numbers of inputs (naming the bags and their command
            names), d = 3 for planar tips, a command outside the given bounds, an input that
            never changed.
        ShapeError: bounds of the wrong count or empty, or only one of the two lists given.
    """
    recs = [rec for rec, _ in train_set + val_set]
    first = recs[0]
    for rec in recs[1:]:
        if rec.n_inputs != first.n_inputs:
            raise BagDataError(f'bag {rec.path} commands {rec.n_inputs} input(s) per finger '
                               f'({list(rec.joint_names)[:8]}), bag {first.path} '
                               f'{first.n_inputs} ({list(first.joint_names)[:8]}): every bag '
                               'must record the same finger')
    d = task_dimension([rec for rec, _ in train_set], task_dim)
    moving = [rec for rec, _ in train_set if rec.z_moves()]
    if d == 2 and moving:
        z = np.concatenate([rec.tips[:, :, 2] - rec.tips[:1, :, 2] for rec in moving])
        print(f"note: the tips' z moves in {len(moving)} training bag(s) (by up to "
              f'{1e3 * float(np.abs(z).max()):.3g} mm); this model learns x and y only '
              '(--task-dim 3 or auto learns z too)')
    shape = FingerShape(d, first.n_inputs)
    what = '--input-lower/--input-upper'
    if (input_lower is None) != (input_upper is None):
        raise ShapeError(f'{what}: give both, one value per input, or neither (the range the '
                         'commands spanned)')
    if input_lower is None:
        bounds = recorded_bounds([rec for rec, _ in train_set])
    else:
        bounds = InputBounds.parse(input_lower, input_upper, shape.m, what)
        check_within(recs, bounds, what)
    return shape, bounds


@dataclass
class _BagData:
    """The labelled bags: their samples, stacked for training, with their provenance, the first
    rest tip (3,), the measurement σ [m] and the labels' jerk intensity [(m/s³)²/Hz]."""

    train_set: list[tuple[Recording, list[int]]]
    samples: list[FingerSamples]
    val_samples: list[FingerSamples]
    provenance: list[dict]
    val_provenance: list[dict]
    rest_tip: np.ndarray
    noise: float
    jerk: float
    shape: FingerShape
    bounds: InputBounds
    #: the bounds were given (the actuators'), not read off the commands' range
    bounds_given: bool = False

    def __post_init__(self) -> None:
        _, self.x, self.u, self.acc = _stack(self.samples)
        self.t_val, self.x_val, self.u_val, self.acc_val = _stack(self.val_samples)

    @cached_property
    def own_fits(self) -> tuple[list[finger_fits.LinearFinger], list[str]]:
        """Each finger's own linear fit and the fingers without one
        (:func:`~soft_gripper_sdre.analysis.finger_fits.fit_fingers`): the recordings', the same
        for every draw, so fitted once."""
        return finger_fits.fit_fingers(self.samples, self.val_samples)

    @property
    def dt(self) -> float:
        """The first training bag's median tip period [s]."""
        return float(np.median(np.diff(self.train_set[0][0].tip_ns)) / 1e9)

    def info(self, tips_topic: str, torques_topic: str) -> dict:
        """The checkpoint's ``data``: where the samples came from."""
        return {'source': 'rosbag2', 'topics': {'tips': tips_topic, 'torques': torques_topic},
                'bags': self.provenance, 'validation_bags': self.val_provenance,
                'train_samples': int(len(self.x)), 'validation_samples': int(len(self.x_val)),
                'fingerprint': fingerprint(self.x, self.u, self.acc), 'jerk_psd': float(self.jerk),
                'noise_std': float(self.noise), 'shape': self.shape.to_record(),
                'input_bounds': self.bounds.to_record()}


def _label_sets(train_set: list[tuple[Recording, list[int]]],
                val_set: list[tuple[Recording, list[int]]], jerk_psd: float | None,
                meas_std: float | None, shape: FingerShape, bounds: InputBounds,
                bounds_given: bool = False) -> _BagData:
    """Both sets labelled (:func:`label_bags`), saying which jerk intensity the labels used;
    ``bounds_given``: ``bounds`` are the actuators' (given), not the commands' range.

    Raises:
        BagDataError: the first bag has no settle phase to measure the noise on, or a set gave
            no samples.
    """
    rec0, fingers0 = train_set[0]
    d = shape.d
    noise = meas_std if meas_std is not None else settle_noise(rec0, fingers0[0], d)[1]
    samples, provenance, rest_tip = label_bags(tqdm(train_set, desc='bags: KF + RTS', unit='bag'),
                                               jerk_psd, meas_std, dims=d)
    val_samples, val_provenance, _ = label_bags(val_set, jerk_psd, meas_std, dims=d)
    tuned = [f['jerk_psd'] for bag in provenance for f in bag['fingers'].values()]
    jerk = jerk_psd if jerk_psd is not None else float(np.median(tuned))
    print('KF/RTS white-jerk intensity q [(m/s³)²/Hz]: '
          + (f'{jerk_psd:g}' if jerk_psd is not None else
             f'tuned per bag and finger, {min(tuned):g} to {max(tuned):g}'))
    if not samples or not val_samples:
        raise BagDataError('no training samples' if not samples else 'no validation samples')
    return _BagData(train_set, samples, val_samples, provenance, val_provenance, rest_tip, noise,
                    jerk, shape, bounds, bounds_given)


@dataclass
class Draw:
    """One training of the recipe: its ``seed`` and its derivation (``derived``: None when the
    model is not fit to control, ``unfit`` then saying why). The rule of
    :func:`train_from_bags`'s draws."""

    seed: int
    derived: loop_settings.Derivation | None
    unfit: tuple[str, ...] = ()

    @property
    def expected(self) -> float | None:
        """The largest error / travel the fingers' own fits expect of the chosen settings (inf:
        one diverges); None: no settings, or no finger has a fit."""
        d = self.derived
        if d is None or d.settings is None or not d.on_fingers:
            return None
        return max(float('inf') if r['diverged'] else r['rmse_rel'] for r in d.on_fingers.values())

    @property
    def score(self) -> float | None:
        """The chosen settings' score on the model (:attr:`Derivation.score
        <soft_gripper_sdre.analysis.loop_settings.Derivation.score>`); None: no settings."""
        return None if self.derived is None else self.derived.score

    @property
    def retry(self) -> bool:
        """Whether another seed may do better: the model is not fit to control (one seed's model
        of a recording set can fail the verdict where the next seeds' pass), no setting passed,
        the fits expect a miss beyond KEEP_NOMINAL, or, with no fit to expect by, the score is
        over RETRY_SCORE."""
        if self.derived is None or self.derived.settings is None:
            return True
        expected = self.expected
        if expected is not None:
            return not expected <= loop_settings.KEEP_NOMINAL
        return self.score is not None and not self.score <= RETRY_SCORE

    def rank(self) -> tuple:
        """Better draws sort first: fit, with settings, the smaller expected miss, the smaller
        score, the earlier seed."""
        d, expected, score = self.derived, self.expected, self.score
        return (d is None, d is None or d.settings is None,
                math.inf if expected is None else expected,
                math.inf if score is None else score, self.seed)

    def text(self) -> str:
        d = self.derived
        if d is None:
            return 'not fit to control' + (f' ({"; ".join(self.unfit)})' if self.unfit else '')
        if d.settings is None:
            return 'fit to control; no controller setting passed its checks'
        score = ('' if self.score is None else
                 f'; score {100 * self.score:.2f} % (the worst error / travel of its checks on '
                 'the model, the input gain halved among them)')
        said = d.fingers_text()[0]
        if not said:
            said = f'error / travel on the model {100 * d.checks["sdre_ff"].rmse_rel:.2f} %'
        return said + score

    def summary(self) -> dict:
        return {'seed': self.seed, 'fit_for_control': self.derived is not None,
                'settings': self.derived is not None and self.derived.settings is not None,
                'expected_rmse_rel': self.expected, 'score': self.score}


@dataclass
class _Trained:
    """A draw's training, its checkpoint at ``path`` and what judging it gave."""

    draw: Draw
    path: Path
    result: TrainResult
    verdict: _Verdict
    scores: training_run.Scores
    metrics: dict


def _draw(data: _BagData, settings: TrainSettings, clock: training_run.Stages, path: Path,
          bounds: InputBounds, tips_topic: str, torques_topic: str) -> _Trained:
    """Train with ``settings`` (its seed), write the checkpoint to ``path``, judge it and, when
    fit, derive its settings."""
    bar = tqdm(total=settings.epochs + settings.rollout_epochs,
               desc=f'train ({settings.preset}, seed {settings.seed})', unit='epoch')
    result = train(data.x, data.u, data.acc, data.x_val, data.u_val, data.acc_val, settings,
                   lambda epoch, tl, vl: (bar.update(1),
                                          bar.set_postfix(train=f'{tl:.3g}', val=f'{vl:.3g}')),
                   runs=runs(data.samples), val_runs=runs(data.val_samples), shape=data.shape)
    bar.close()
    clock.lap('training')
    for stage, seconds in result.timings.items():          # each draw's stages add up
        clock.seconds[stage] = clock.seconds.get(stage, 0.0) + seconds
    verdict = _Verdict(data, settings, result, clock)
    _, scores, metrics = training_run.checkpoint(
        path, result, settings, rest_tip=data.rest_tip, dt=data.dt,
        data=data.info(tips_topic, torques_topic), train=(data.x, data.u, data.acc),
        val=(data.x_val, data.u_val), acc_ref=data.acc_val, describe=verdict.describe,
        input_bounds=bounds)
    clock.lap('checkpoint')                 # the writing after the verdict, not the next draw's
    unfit = () if verdict.fitness is None or verdict.fitness.fit else tuple(verdict.fitness.reasons)
    return _Trained(Draw(settings.seed, verdict.derived, unfit), path, result, verdict, scores,
                    metrics)


class _Verdict:
    """The checkpoint's ``describe`` (:func:`~soft_gripper_sdre.analysis.training_run.checkpoint`):
    the bag path's metrics, with the model's fitness for control and, for a fit model, the loop
    settings derived for it, both kept for the parameter file and the report."""

    def __init__(self, data: _BagData, settings: TrainSettings, result: TrainResult,
                 clock: training_run.Stages | None = None) -> None:
        self.data, self.settings, self.result = data, settings, result
        self.clock = clock if clock is not None else training_run.Stages()
        self.fitness: model_fitness.Fitness | None = None
        self.fingers: list[finger_fits.LinearFinger] = []
        self.gains: list[finger_fits.InputGain] = []
        self.derived: loop_settings.Derivation | None = None

    def describe(self, model, scores: training_run.Scores) -> dict:
        """The metrics of ``model``, scored as ``scores``; judges it and, when fit, derives its
        settings on the way."""
        data, result = self.data, self.result
        self.clock.lap('checkpoint')
        self.fitness = model_fitness.judge(model, validation_segments(data.val_samples))
        self.clock.lap('fitness')
        self.derived = None
        if self.fitness.fit:
            self.fingers, unfit = data.own_fits
            for name in unfit:
                print(f'  {name}: no linear fit of its own runs free within '
                      f'{100 * model_fitness.FREE_RUN_LIMIT:.0f} % of its validation motion; '
                      'the settings are checked on the model alone for it')
            self.gains, unread = finger_fits.input_gains(model, data.samples + data.val_samples)
            report_gains(self.gains, unread)
            self.clock.lap('finger_fits')
            d = data.shape.d
            facts = data_facts(data.x[:, :d], data.u, data.dt, data.noise,
                               [tuning_stretch(rec, f[0], d) for rec, f in data.train_set],
                               bounds=data.bounds, given=data.bounds_given)
            if self.gains:
                facts = replace(facts, input_gains=finger_fits.gains_by_finger(self.gains, unread))
            rest = None if data.bounds is None else data.bounds.rest
            self.derived = loop_settings.derive(model, facts, progress=lambda text: print(
                f'  closed-loop check on the model: {text}', flush=True), excitation=[
                    excitation_stretch(rec, f[0], d, rest) for rec, f in data.train_set],
                fingers=tuple(self.fingers))
            self.clock.lap('loop_settings')
        derived = self.derived
        return {**scores.common_metrics(self.settings, result), 'source': 'rosbag2',
                'rollout_epochs_run': len(result.rollout_loss),
                'best_val_sim_error': min(result.val_sim_error) if result.val_sim_error else None,
                'val_r2_labels': dict(zip(data.shape.axes, scores.r2)),
                'val_r2_ls_baseline': dict(zip(data.shape.axes, scores.r2_ls)),
                'train_samples': int(len(data.x)), 'validation_samples': int(len(data.x_val)),
                'noise_std': data.noise, 'fitness': _plain(self.fitness.summary()),
                'finger_fits': _plain([fit.summary() for fit in self.fingers]),
                'input_gains': _plain([gain.summary() for gain in self.gains]),
                'derived_settings': _plain(derived.summary()) if derived is not None else None}


def report_gains(gains: list[finger_fits.InputGain], unread: list[str]) -> None:
    """Say how strongly each finger's inputs act against the shared model."""
    for g in gains:
        print(f'  {g.name}: its inputs act {g.gain:.3g} times as strongly as the model\'s '
              f'(read below {finger_fits.STATIC_HZ:g} Hz over {g.seconds:.0f} s of its '
              'recordings); the controller divides its commands by that (input_gains)'
              + (f'; WARNING: the least-squares value {g.raw:.3g} lies outside '
                 f'{list(INPUT_GAIN_RANGE)} and was clipped: this finger is not the model\'s '
                 '(or moves against its input map); train a model of its own' if g.clipped
                 else ''))
    for name in unread:
        print(f'  {name}: no recording of {1 / finger_fits.STATIC_HZ:g} s or more moved it; its '
              'input gain is the model\'s (1)')


def limit_text(derived: loop_settings.Derivation) -> str:
    """The controller's limit as ``params.yaml`` gives it: ``torque_limit`` [N·m], or the
    bounds of ``input_lower`` / ``input_upper``."""
    bounds = derived.input_bounds()
    if bounds is None:
        return f'torque_limit {derived.settings.torque_limit:.3g} N·m'
    return f'inputs {bounds} (input_lower, input_upper)'


def roll_off_text(hz: float, period: float) -> str:
    """The roll-off's corner as the controller applies it at ``period``: ``hz``, or a tenth of
    the rate where that is lower (:func:`~soft_gripper_sdre.control.tracking.roll_off_corner_hz`),
    said so."""
    corner = roll_off_corner_hz(hz, period)
    if corner < hz:
        return f'{hz:g} Hz (applied at {corner:g} Hz, a tenth of the rate)'
    return f'{hz:g} Hz'


def report_fitness(fitness: model_fitness.Fitness, derived, out: Path) -> None:
    """Say plainly whether the model is fit to control and what was written for the loop."""
    rest, run = fitness.rest, fitness.free_run
    print(f'rest: A(0) eigenvalues with real parts up to {rest.max_real:+.3g} 1/s '
          f'(modes {", ".join(f"{hz:.2f}" for hz in rest.natural_hz) or "none"} Hz); '
          f'free run over {run.window_s:g} s windows: {1e3 * run.rmse_m:.3f} mm, '
          f'{100 * run.relative:.0f} % of the validation motion')
    if not fitness.fit:
        print('THE MODEL IS NOT FIT TO CONTROL: ' + '; '.join(fitness.reasons) + '.\n'
              f'  {PARAMS_FILE} was not written. Record longer or richer excitation '
              '(docs/own_gripper.md), check the settle phase and the noise level, then train '
              'again.')
        return
    if derived is None or derived.settings is None:
        why = derived.reason if derived is not None and derived.reason else \
            'no controller setting passed the closed-loop check on the model'
        print(f'{why}; {PARAMS_FILE} was not written (docs/own_gripper.md)')
        return
    d = derived.settings
    checks = ', '.join(f'{law} {100 * c.rmse_rel:.2f} %' for law, c in derived.checks.items())
    print(f'model fit to control. {out / PARAMS_FILE}: control_period {d.control_period:g} s, '
          f'meas_std {d.meas_std:.3g} m, accel_psd {d.accel_psd:.3g}, '
          f'bandwidth {d.bandwidth_hz:g} Hz '
          f'(q_pos {d.q_pos:.3g}, r {d.r:.3g}), {limit_text(derived)}, '
          + f'roll-off {roll_off_text(d.torque_lowpass_hz, d.control_period)}, integral '
          f'{d.integral_gain:.3g} / '
          f'{1e3 * d.integral_band:.2f} mm; closed loop on the model, error / travel '
          f'{1e3 * derived.facts.travel:.2f} mm: {checks}')
    for line in derived.fingers_text():
        if line:
            print(line)
    close, side = derived.facts.move()
    if derived.facts.d == 2 and derived.facts.path is None:
        print(f'the checked move: {1e3 * derived.facts.travel:.2f} mm at '
              f'{derived.facts.direction:.0f}° from +X toward +Y, close_distance '
              f'{1e3 * close:.2f} mm and side_distance {1e3 * side:.2f} mm '
              f'(the trajectory section of {PARAMS_FILE}); a longer move is not checked')
    else:
        print(f'the checked move: {derived.move_text()} (the trajectory section of '
              f'{PARAMS_FILE}); a longer move is not checked')
    if derived.facts.bounds is not None:
        print(f'the loop\'s input bounds: {derived.facts.bounds} (input_lower, input_upper)')
    paper, needs = derived.paper_law, derived.paper_law['needs_bandwidth_hz']
    print(f'the paper\'s law (sdre) on these settings holds {100 * paper["hold_offset"]:.0f} % '
          f'short of the move: its cost weighs the torque that holds the finger against its '
          f'spring; within {100 * paper["share"]:.0f} % it needs '
          + (f'a {needs:.3g} Hz loop' if needs else 'over 1 kHz')
          + ' (docs/own_gripper.md). The default law, sdre_ff, has no such offset')
