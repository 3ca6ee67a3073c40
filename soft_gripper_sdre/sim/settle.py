"""The first settle phase of an identification run, as rules on run times and torques (ROS-free;
the excitation run, :class:`~soft_gripper_sdre.sim.excitation_run.ExcitationRun`, holds one).

The phase lasts ``settle_time`` of run time and, with ``settle_time`` > 0, until ``samples`` tip
messages were heard since the start: a driver that delivers fewer in ``settle_time`` extends it,
at zero torque, and every later time is shifted by the extension. The zero-torque answers before
the first non-zero torque are counted: training estimates the noise level from them.
"""
from __future__ import annotations

import numpy as np

#: zero-torque tips a settle phase needs for training to estimate the noise level from it
MIN_SETTLE_SAMPLES = 10


class SettlePhase:
    """The first settle phase and the zero-torque answers before the first torque.

    Args:
        settle_time: its length in run time [s] (0: none).
        samples: tip messages it waits for beyond ``settle_time`` (0: ``settle_time`` alone).
    """

    def __init__(self, settle_time: float, samples: int) -> None:
        self.settle_time, self.samples = float(settle_time), int(samples)
        self.heard = 0                  # tip messages heard during the phase
        self.extended = False           # it outlasted settle_time
        self.shift: float | None = None  # its extension [s], once it is over
        self.zero_answers = 0           # answers with zero torque before the first non-zero one
        self.excited = False            # a non-zero torque went out

    def heard_tips(self) -> None:
        """One more tip message heard (counted while the phase lasts)."""
        if self.shift is None:
            self.heard += 1

    def run_time(self, t: float) -> float | None:
        """Run time ``t`` [s] less the phase's extension, or None while it is extended."""
        if self.shift is None:
            if t < self.settle_time:
                return t
            if self.settle_time > 0 and self.heard < self.samples:
                self.extended = True
                return None
            self.shift = t - self.settle_time if self.extended else 0.0
        return t - self.shift

    def answered(self, u: np.ndarray) -> bool:
        """Count an answer ``u`` (n, 2); True for the first non-zero torque (the moment to report
        how many zero answers came before it)."""
        if self.excited:
            return False
        if not np.any(u != 0.0):
            self.zero_answers += 1
            return False
        self.excited = True
        return True
