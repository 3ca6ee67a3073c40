"""Figures 5–7 and tracking metrics of a recorded run.

    python -m soft_gripper_sdre.tools.judging.report BAG --out DIR [--torque-limit 0.1] [--render]

Writes DIR/fig5_positions.png and fig6_velocities.png (the reference against the true tip, from the
simulator's joint states in the bag; the measured tip where the bag has no joint_states),
fig7_torques.png (commands) and DIR/metrics.json:

* per finger: free-space tracking RMSE / max of the 2-D tip error [mm] and the RMSE as % of the
  reference's peak excursion from its first point; free space = samples where that finger's
  cube contact force (held from the last cube_contacts message) is 0 — all samples if the bag has
  no cube_contacts; plus the fraction of samples in contact; the errors are those of the measured
  tips (sensor noise included), and, with joint_states in the bag, ``true_tip`` holds the same
  figures for the true tip at the joint states' rate; ``held_mm``: the mean 2-D error where the
  reference stands still and the finger touches nothing
  (:func:`~soft_gripper_sdre.analysis.metrics.held_reference_error`);
* the cube's largest displacement from its first pose [mm];
* with ``--torque-limit``: how many torque commands reached the actuator limit (the simulator clips
  them there), per finger;
* messages per topic, and malformed messages that were skipped.

With ``--render`` it also draws the hand from the bag's joint states (:mod:`.render`): Fig. 1
``fig1_hand.png``, Fig. 4 ``fig4_snapshots.png`` and the animation ``grasp.gif``.

The run starts at the first tip sample that has a reference in force. Exit status 2 for a missing
or unusable bag.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
from typing import NamedTuple

import numpy as np

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.analysis.bag import BagError, Run, extract_run
from soft_gripper_sdre.analysis.metrics import held_reference_error, tracking_metrics
from soft_gripper_sdre.analysis.plots import plot_torques, plot_tracking

FIGURES = ('fig5_positions.png', 'fig6_velocities.png', 'fig7_torques.png')
METRICS = 'metrics.json'


def interpolate(t_src: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``values`` (T_src, …) sampled at ``t`` by linear interpolation, NaN outside ``t_src``."""
    flat = values.reshape(len(t_src), -1)
    out = np.stack([np.interp(t, t_src, flat[:, c], left=np.nan, right=np.nan)
                    for c in range(flat.shape[1])], axis=1)
    return out.reshape((len(t),) + values.shape[1:])


