"""Excitation recordings (rosbag2) → training samples of the SDC model.

A recording holds ``tip_positions`` (geometry_msgs/PoseArray, pose i = finger i's tip, position
x, y and z) and ``torque_commands`` (sensor_msgs/JointState, efforts named ``<finger>/ax<k>`` for
the m inputs k = 0 … m − 1 of each finger, in each input's SI unit) at any rates, on stamps of
their own: :func:`read_recording` reads and checks them, and refuses a bag that cannot give
training data with a :class:`BagDataError` naming the bag, the topic and the problem (missing
topics, wrong types, too few or non-finite values, stamps that do not increase, command names
that are not m contiguous inputs per finger, a run too short). The number of inputs m is what the
command's names say; the task dimension d (2: the tips' x, y; 3: x, y, z) is the caller's
(:func:`task_dimension`: 3 when a tip's z moves). :func:`label_finger` then turns one finger's
tips into the training samples of ``tools.learning.train``:

* tip stamps that are evenly spaced (a lockstep simulator) are used as they are, through the
  same KF + RTS as the ``.npz`` path
  (:func:`~soft_gripper_sdre.learning.derivatives.estimate_kinematics`);
  jittery or gappy ones go through a filter with a step per interval, evaluated on a uniform grid
  at the median tip period
  (:func:`~soft_gripper_sdre.learning.derivatives.estimate_kinematics_irregular`);
* both run compiled (:mod:`~soft_gripper_sdre.learning.compiled_labels`: filterpy's estimates
  to rounding), and so does the likelihood that tunes the jerk intensity;
* a gap longer than ``gap_periods`` median tip periods splits the tips into separate stretches;
* the command is held from its stamp to the next one (zero-order hold) onto each sample time;
  samples before the first command, from the last one on (how long a driver held it is not
  known), or holding a command older than ``gap_periods`` command periods are left out;
* the rest pose and the measurement noise come from the leading stretch of zero command (the
  excitation node's settle phase): the mean tip, and σ from successive differences of its d
  coordinates. The state is x = [p − p₀, ṗ] (2d) with p₀ that rest, so f(0) = 0 for every
  finger, one-sided inputs (a chamber, a tendon, whose data lie about a mid level) included.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.analysis.bag import (
    NS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
    BagError,
    read_bag,
    topic_counts,
)
from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.sim.settle import MIN_SETTLE_SAMPLES  # the excitation node's too
from soft_gripper_sdre.sim.shape import MAX_INPUTS, InputBounds

TIPS_TYPE = 'geometry_msgs/msg/PoseArray'
TORQUES_TYPE = 'sensor_msgs/msg/JointState'
#: a recording must hold at least this much commanded time with tips [s] and this many tips
DEFAULT_MIN_DURATION = 1.0
MIN_SAMPLES = 20
#: a tip gap of more than this many median periods splits a recording; a command older than this
#: many command periods is not held
DEFAULT_GAP_PERIODS = 10.0


class BagDataError(BagError):
    """A recording cannot give training data; the message names the bag, topic and problem."""


@dataclass(frozen=True)
class Recording:
    """The tips and commands of one bag, checked (:func:`read_recording`); stamps in ns."""

    path: Path
    tips_topic: str
    torques_topic: str
    tip_ns: np.ndarray           # (T,) int64, strictly increasing
    tips: np.ndarray             # (T, n, 3) [m]
    cmd_ns: np.ndarray           # (C,) int64, strictly increasing
    torques: np.ndarray          # (C, n, m) each input's SI unit (N·m, N, Pa)
    finger_names: tuple[str, ...] = ()   # as the torque names give them, in tip order
    joint_names: tuple[str, ...] = ()    # the command's names in finger, then input order

    @property
    def n_fingers(self) -> int:
        return self.tips.shape[1]

    @property
    def n_inputs(self) -> int:
        """m: the inputs of each finger, as the command's names ``<finger>/ax<k>`` give them."""
        return self.torques.shape[2]

    def z_moves(self) -> bool:
        """Some finger's tip z is not one value throughout (a planar driver publishes z = 0)."""
        z = self.tips[:, :, 2]
        return bool(np.any(z != z[:1]))

    def describe(self) -> dict:
        """Provenance: topics, counts, median rates, jitter, gaps and spans (for the checkpoint)."""
        def stream(stamps: np.ndarray, topic: str, msg_type: str) -> dict:
            d = np.diff(stamps) / NS
            period = float(np.median(d))
            return {'topic': topic, 'type': msg_type, 'messages': int(stamps.size),
                    'rate_hz': round(1.0 / period, 3),
                    'period_jitter': round(float(np.std(d) / period), 4),
                    'gaps': int(np.count_nonzero(d > 1.5 * period)),
                    'first_s': stamps[0] / NS,
                    'duration_s': round((stamps[-1] - stamps[0]) / NS, 6)}
        return {'path': str(self.path.resolve()), 'n_fingers': self.n_fingers,
                'n_inputs': self.n_inputs,
                'tips': stream(self.tip_ns, self.tips_topic, TIPS_TYPE),
                'torques': stream(self.cmd_ns, self.torques_topic, TORQUES_TYPE)}


