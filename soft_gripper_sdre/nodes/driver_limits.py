"""What the excitation sends against what the driver takes: a driver that reports its bounds on
/diagnostics (``plant_driver``: ``bounds``, ``ax0 [lower, upper], …`` per finger joined by ``;``,
and the count ``clipped_commands``) is compared with the excitation's own limits.

* The driver's bounds narrower than the excitation's (``torque_limit`` or ``input_lower`` /
  ``input_upper``): one WARN naming both and the parameters to give, and ``driver_bounds`` in
  /diagnostics. The driver would clip the signals into other signals than the ones recorded as
  sent, and the level search would probe amplitudes the finger never received.
* The driver's ``clipped_commands`` rising: a WARN with the count (at most one per
  :data:`WARN_PERIOD`), and ``driver_clipped`` in /diagnostics.

A driver that reports neither is not checked (the excitation's limit is then the user's to match
to it).
"""
from __future__ import annotations

import re
import time

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rclpy.node import Node

from soft_gripper_sdre.nodes.common import Diagnostics
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

#: the least time between two warnings about clipped commands [s]
WARN_PERIOD = 5.0
_BOUND = re.compile(r'ax(\d+) \[([^,\]]+), ([^\]]+)\]')


def parse_bounds(text: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The tightest (lower, upper) (m,) over the fingers of a driver's ``bounds`` value, or None
    when it does not read as one."""
    lowers, uppers = [], []
    for finger in text.split(';'):
        found = _BOUND.findall(finger)
        if not found or [int(k) for k, _, _ in found] != list(range(len(found))):
            return None
        try:
            lowers.append([float(lo) for _, lo, _ in found])
            uppers.append([float(hi) for _, _, hi in found])
        except ValueError:
            return None
    if len({len(lo) for lo in lowers}) != 1:
        return None
    return np.max(lowers, axis=0), np.min(uppers, axis=0)


class DriverLimits:
    """The checks of the module doc for a node sending inputs within (``lower``, ``upper``)
    (m,), reporting on ``diag``."""

    def __init__(self, node: Node, lower: np.ndarray, upper: np.ndarray,
                 diag: Diagnostics) -> None:
        self.node, self.diag = node, diag
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.warned_bounds = False
        self.clipped: dict[str, int] = {}         # by driver: its newest count
        self._last_warn = -np.inf
        self._sub = node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_report,
                                             STREAM_QOS)

    def _on_report(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'bounds' in values and not self.warned_bounds:
                self._check_bounds(status.name, values['bounds'])
            if 'clipped_commands' in values:
                self._check_clipped(status.name, values['clipped_commands'])

    def _check_bounds(self, driver: str, text: str) -> None:
        got = parse_bounds(text)
        if got is None or got[0].shape != self.lower.shape:
            return
        lower, upper = got
        tol = 1e-9 * np.maximum(1.0, np.abs(self.upper - self.lower))
        if np.all(lower <= self.lower + tol) and np.all(upper >= self.upper - tol):
            return
        self.warned_bounds = True
        self.diag.values['driver_bounds'] = text
        mine = ', '.join(f'ax{k} [{lo:g}, {hi:g}]' for k, (lo, hi)
                         in enumerate(zip(self.lower, self.upper)))
        self.node.get_logger().warn(
            f'the driver {driver} takes {text}, narrower than what this excitation sends '
            f'({mine}): it will clip the signals and the level probes. Give the driver\'s limit '
            '(torque_limit for ± torques, input_lower/input_upper otherwise)')

    def _check_clipped(self, driver: str, value: str) -> None:
        try:
            count = int(float(value))
        except ValueError:
            return
        before = self.clipped.get(driver)
        self.clipped[driver] = count
        if before is None or count <= before:
            return
        self.diag.values['driver_clipped'] = str(count)
        now = time.monotonic()
        if now - self._last_warn >= WARN_PERIOD:
            self._last_warn = now
            self.node.get_logger().warn(
                f'the driver {driver} has clipped {count} command(s) of this run: the finger '
                'receives other inputs than the ones recorded (give the driver\'s limit)')
