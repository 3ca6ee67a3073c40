"""One answered state estimate to one torque command: the controller node's arithmetic between
its command gate and its publishers (no ROS).

The plan is sampled at the estimate's stamp by the compiled kernel
(:func:`~soft_gripper_sdre.control.kernels.plan_sample`, the same bits as
:func:`~soft_gripper_sdre.control.horizon.sample_plan`, which takes over where the kernel declines)
on the plan's arrays made contiguous once per plan. For a model learned from several fingers that
rest apart, each finger's tip and reference are moved into the model's frame
(:func:`rest_shift`), and with ``input_gains`` each finger's command out of the model's units:
the law commands the model, whose inputs act g_f times as weakly as finger f's, so the finger
receives the law's command divided by g_f. The law's compute is timed for /diagnostics, and a
torque that is still not finite (the law guarantees it is; the promise is kept here too) becomes
each input's rest (zero for the hand's torques). With bounds of its own (one-sided inputs, say)
a command is also clipped into them, should the law ever leave them.

The finger's shape (task dimension d, inputs m) is the model's: the estimate is (n, 2d), the
plan (h, n, d), the command (n, m). The hand's planar plans are sampled by the compiled kernel,
3-D ones by :func:`~soft_gripper_sdre.control.horizon.sample_plan`.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from soft_gripper_sdre.control.command_gate import Plan
from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.control.kernels import plan_sample
from soft_gripper_sdre.control.tracking import Law, LawStep
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, InputBounds


def rest_shift(model, names: tuple[str, ...], d: int = 2) -> np.ndarray | None:
    """(n, d) p₀ − p₀ᶠ per finger: added to a finger's tip and reference, it puts the finger's own
    rest p₀ᶠ where the model's coordinates have theirs, p₀ (a model learned from several fingers
    that rest apart, each translated by its own rest in training); None when the model does not
    know every finger's rest, or they all rest where it does."""
    rests = model.finger_rests
    if not all(name in rests for name in names):
        return None
    shift = np.array([model.rest_tip[:d] - rests[name][:d] for name in names])
    return shift if np.any(shift != 0.0) else None


class Command(NamedTuple):
    """The torque to publish and the law's step it came from."""

    u: np.ndarray            # (n, m) [N·m or the inputs' SI unit], finite, within the bounds
    out: LawStep
    replaced: bool           # the law's command was not finite and ``u`` is the inputs' rest
    clipped: bool = False    # the law's command left the node's own bounds and was clipped


class TrackingStep:
    """The plan sampled, the fingers put in the model's frame, the law applied and timed.

    Args:
        model: the learned SDC model (its rest and the fingers' own rests).
        names: the fingers, in the order of the estimates' rows.
        shape: the finger's shape (the model's).
        bounds: bounds the command is clipped into besides the law's own saturation; None: the
            law's ±limit alone (the hand's loop, which the law keeps within it).
        input_gains: (n,) per finger how much more strongly its inputs act than the model's
            (None: every finger is the model's); they need ``bounds``, the actuators' own.

    Raises:
        ValueError: ``input_gains`` without ``bounds``, or not one finite gain > 0 per finger.
    """

    def __init__(self, model, names: tuple[str, ...], shape: FingerShape = HAND_SHAPE,
                 bounds: InputBounds | None = None,
                 input_gains: np.ndarray | None = None) -> None:
        self.n = len(names)
        self.gains = None
        if input_gains is not None:
            gains = np.asarray(input_gains, dtype=float).reshape(-1)
            if bounds is None or gains.shape != (self.n,) or not np.all(np.isfinite(gains)
                                                                         & (gains > 0)):
                raise ValueError(f'input_gains must be one finite gain > 0 per finger ({self.n}) '
                                 f'with the actuators\' bounds, got {input_gains!r} and bounds '
                                 f'{bounds}')
            self.gains = gains[:, None]
            # a command at the law's shared bound lands on the actuator's to rounding
            self._tol = 1e-9 * float(np.max(bounds.upper - bounds.lower))
        self.d = shape.d
        self.bounds = bounds
        self._rest_u = None if bounds is None else bounds.rest
        self._reports_unreachable = not shape.square
        self._unreachable: list[float] = []
        self.rest_shift = rest_shift(model, names, self.d)
        self._plan: Plan | None = None      # the plan the contiguous copies below are of
        self._plan_arrays: tuple = ()
        self._compute_s: list[float] = []   # the law's compute times since the last take

    def command(self, law: Law, stamp: int, x: np.ndarray, plan: Plan) -> Command:
        """The command of ``law`` for the estimate ``x`` (n, 2d) stamped ``stamp`` [ns]
        tracking ``plan``."""
        ref_pos, ref_vel, ref_acc = self.sample(plan, stamp)
        d = self.d
        pos = x[:, :d]
        if self.rest_shift is not None:         # each finger into the model's frame
            pos, ref_pos = pos + self.rest_shift, ref_pos + self.rest_shift
        t0 = time.perf_counter()
        out = law.compute(pos, x[:, d:], ref_pos, ref_vel, ref_acc=ref_acc)
        self._compute_s.append(time.perf_counter() - t0)
        if self._reports_unreachable:
            unreachable = getattr(out, 'unreachable', None)
            if unreachable is not None:
                self._unreachable.append(float(np.max(unreachable)))
        if self.bounds is None:                 # the hand's loop: the law's ±limit
            if np.isfinite(out.u).all():
                return Command(out.u, out, False)
            return Command(np.zeros_like(out.u), out, True)
        u = out.u if self.gains is None else out.u / self.gains
        replaced = not np.isfinite(u).all()
        if replaced:
            u = np.where(np.isfinite(u), u, self._rest_u)
        clipped = not self.bounds.contains(u)
        if clipped:
            # with input gains a command at the law's shared bound lands on the actuator's own
            # only to rounding: clipped, and not counted
            clipped = self.gains is None or not self.bounds.contains(u, tol=self._tol)
            u = self.bounds.clip(u)
        return Command(u, out, replaced, clipped)

    def sample(self, plan: Plan, stamp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The plan's position, velocity and acceleration (n, d) at ``stamp``: for d = 2
        :func:`sample_plan` compiled (the same bits), on the plan's arrays made contiguous once per
        plan."""
        if self.d != 2:
            return sample_plan(plan.times, plan.pos, plan.vel, plan.acc, stamp, with_acc=True)
        if plan is not self._plan:
            self._plan = plan
            self._plan_arrays = (np.ascontiguousarray(plan.times, dtype=np.int64),
                                 *(np.ascontiguousarray(a, dtype=np.float64)
                                   for a in (plan.pos, plan.vel, plan.acc)))
        out = np.empty((3, self.n, 2))
        if plan_sample(*self._plan_arrays, stamp, out[0], out[1], out[2]):
            return out[0], out[1], out[2]
        return sample_plan(plan.times, plan.pos, plan.vel, plan.acc, stamp, with_acc=True)

    def take_unreachable(self) -> float | None:
        """The largest unreachable acceleration demand [m/s²] of any finger since the last call
        (None: none reported since, or a finger whose inputs reach every direction)."""
        if not self._unreachable:
            return None
        worst = max(self._unreachable)
        self._unreachable.clear()
        return worst

    def take_compute_us(self) -> tuple[float, float] | None:
        """Mean and max compute time [µs] since the last call (None: no step since)."""
        if not self._compute_s:
            return None
        c = np.asarray(self._compute_s) * 1e6
        self._compute_s.clear()
        return float(c.mean()), float(c.max())