@dataclass
class FingerSamples:
    """One finger's training samples from one recording: states, inputs and labels (SI), for a
    task dimension d and m inputs."""

    name: str
    t: np.ndarray                # (N,) s from the first tip of the recording
    x: np.ndarray                # (N, 2d) [p − p₀, ṗ]: the hand's [X − X₀, Y − Y₀, Ẋ, Ẏ]
    u: np.ndarray                # (N, m) held command
    acc: np.ndarray              # (N, d) KF + RTS acceleration labels
    info: dict = field(default_factory=dict)


# -- reading and checking --------------------------------------------------------------------

def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * NS + int(msg.header.stamp.nanosec)


def _check_type(path: Path, topic: str, messages: list, expected: str) -> None:
    found = getattr(type(messages[0][1]), '__msgtype__', type(messages[0][1]).__name__)
    if found != expected:
        raise BagDataError(f'bag {path}: topic {topic} has type {found}; expected {expected}')


def _check_stamps(path: Path, topic: str, stamps: np.ndarray) -> None:
    d = np.diff(stamps)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0]) + 1
        raise BagDataError(f'bag {path}: {topic} stamps do not increase: message {i} is stamped '
                           f'{stamps[i] / NS:.6f} s after one stamped {stamps[i - 1] / NS:.6f} s '
                           '(reordered or duplicated messages)')


