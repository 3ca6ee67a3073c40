"""The grasp demo's arguments checked before any process starts
(:mod:`soft_gripper_sdre.tools.graph.demo`): each against the limits of the node parameter it
becomes, in the units the command line takes (mm, ms), and ``--fingers`` against the hand.
"""
from __future__ import annotations

import argparse

from soft_gripper_sdre.nodes.graph import CUBE_FINGERS, PERIOD_RANGE


def argument_problem(a: argparse.Namespace) -> str | None:
    """What is wrong with the demo's arguments, checked against the nodes' own parameter limits,
    or None. Runs before any process starts."""
    from soft_gripper_sdre.nodes.simulator import PARAMS as SIMULATOR_PARAMS
    limits = {p.name: p for p in SIMULATOR_PARAMS}
    if not (a.duration > 0 and limits['duration'].check(a.duration) is None):
        return (f'--duration must be > 0 and <= {limits["duration"].max:g} s of sim time, '
                f'got {a.duration}')
    if a.noise is not None:
        reason = limits['noise_std'].check(a.noise * 1e-3)
        if reason or not a.noise == a.noise:
            return (f'--noise is σ in mm, from 0 to {limits["noise_std"].max * 1e3:g} mm, '
                    f'got {a.noise} (e.g. --noise 0.05)')
    if a.period is not None and not PERIOD_RANGE[0] <= a.period * 1e-3 <= PERIOD_RANGE[1]:
        return (f'--period is the control period in ms, from {1e3 * PERIOD_RANGE[0]:g} to '
                f'{1e3 * PERIOD_RANGE[1]:g}, got {a.period} (e.g. --period 5)')
    if a.seed is not None and limits['seed'].check(a.seed):
        return f'--seed must be in [0, {limits["seed"].max}], got {a.seed}'
    if a.integral_gain is not None:
        from soft_gripper_sdre.nodes.controller import PARAMS as CONTROLLER_PARAMS
        gain = next(p for p in CONTROLLER_PARAMS if p.name == 'integral_gain')
        if gain.check(a.integral_gain) or not a.integral_gain == a.integral_gain:
            return (f'--integral-gain must be in [0, {gain.max:g}] 1/s³ (0 = off), '
                    f'got {a.integral_gain}')
    if a.domain_id is not None and not 0 <= a.domain_id <= 232:
        return f'--domain-id must be a ROS domain ID in [0, 232], got {a.domain_id}'
    if not a.timeout > 0:
        return f'--timeout must be > 0 s, got {a.timeout}'
    if a.realtime:
        from soft_gripper_sdre.nodes.scheduling import fifo_problem
        problem = fifo_problem(a.realtime)
        if problem:
            return f'--realtime {a.realtime}: {problem}'
    if a.pin:
        from soft_gripper_sdre.nodes.graph import pinning_problem
        problem = pinning_problem()
        if problem:
            return f'--pin: {problem}'
    if a.fingers is not None:
        problem = fingers_problem(a.fingers)
        if problem:
            return f'--fingers: {problem}'
    if a.model is not None:
        from soft_gripper_sdre.learning.model import ModelFileError, read_checkpoint
        try:
            read_checkpoint(a.model)
        except ModelFileError as exc:
            return f'--model: {exc}'
    return None


def parse_fingers(text: str) -> dict[str, int]:
    """``'left=0,right=2'`` → ``{'left': 0, 'right': 2}`` (ValueError if not of that form)."""
    out = {}
    for item in text.split(','):
        name, sep, index = item.strip().partition('=')
        if not sep or name.strip() in out:
            raise ValueError(f'{item.strip()!r}: give each finger once as NAME=HAND_FINGER')
        out[name.strip()] = int(index)
    return out


def fingers_problem(text: str) -> str | None:
    """What is wrong with a ``--fingers`` value, or None."""
    from soft_gripper_sdre.nodes.conversions import finger_names_problem
    try:
        fingers = parse_fingers(text)
    except ValueError as exc:
        return f'{text!r} is not NAME=HAND_FINGER,...: {exc}'
    problem = finger_names_problem(list(fingers))
    if problem:
        return problem
    mounted = list(fingers.values())
    if len(set(mounted)) != len(mounted) or not all(0 <= i <= 3 for i in mounted):
        return f'hand fingers must be distinct, 0 to 3, got {mounted}'
    if not set(mounted) & set(CUBE_FINGERS):
        return (f'none of the fingers is at hand finger {CUBE_FINGERS[0]} or {CUBE_FINGERS[1]}, '
                'the two that grasp the cube')
    return None