def hold(t_src: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``values`` at ``t`` by zero-order hold of the latest sample (the first before it starts)."""
    idx = np.clip(np.searchsorted(t_src, t, side='right') - 1, 0, len(t_src) - 1)
    return values[idx]


def _json_safe(value):
    """NaN/Inf → None and numpy scalars → Python, recursively (strict JSON)."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _start(run: Run, path) -> int:
    """Index of the first tip sample with a reference in force."""
    valid = np.all(np.isfinite(run.reference.values.reshape(len(run.reference.t), -1)), axis=1)
    if not valid.any():
        raise BagError(f'bag {path}: grasp_reference starts after the last tip_positions sample')
    return int(np.argmax(valid))


class _Span(NamedTuple):
    """The run from its start, on the tip samples' times: the measured tips and what they are
    scored against."""

    t: np.ndarray              # (T,) [s]
    pos: np.ndarray            # (T, n, 2) measured tips [m]
    ref: np.ndarray            # (T, n, 4) reference position and velocity
    vel: np.ndarray            # (T, n, 2) the estimator's tip velocity
    contact: np.ndarray        # (T, n) the finger touches the cube (all False without contacts)
    has_contacts: bool
    t_u: np.ndarray            # (U,) the torque commands within the span [s]
    u: np.ndarray              # (U, n, 2) [N·m]

    @property
    def excursion(self) -> np.ndarray:
        """(n,) the reference's peak distance from its first point [m]."""
        return np.linalg.norm(self.ref[..., :2] - self.ref[0, :, :2], axis=2).max(axis=0)


def _span(run: Run, path) -> _Span:
    """The run from its first tip sample with a reference in force (``path`` names the bag in the
    error when there is none)."""
    k0 = _start(run, path)
    t = run.tips.t[k0:]
    has_contacts = run.contacts is not None
    if has_contacts:
        contact = hold(run.contacts.t, run.contacts.values, t) > 0.0
    else:
        contact = np.zeros((len(t), run.n_fingers), dtype=bool)
    # commands outside the recorded run (e.g. a controller's zero torques, stamped with its own
    # clock, after the simulator stopped) are not part of it
    keep_u = (run.torques.t >= t[0]) & (run.torques.t <= t[-1])
    return _Span(t, run.tips.values[k0:], run.reference.values[k0:],
                 interpolate(run.estimate.t, run.estimate.values[..., 2:4], t), contact,
                 has_contacts, run.torques.t[keep_u], run.torques.values[keep_u])


def _true_tips(run: Run, t: np.ndarray):
    """(t, pos, vel) of the true tips over the run's span from its joint states, or None."""
    if run.joints is None:
        return None
    keep = (run.joints.t >= t[0]) & (run.joints.t <= t[-1])
    if keep.sum() < 2:
        return None
    from soft_gripper_sdre.analysis.ground_truth import true_tips
    pos, vel = true_tips(run.joints.values[keep])
    return run.joints.t[keep], pos, vel


def _finger_metrics(span: _Span, names: list[str]) -> dict[str, dict]:
    """Per finger: the measured tips' free-space tracking figures, the share of samples in
    contact and the held-reference error."""
    ref = span.ref
    tracking = tracking_metrics(span.pos, ref[..., :2], ~span.contact, span.excursion)
    held = held_reference_error(span.pos, ref[..., :2], ref[..., 2:4], span.contact)
    fingers = {}
    for i, name in enumerate(names):
        fingers[name] = tracking[i].as_dict()
        fingers[name]['contact_fraction'] = (float(span.contact[:, i].mean())
                                             if span.has_contacts else None)
        fingers[name]['held_mm'] = float(held[i])
    return fingers


def _true_tip_metrics(span: _Span, truth, names: list[str]) -> dict[str, dict]:
    """Per finger: the same figures on the true tips ``truth`` (t, pos, vel), with the reference
    interpolated and the contact held onto their times."""
    t_true, pos_true, _ = truth
    ref_true = interpolate(span.t, span.ref, t_true)
    contact_true = hold(span.t, span.contact, t_true)
    true_metrics = tracking_metrics(pos_true, ref_true[..., :2], ~contact_true, span.excursion)
    held_true = held_reference_error(pos_true, ref_true[..., :2], ref_true[..., 2:4],
                                     contact_true)
    return {name: _json_safe(dict(true_metrics[i].as_dict(), held_mm=float(held_true[i])))
            for i, name in enumerate(names)}


def _cube_mm(run: Run) -> float | None:
    """The cube's largest displacement from its first pose [mm], None without cube_pose."""
    if run.cube_pose is None:
        return None
    p = run.cube_pose.values[:, :3]
    return 1e3 * float(np.linalg.norm(p - p[0], axis=1).max())


def _saturation(u: np.ndarray, torque_limit: float | None, names: list[str]) -> dict | None:
    """How many commands reached ``torque_limit`` in either axis, per finger (None: no limit)."""
    if torque_limit is None:
        return None
    hit = np.abs(u) >= torque_limit * (1.0 - 1e-9)          # (T, n, 2)
    return {'limit_Nm': float(torque_limit), 'commands': int(len(u)),
            'saturated': {name: int(hit[:, i].any(axis=1).sum()) for i, name in enumerate(names)}}


def _plot_figures(out: Path, span: _Span, truth, names: list[str],
                  torque_limit: float | None) -> None:
    """Figs. 5–7: the reference against the true tip where ``truth`` is given, else against the
    measured tip and the estimator's velocity; the torque commands."""
    if truth is not None:
        label = 'true tip (simulator ground truth: forward kinematics of joint_states)'
        t_act, pos_act, vel_act = truth
    else:
        label = 'measured tip (with sensor noise)'
        t_act, pos_act, vel_act = span.t, span.pos, span.vel
    contact = span.contact if span.has_contacts else None
    plot_tracking(span.t, span.ref[..., :2], t_act, pos_act, out / FIGURES[0],
                  quantity='position', achieved_label=label, finger_names=names, contact=contact,
                  title=f'Fig. 5  Tip position: desired vs {label.split(" (")[0]} '
                        '[mm from the start]')
    vel_label = label if truth is not None else 'Kalman-filter estimate (state_estimate)'
    plot_tracking(span.t, span.ref[..., 2:4], t_act, vel_act, out / FIGURES[1],
                  quantity='velocity', achieved_label=vel_label.replace('tip', 'tip velocity', 1),
                  finger_names=names, contact=contact,
                  title=f'Fig. 6  Tip velocity: desired vs {vel_label.split(" (")[0]} velocity')
    plot_torques(span.t_u, span.u, out / FIGURES[2], names, u_max=torque_limit)


def report(bag_path: str | Path, out_dir: str | Path, torque_limit: float | None = None,
           render: bool = False) -> dict:
    """Write the figures and metrics.json of the run in ``bag_path`` to ``out_dir``; return the
    metrics.

    Args:
        bag_path: rosbag2 directory recorded from the graph.
        out_dir: created if needed.
        torque_limit: actuator limit [N·m]; if given, commands at or beyond it are counted.
        render: also draw the hand (:func:`.render.render_run`: Figs. 1 and 4, the animation)
            from the same reading of the bag, where it has joint_states; ``metrics['render']``
            says what was written and in how long.

    Raises:
        BagError: the bag is missing, unreadable or lacks a required topic.
    """
    run = extract_run(bag_path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(run.finger_names) or list(FINGER_NAMES[:run.n_fingers])
    span = _span(run, bag_path)
    metrics = _json_safe({
        'bag': str(Path(bag_path)),
        'start_s': float(span.t[0]), 'end_s': float(span.t[-1]), 'samples': int(len(span.t)),
        'free_space': 'cube contact force == 0' if span.has_contacts
                      else 'all samples (no cube_contacts)',
        'fingers': _finger_metrics(span, names),
        'cube_max_displacement_mm': _cube_mm(run),
        'torque_saturation': _saturation(span.u, torque_limit, names),
        'message_counts': run.counts,
        'skipped_messages': run.skipped,
    })
    truth = _true_tips(run, span.t)
    if truth is not None:
        for name, figures in _true_tip_metrics(span, truth, names).items():
            metrics['fingers'][name]['true_tip'] = figures
    _plot_figures(out, span, truth, names, torque_limit)
    if render and run.joints is not None:
        from soft_gripper_sdre.tools.judging.render import render_run
        metrics['render'] = render_run(bag_path, out, run=run)
    (out / METRICS).write_text(json.dumps(metrics, indent=2) + '\n', encoding='utf-8')
    return metrics


def _fmt(value: float | None, spec: str, unit: str = '') -> str:
    return 'n/a' if value is None else format(value, spec) + unit


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.judging.report',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory of a run')
    parser.add_argument('--out', required=True, type=Path, help='output directory')
    parser.add_argument('--torque-limit', type=float, default=None,
                        help='actuator limit [N·m] (the simulator\'s torque_limit) to count '
                             'saturation')
    parser.add_argument('--render', action='store_true',
                        help='also draw the hand: Fig. 1, Fig. 4 and grasp.gif '
                             '(needs joint_states)')
    args = parser.parse_args(argv)
    if args.torque_limit is not None and not args.torque_limit > 0:
        parser.error(f'--torque-limit must be > 0 N·m, got {args.torque_limit}')
    try:
        metrics = report(args.bag, args.out, args.torque_limit, args.render)
    except BagError as exc:
        print(f'{parser.prog}: error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:
        print(f'{parser.prog}: error: cannot write to {args.out}: {exc}', file=sys.stderr)
        return 2
    print(f'{metrics["samples"]} samples, t = {metrics["start_s"]:.3f} … {metrics["end_s"]:.3f} s; '
          f'free space: {metrics["free_space"]}')
    for name, m in metrics['fingers'].items():
        print(f'  {name}: RMSE {_fmt(m["rmse_mm"], ".3f", " mm")} '
              f'({_fmt(m["rmse_pct"], ".1f", " %")} of '
              f'{_fmt(m["excursion_mm"], ".1f", " mm")}), max {_fmt(m["max_mm"], ".3f", " mm")}, '
              f'contact {_fmt(m["contact_fraction"], ".0%")}')
    print(f'  cube moved at most {_fmt(metrics["cube_max_displacement_mm"], ".2f", " mm")}')
    if metrics['torque_saturation']:
        print(f'  torque commands at the limit: {metrics["torque_saturation"]["saturated"]}')
    drawn = metrics.get('render', {}).get('files', [])
    print(f'wrote {", ".join(FIGURES + tuple(drawn))} and {METRICS} to {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
