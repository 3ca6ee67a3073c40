"""One answered state estimate to one torque command: the controller node's arithmetic between
its command gate and its publishers (no ROS).

The plan is sampled at the estimate's stamp by the compiled kernel
(:func:`~soft_gripper_sdre.control.compiled.plan_sample`, the same bits as
:func:`~soft_gripper_sdre.control.horizon.sample_plan`, which takes over where the kernel declines)
on the plan's arrays made contiguous once per plan. For a model learned from several fingers that
rest apart, each finger's tip and reference are moved into the model's frame
(:func:`rest_shift`). The law's compute is timed for /diagnostics, and a torque that is still
not finite (the law guarantees it is; the promise is kept here too) becomes zero.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.command_gate import Plan
from soft_gripper_sdre.control.compiled import plan_sample
from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.control.tracking import Law, LawStep


def rest_shift(model, names: tuple[str, ...]) -> np.ndarray | None:
    """(n, 2) p₀ − p₀ᶠ per finger: added to a finger's tip and reference, it puts the finger's own
    rest p₀ᶠ where the model's coordinates have theirs, p₀ (a model learned from several fingers
    that rest apart, each translated by its own rest in training); None when the model does not
    know every finger's rest, or they all rest where it does."""
    rests = model.finger_rests
    if not all(name in rests for name in names):
        return None
    shift = np.array([model.rest_tip[:2] - rests[name][:2] for name in names])
    return shift if np.any(shift != 0.0) else None


class Command(NamedTuple):
    """The torque to publish and the law's step it came from."""

    u: np.ndarray            # (n, 2) [N·m], finite
    out: LawStep
    replaced: bool           # the law's torque was not finite and ``u`` is zero


class TrackingStep:
    """The plan sampled, the fingers put in the model's frame, the law applied and timed.

    Args:
        model: the learned SDC model (its rest and the fingers' own rests).
        names: the fingers, in the order of the estimates' rows.
    """

    def __init__(self, model, names: tuple[str, ...]) -> None:
        self.n = len(names)
        self.rest_shift = rest_shift(model, names)
        self._plan: Plan | None = None      # the plan the contiguous copies below are of
        self._plan_arrays: tuple = ()
        self._compute_s: list[float] = []   # the law's compute times since the last take

    def command(self, law: Law, stamp: int, x: np.ndarray, plan: Plan) -> Command:
        """The torque of ``law`` for the estimate ``x`` (n, 4) stamped ``stamp`` [ns] tracking
        ``plan``."""
        ref_pos, ref_vel, ref_acc = self.sample(plan, stamp)
        pos = x[:, :2]
        if self.rest_shift is not None:         # each finger into the model's frame
            pos, ref_pos = pos + self.rest_shift, ref_pos + self.rest_shift
        t0 = time.perf_counter()
        out = law.compute(pos, x[:, 2:], ref_pos, ref_vel, ref_acc=ref_acc)
        self._compute_s.append(time.perf_counter() - t0)
        if np.isfinite(out.u).all():
            return Command(out.u, out, False)
        return Command(np.zeros_like(out.u), out, True)

    def sample(self, plan: Plan, stamp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The plan's position, velocity and acceleration (n, 2) at ``stamp``: :func:`sample_plan`
        compiled (the same bits), on the plan's arrays made contiguous once per plan."""
        if plan is not self._plan:
            self._plan = plan
            self._plan_arrays = (np.ascontiguousarray(plan.times, dtype=np.int64),
                                 *(np.ascontiguousarray(a, dtype=np.float64)
                                   for a in (plan.pos, plan.vel, plan.acc)))
        out = np.empty((3, self.n, 2))
        if plan_sample(*self._plan_arrays, stamp, out[0], out[1], out[2]):
            return out[0], out[1], out[2]
        return sample_plan(plan.times, plan.pos, plan.vel, plan.acc, stamp, with_acc=True)

    def take_compute_us(self) -> tuple[float, float] | None:
        """Mean and max compute time [µs] since the last call (None: no step since)."""
        if not self._compute_s:
            return None
        c = np.asarray(self._compute_s) * 1e6
        self._compute_s.clear()
        return float(c.mean()), float(c.max())