def _check_finite(path: Path, topic: str, stamps: np.ndarray, values: np.ndarray) -> None:
    bad = ~np.all(np.isfinite(values.reshape(len(values), -1)), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise BagDataError(f'bag {path}: {topic} holds NaN or Inf in {int(bad.sum())} message(s), '
                           f'the first stamped {stamps[i] / NS:.6f} s')


def _tips(path: Path, topic: str, messages: list) -> tuple[np.ndarray, np.ndarray]:
    n = len(messages[0][1].poses)
    if not 1 <= n <= len(FINGER_NAMES):
        raise BagDataError(f'bag {path}: {topic} messages hold {n} poses; '
                           f'expected 1 to {len(FINGER_NAMES)} (one per finger)')
    stamps, values = [], []
    for i, (_, msg) in enumerate(messages):
        if len(msg.poses) != n:
            raise BagDataError(f'bag {path}: {topic} message {i} holds {len(msg.poses)} poses, the '
                               f'first held {n}')
        stamps.append(_stamp(msg))
        values.append([(p.position.x, p.position.y, p.position.z) for p in msg.poses])
    return np.asarray(stamps, dtype=np.int64), np.asarray(values, dtype=float)


def torque_joint_order(names: list[str]) -> list[str]:
    """The joints of a torque message in finger order: ``<finger>/ax0`` … ``<finger>/ax<m−1>``
    for each finger in the order its names first appear (the order of the finger names the graph
    was given, as pose i of the tips is finger i); [] when the names are not of that form (every
    finger the same number m of inputs, 1 to 4, numbered contiguously from 0)."""
    fingers = list(dict.fromkeys(name.rsplit('/', 1)[0] for name in names))
    m = len(names) // len(fingers) if fingers else 0
    if not 1 <= m <= MAX_INPUTS:
        return []
    expected = [f'{finger}/ax{a}' for finger in fingers for a in range(m)]
    return expected if sorted(names) == sorted(expected) else []


def _torques(path: Path, topic: str, messages: list, n: int) -> tuple[np.ndarray, np.ndarray]:
    first = list(messages[0][1].name)
    expected = torque_joint_order(first)
    named = len(dict.fromkeys(name.rsplit('/', 1)[0] for name in expected))
    if not expected or named != n:
        raise BagDataError(f'bag {path}: {topic} message 0 names {first[:12]}; expected '
                           f"'<finger>/ax0' … '<finger>/ax<m-1>' for each of the {n} finger(s) in "
                           f'tip_positions, the same m (1 to {MAX_INPUTS}) for every finger and '
                           f'k numbered from 0 without a gap (e.g. {FINGER_NAMES[0]}/ax0)')
    m = len(expected) // n
    stamps, values = [], []
    for i, (_, msg) in enumerate(messages):
        names = list(msg.name)
        if sorted(names) != sorted(expected) or len(msg.effort) != len(names):
            raise BagDataError(f'bag {path}: {topic} message {i} names {names[:12]} with '
                               f'{len(msg.effort)} efforts; expected the {len(expected)} joints '
                               f'{expected} of the {n} finger(s) in tip_positions, '
                               'each with an effort')
        effort = np.asarray(msg.effort, dtype=float)
        stamps.append(_stamp(msg))
        values.append(effort[[names.index(name) for name in expected]].reshape(n, m))
    return np.asarray(stamps, dtype=np.int64), np.asarray(values, dtype=float)


def read_recording(path: str | Path, tips_topic: str = TIP_POSITIONS,
                   torques_topic: str = TORQUE_COMMANDS,
                   min_duration: float = DEFAULT_MIN_DURATION) -> Recording:
    """Read and check the tips and commands of the bag ``path`` (topic names with or without the
    leading '/'; a namespaced recording is found by the last name component).

    Raises:
        BagDataError: the bag is missing or unreadable, lacks a topic, has a topic of another type,
            too few messages, non-finite values, stamps that do not strictly increase, torques
            that do not name the fingers of the tips, or less than ``min_duration`` seconds of
            tips while commands were given.
    """
    path = Path(path)
    try:
        counts = topic_counts(path)
        messages = read_bag(path, [tips_topic, torques_topic])
    except BagDataError:
        raise
    except BagError as exc:
        raise BagDataError(str(exc)) from None
    if len(messages) != 2:
        raise BagDataError(f'bag {path}: {tips_topic!r} and {torques_topic!r} name the same topic')
    (tips_name, tip_msgs), (torques_name, cmd_msgs) = messages.items()
    for topic, msgs, expected in ((tips_name, tip_msgs, TIPS_TYPE),
                                  (torques_name, cmd_msgs, TORQUES_TYPE)):
        if msgs:
            _check_type(path, topic, msgs, expected)
        if len(msgs) < MIN_SAMPLES:
            raise BagDataError(f'bag {path}: topic {topic} holds {len(msgs)} message(s); at least '
                               f'{MIN_SAMPLES} needed (messages per topic: {counts})')
    tip_ns, tips = _tips(path, tips_name, tip_msgs)
    cmd_ns, torques = _torques(path, torques_name, cmd_msgs, tips.shape[1])
    for topic, stamps, values in ((tips_name, tip_ns, tips), (torques_name, cmd_ns, torques)):
        _check_stamps(path, topic, stamps)
        _check_finite(path, topic, stamps, values)
    inside = (tip_ns >= cmd_ns[0]) & (tip_ns <= cmd_ns[-1])
    span = (tip_ns[inside][-1] - tip_ns[inside][0]) / NS if inside.sum() > 1 else 0.0
    if inside.sum() < MIN_SAMPLES or span < min_duration:
        raise BagDataError(f'bag {path}: too short: {int(inside.sum())} tips over {span:.3f} s '
                           f'while commands were given ({cmd_ns[0] / NS:.3f} to '
                           f'{cmd_ns[-1] / NS:.3f} s); at '
                           f'least {MIN_SAMPLES} tips over {min_duration:g} s needed')
    joints = torque_joint_order(list(cmd_msgs[0][1].name))
    names = tuple(j.rsplit('/', 1)[0] for j in joints[::torques.shape[2]])
    return Recording(path, tips_name, torques_name, tip_ns, tips, cmd_ns, torques, names,
                     tuple(joints))


def task_dimension(recordings: list[Recording], requested: str | int = 'auto') -> int:
    """The task dimension d of training on ``recordings``: ``requested`` 2 or 3 as given, or
    'auto': 3 when some tip's z moves in some recording (:meth:`Recording.z_moves`), else 2.

    Raises:
        BagDataError: 3 requested while no tip's z moves in any recording (naming them), or a
            value other than 'auto', 2 or 3.
    """
    moves = [rec for rec in recordings if rec.z_moves()]
    if requested == 'auto':
        return 3 if moves else 2
    if requested not in (2, 3, '2', '3'):
        raise BagDataError(f'task dimension must be auto, 2 or 3, got {requested!r}')
    d = int(requested)
    if d == 3 and not moves:
        raise BagDataError('task dimension 3, but no tip\'s z moves in '
                           + ', '.join(str(rec.path) for rec in recordings)
                           + ' (planar tips: give 2 or auto)')
    return d


def recorded_bounds(recordings: list[Recording]) -> InputBounds:
    """Per input, the range [min, max] the recorded commands spanned over every finger of every
    recording, widened to hold 0: the model's rest is the finger settled at zero input (the
    settle phase), so 0 is an input the actuator delivers; a one-sided input's range is
    [0, max] or [min, 0].

    Raises:
        BagDataError: an input that was 0 in every command (naming it and the recordings).
    """
    u = np.concatenate([rec.torques.reshape(-1, rec.n_inputs) for rec in recordings])
    lower, upper = np.minimum(u.min(axis=0), 0.0), np.maximum(u.max(axis=0), 0.0)
    for k in range(u.shape[1]):
        if not lower[k] < upper[k]:
            raise BagDataError(f'input ax{k} was 0 in every command of '
                               + ', '.join(str(rec.path) for rec in recordings)
                               + ': nothing to learn its effect from, nor its bounds (give '
                               '--input-lower/--input-upper to train regardless)')
    return InputBounds(lower, upper)


def check_within(recordings: list[Recording], bounds: InputBounds, what: str) -> None:
    """Every recorded command lies within ``bounds``.

    Raises:
        BagDataError: naming ``what`` (the bounds' source), the recording, the input and the
            command outside.
    """
    for rec in recordings:
        u = rec.torques.reshape(-1, rec.n_inputs)
        span = bounds.upper - bounds.lower
        out = (u < bounds.lower - 1e-9 * span) | (u > bounds.upper + 1e-9 * span)
        if out.any():
            k = int(np.flatnonzero(out.any(axis=0))[0])
            worst = u[out[:, k], k]
            raise BagDataError(f'{what}: bag {rec.path} commands input ax{k} '
                               f'{worst.min():g} … {worst.max():g}, outside '
                               f'[{bounds.lower[k]:g}, {bounds.upper[k]:g}]')


# -- from a recording to samples --------------------------------------------------------------

def hold_commands(cmd_ns: np.ndarray, values: np.ndarray,
                  t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order hold: the command in force at each time ``t_ns`` (the last one stamped at or
    before it) and its age [ns]; NaN values and age −1 before the first command."""
    which = np.searchsorted(cmd_ns, t_ns, side='right') - 1
    held = np.full((len(t_ns),) + values.shape[1:], np.nan)
    age = np.full(len(t_ns), -1, dtype=np.int64)
    ok = which >= 0
    held[ok] = values[which[ok]]
    age[ok] = t_ns[ok] - cmd_ns[which[ok]]
    return held, age


def excited_fingers(rec: Recording) -> list[int]:
    """The fingers that received a non-zero torque."""
    return [i for i in range(rec.n_fingers) if np.any(rec.torques[:, i] != 0.0)]


def first_torque_ns(rec: Recording, finger: int) -> int | None:
    """The stamp of ``finger``'s first non-zero torque (the end of its settle phase), or None."""
    nonzero = np.flatnonzero(np.any(rec.torques[:, finger] != 0.0, axis=1))
    return int(rec.cmd_ns[nonzero[0]]) if nonzero.size else None


def settle_estimates(rec: Recording, finger: int,
                     dims: int = 2) -> tuple[np.ndarray, float | None, int]:
    """(rest tip (3,), measurement σ [m] or None, settle samples) of ``finger`` from the tips
    stamped from the first command until its first non-zero torque (the first tip at or after
    the first command when there are none); σ, the mean over the first ``dims`` coordinates,
    needs :data:`MIN_SETTLE_SAMPLES` of them."""
    onset = first_torque_ns(rec, finger)
    end = onset if onset is not None else rec.cmd_ns[-1] + 1
    settle = (rec.tip_ns >= rec.cmd_ns[0]) & (rec.tip_ns < end)
    tips = rec.tips[settle, finger]
    if not len(tips):
        first = int(np.searchsorted(rec.tip_ns, rec.cmd_ns[0]))
        return rec.tips[first, finger].copy(), None, 0
    sigma = None
    if len(tips) >= MIN_SETTLE_SAMPLES:
        sigma = float(np.mean(np.std(np.diff(tips[:, :dims], axis=0), axis=0)) / np.sqrt(2.0))
    return tips.mean(axis=0), sigma, len(tips)


def settle_noise(rec: Recording, finger: int, dims: int = 2) -> tuple[np.ndarray, float, int]:
    """(rest tip (3,), measurement σ [m], settle samples) of ``finger``, as
    :func:`settle_estimates`, for training that takes the noise level from the bag.

    Raises:
        BagDataError: fewer than :data:`MIN_SETTLE_SAMPLES` tips of the settle phase (the tips
            stamped from the first command until the finger's first non-zero torque), naming the
            bag and the finger and saying what to do.
    """
    rest, sigma, n = settle_estimates(rec, finger, dims)
    if sigma is None:
        name = rec.finger_names[finger] if finger < len(rec.finger_names) else f'finger {finger}'
        raise BagDataError(
            f'bag {rec.path}: {name}: no settle phase of zero torque before the first non-zero '
            f'torque ({n} tip(s) from the first command on, {MIN_SETTLE_SAMPLES} needed to '
            "estimate the noise level): record with the excitation node's settle_time > 0, or "
            'give --meas-std')
    return rest, sigma, n


def tip_stretches(rec: Recording, gap_periods: float = DEFAULT_GAP_PERIODS) -> list[slice]:
    """Index ranges of the tips without a gap longer than ``gap_periods`` median periods, each
    of at least :data:`MIN_SAMPLES` tips."""
    d = np.diff(rec.tip_ns)
    cuts = np.flatnonzero(d > gap_periods * np.median(d)) + 1
    edges = [0, *cuts.tolist(), len(rec.tip_ns)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b - a >= MIN_SAMPLES]


def label_finger(rec: Recording, finger: int, jerk_psd: float, meas_std: float,
                 rest_tip: np.ndarray, gap_periods: float = DEFAULT_GAP_PERIODS,
                 dims: int = 2) -> list[FingerSamples]:
    """Training samples of ``finger`` (module doc) for the task dimension ``dims`` (the tips'
    first d coordinates): one :class:`FingerSamples` per stretch of tips."""
    cmd_period = float(np.median(np.diff(rec.cmd_ns)))
    tip_period = float(np.median(np.diff(rec.tip_ns)))
    out = []
    for k, stretch in enumerate(tip_stretches(rec, gap_periods)):
        t_ns = rec.tip_ns[stretch] - rec.tip_ns[0]
        t = t_ns / NS
        xy = rec.tips[stretch, finger, :dims]
        if derivatives.is_uniform(t):
            grid_ns = t_ns
            pos, vel, acc = derivatives.estimate_kinematics(t, xy, jerk_psd, meas_std, smooth=True,
                                                            compiled=True)
            resampled = False
        else:
            grid_ns = (t_ns[0] + np.arange(int((t_ns[-1] - t_ns[0]) // tip_period) + 1)
                       * int(round(tip_period)))
            pos, vel, acc = derivatives.estimate_kinematics_irregular(t, xy, grid_ns / NS,
                                                                      jerk_psd, meas_std,
                                                                      compiled=True)
            resampled = True
        u, age = hold_commands(rec.cmd_ns - rec.tip_ns[0], rec.torques[:, finger], grid_ns)
        # how long the last command was held is unknown (the driver may hold or drop it)
        keep = ((age >= 0) & (age <= gap_periods * cmd_period)
                & (grid_ns < rec.cmd_ns[-1] - rec.tip_ns[0]))
        if keep.sum() < MIN_SAMPLES:
            continue
        x = np.hstack([pos - rest_tip[:dims], vel])
        out.append(FingerSamples(
            f'{rec.path.name}/{rec.finger_names[finger]}#{k}', grid_ns[keep] / NS, x[keep], u[keep],
            acc[keep],
            {'resampled': resampled, 'samples': int(keep.sum()), 'left_out': int((~keep).sum()),
             'span_s': [float(grid_ns[keep][0] / NS), float(grid_ns[keep][-1] / NS)]}))
    return out
