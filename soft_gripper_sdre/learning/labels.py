"""Training labels of the simulator's ``.npz`` records (``tools.learning.collect``): the KF + RTS
estimates of each signal's states and accelerations, the signals that train and the one that
validates, and the rounding-level jitter of the seed sweep's data draws.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.learning.dataset import Record

#: training signals per data variant; validation is always u4
DATA_VARIANTS = {'paper': ('u1', 'u2', 'u3'), 'identifying': ('u1', 'u2', 'u3', 'x1', 'x2')}
VALIDATION = 'u4'


def states(record: Record, jerk_psd: float) -> dict[str, np.ndarray]:
    """Translated state x = [X−X₀, Y−Y₀, Ẋ, Ẏ], input and acceleration labels from the KF + RTS."""
    return states_of([record], jerk_psd)[0]


def states_of(records: list[Record], jerk_psd: float) -> list[dict[str, np.ndarray]]:
    """:func:`states` of each of ``records``, the same bits: the records sampled alike (evenly, at
    the same length, period and noise) are smoothed as the columns of one stack
    (:func:`~soft_gripper_sdre.learning.derivatives.estimate_kinematics` smooths each column
    alone, stacked for speed: the simulator's six signals in one pass)."""
    groups: dict[tuple, list[int]] = {}
    for i, r in enumerate(records):
        # unevenly stamped records alone: estimate_kinematics refuses them, naming the reason
        key = ((r.t.size, float(np.median(np.diff(r.t))), float(r.noise_std))
               if derivatives.is_uniform(r.t) else (i,))
        groups.setdefault(key, []).append(i)
    out: list[dict[str, np.ndarray]] = [{} for _ in records]
    for members in groups.values():
        first = records[members[0]]
        tips = np.hstack([records[i].tip[:, :2] for i in members])
        pos, vel, acc = derivatives.estimate_kinematics(first.t, tips, jerk_psd, first.noise_std,
                                                        smooth=True)
        for k, i in enumerate(members):
            axes = slice(2 * k, 2 * k + 2)
            out[i] = {'x': np.hstack([pos[:, axes] - records[i].rest_tip[:2], vel[:, axes]]),
                      'u': records[i].u, 'acc': acc[:, axes], 'vel': vel[:, axes]}
    return out


def tuned_jerk_psd(record: Record) -> float:
    """The KF/RTS white-jerk intensity picked by likelihood on the first 2 s of ``record`` (the
    first training record: the labels of every model fitted to the same data). The likelihoods
    are the compiled filter's: they part from filterpy's at 1e-13 of their size, and neighbouring
    intensities a decade apart part by over 1 %, so the pick is filterpy's at a tenth of the
    time."""
    seg = slice(0, min(2000, record.t.size))
    return derivatives.tune_jerk_psd(record.t[seg], record.tip[seg, :2], record.noise_std,
                                     np.logspace(1, 7, 7), compiled=True)


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


def label_records(records: dict[str, Record], variant: str,
                  jerk_psd: float | None = None) -> LabelledData:
    """Label ``records`` (``DATA_VARIANTS[variant]`` and the validation signal) with the KF + RTS at
    ``jerk_psd`` (None: :func:`tuned_jerk_psd` on the first training record)."""
    names = list(DATA_VARIANTS[variant]) + [VALIDATION]
    first = records[names[0]]
    jerk = jerk_psd if jerk_psd is not None else tuned_jerk_psd(first)
    est = dict(zip(names, states_of([records[name] for name in names], jerk)))
    deriv_err = {}
    for name in names:
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
