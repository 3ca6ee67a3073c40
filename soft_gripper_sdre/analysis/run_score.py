"""The score of a deployed grasp from its bag, for fingers of any shape (d tip coordinates, m
inputs): how closely the tips followed the plan, whether the loop saturated while the plan held
at rest, and whether any command left the bounds.

The plan is the newest ``grasp_reference`` message of the bag (the trajectory node publishes the
whole plan, its points stamped from the plan's origin). Over ``plan_seconds`` from the plan's
first point, each tip message (``true_tip_positions`` when the bag has them, the driver's truth;
else ``tip_positions``, the measured tips) is compared with the plan sampled at its stamp: the
RMSE per finger [m], as a share of ``travel``. The commands (``torque_commands``, ``<finger>/ax0``
… ``ax<m−1>`` by finger) stamped within the first ``rest_seconds`` of the plan (the hold at rest)
tell the saturation at rest: for symmetric bounds the share of inputs at ±the limit, for bounds of
their own the share at a bound other than the input's rest (a vented chamber, a slack tendon is
not saturation). Every command is checked against the controller's bounds and the gripper's.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.sim.shape import InputBounds

#: the tips the score prefers, in order: the driver's truth, then the measured tips
TIPS_TOPICS = ('true_tip_positions', 'tip_positions')


class ScoreError(ValueError):
    """A bag that cannot be scored (the message names the bag and what it lacks)."""


def _ns(stamp) -> int:
    return stamp.sec * 10**9 + stamp.nanosec


def score_run(bag: Path, travel: float, bounds: InputBounds, d: int, plan_seconds: float,
              rest_seconds: float, plant_bounds: InputBounds | None = None) -> dict:
    """The score of the grasp recorded in ``bag`` (module doc).

    Args:
        bag: the rosbag2 directory with ``grasp_reference``, ``torque_commands`` and tips.
        travel: the plan's travel [m] the RMSE is a share of.
        bounds: the controller's bounds (m inputs).
        d: the tip's coordinates scored (2: x, y; 3: x, y, z).
        plan_seconds: the plan's length from its first point [s].
        rest_seconds: the hold at rest at the plan's start [s].
        plant_bounds: the gripper's bounds (None: the controller's).

    Returns:
        ``rmse_mm``, ``rmse_pct_of_travel``, ``max_mm`` (per finger), ``samples``,
        ``tips_topic``, ``saturated_at_rest`` (share), ``largest_torque_at_rest`` (the largest
        |u − rest| at rest), ``commands``, ``outside_bounds``, ``outside_plant_bounds``.

    Raises:
        ScoreError: the bag lacks the plan, commands or tips within the plan, holds a command
            of another size than the plan's fingers × the bounds' inputs, or the arguments are
            bad (named).
    """
    from soft_gripper_sdre.analysis.bag import BagError, read_bag, topic_counts
    for name, ok, what in (('travel', np.isfinite(travel) and travel > 0, 'finite and > 0 m'),
                           ('d', d in (2, 3), '2 or 3'),
                           ('plan_seconds', np.isfinite(plan_seconds) and plan_seconds > 0,
                            'finite and > 0 s'),
                           ('rest_seconds', np.isfinite(rest_seconds) and rest_seconds >= 0,
                            'finite and >= 0 s')):
        if not ok:
            raise ScoreError(f'score: {name} must be {what}')
    try:
        present = {t.lstrip("/") for t in topic_counts(bag)}
        tips_topic = next((t for t in TIPS_TOPICS if t in present), None)
        if tips_topic is None or 'grasp_reference' not in present \
                or 'torque_commands' not in present:
            raise ScoreError(f'bag {bag}: needs grasp_reference, torque_commands and '
                             f'{" or ".join(TIPS_TOPICS)}; it has {sorted(present)}')
        msgs = read_bag(bag, [tips_topic, 'grasp_reference', 'torque_commands'])
    except BagError as exc:
        raise ScoreError(str(exc)) from None
    by = {k.lstrip('/'): v for k, v in msgs.items()}
    if not by['grasp_reference']:
        raise ScoreError(f'bag {bag}: no grasp_reference message (no plan was published)')
    plan = by['grasp_reference'][-1][1]
    times = np.array([_ns(p.time_from_start) for p in plan.points]) + _ns(plan.header.stamp)
    n = len(plan.joint_names)
    pos = np.array([[[t.translation.x, t.translation.y, t.translation.z][:d]
                     for t in p.transforms] for p in plan.points])
    vel = np.array([[[v.linear.x, v.linear.y, v.linear.z][:d] for v in p.velocities]
                    for p in plan.points])
    acc = np.array([[[v.linear.x, v.linear.y, v.linear.z][:d] for v in p.accelerations]
                    for p in plan.points])
    start, stop = int(times[0]), int(times[0] + plan_seconds * 1e9)
    errs, rest_cmds, cmds = [], [], []
    for _, m in by[tips_topic]:
        t = _ns(m.header.stamp)
        if start <= t <= stop:
            ref = sample_plan(times, pos, vel, acc, t)[0]
            tip = np.array([[p.position.x, p.position.y, p.position.z][:d] for p in m.poses[:n]])
            errs.append(np.linalg.norm(tip - ref, axis=1))
    if not errs:
        raise ScoreError(f'bag {bag}: no {tips_topic} message within the plan '
                         f'({plan_seconds:g} s from its first point)')
    for _, m in by['torque_commands']:
        u = np.asarray(m.effort, dtype=float)
        if u.size != n * bounds.m:
            raise ScoreError(f'{bag}: a torque command of {u.size} efforts ({list(m.name)}) '
                             f'for {n} finger(s) of {bounds.m} input(s): another graph on this '
                             'ROS domain?')
        u = u.reshape(-1, bounds.m)                                    # by finger
        cmds.append(u)
        if start <= _ns(m.header.stamp) < start + rest_seconds * 1e9:
            rest_cmds.append(u)
    errs = np.array(errs)
    rmse = np.sqrt(np.mean(errs ** 2, axis=0))
    cmds = np.concatenate(cmds) if cmds else np.zeros((0, bounds.m))
    rest = np.concatenate(rest_cmds) if rest_cmds else np.zeros((0, bounds.m))
    limit = bounds.symmetric_limit
    if limit is not None:                              # the torque grippers: |u| at the limit
        at = np.abs(rest) >= limit * (1 - 1e-9)
    else:                                              # at a bound other than the input's rest
        tol = 1e-9 * (bounds.upper - bounds.lower)
        at = (((rest <= bounds.lower + tol) & (bounds.lower != bounds.rest))
              | ((rest >= bounds.upper - tol) & (bounds.upper != bounds.rest)))
    at_rest = float(np.mean(at)) if rest.size else 0.0
    largest = float(np.abs(rest - bounds.rest).max()) if rest.size else 0.0

    def outside(b: InputBounds) -> int:
        span = 1e-9 * (b.upper - b.lower)
        return int(np.sum(~np.isfinite(cmds) | (cmds < b.lower - span) | (cmds > b.upper + span)))

    return {'rmse_mm': (1e3 * rmse).round(4).tolist(),
            'rmse_pct_of_travel': (100 * rmse / travel).round(3).tolist(),
            'max_mm': (1e3 * errs.max(axis=0)).round(4).tolist(), 'samples': int(len(errs)),
            'tips_topic': tips_topic,
            'saturated_at_rest': at_rest, 'largest_torque_at_rest': largest,
            'commands': int(len(cmds)), 'outside_bounds': outside(bounds),
            'outside_plant_bounds': outside(plant_bounds if plant_bounds is not None else bounds)}
