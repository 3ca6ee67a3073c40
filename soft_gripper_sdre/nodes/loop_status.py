"""What the simulator says about its loop, in its /diagnostics status and its log.

:class:`~soft_gripper_sdre.sim.lockstep.Stepping` decides when the loop steps and with what; the
node tells :class:`LoopStatus` what came of it:

* a command timeout: WARN and a throttled warning; a WARN returns to OK at the next period whose
  index is a multiple of 1000;
* lost commands: ERROR, naming the first period stepped without its command and how long each
  period now waits, with a throttled warning;
* commands back after lost ones: OK, logged with the safe periods stepped so far;
* the run's end: OK, published at once (the process exits next) and logged.
"""
from __future__ import annotations

from rclpy.node import Node

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, OK, WARN, Diagnostics, ThrottledLogger
from soft_gripper_sdre.sim.lockstep import Stepping


class LoopStatus:
    """The loop's status in ``diag`` and its messages in ``node``'s log (module doc)."""

    def __init__(self, node: Node, diag: Diagnostics, stepping: Stepping) -> None:
        self._logger = node.get_logger()
        self._log = ThrottledLogger(self._logger)
        self._diag, self._stepping = diag, stepping

    def timed_out(self, t: float, hold: bool, timeout: float) -> None:
        """The period at ``t`` [s] stepped without its command after ``timeout`` [s] of wall
        time, with the held command (``hold``) or zero."""
        self._diag.set_status(WARN, f'command timeout at t = {t:.3f} s; '
                              f'{"holding the last command" if hold else "zero torque"}')
        self._log.warn('timeout', f'no torque_commands for t = {t:.3f} s within {timeout} s; '
                       f'{"holding last" if hold else "applying zero"}')

    def lost(self, how: str) -> None:
        """Commands are lost and the periods step with zero torque (``how``: what they wait)."""
        t = self._stepping.lost_since_ns / cv.NS
        why = f'no torque_commands since t = {t:.4f} s: stepping with zero torque ({how})'
        self._diag.set_status(ERROR, why)
        self._log.warn('lost', why)

    def back(self, stamp: int) -> None:
        """A command stamped ``stamp`` [ns] ended a spell of lost commands."""
        self._diag.set_status(OK, 'torque_commands are back')
        self._logger.info(f'torque_commands are back at t = {stamp / cv.NS:.4f} s '
                          f'({self._diag.counters["safe_periods"]} safe periods so far)')

    def stepped(self, k: int) -> None:
        """The tips of period ``k`` went out."""
        if self._diag.level == WARN and k % 1000 == 0:
            self._diag.set_status(OK, 'stepping')

    def finished(self, k: int) -> None:
        """The run reached its duration after ``k`` steps."""
        self._diag.set_status(OK, f'finished {k} steps')
        self._diag.publish()
        self._logger.info(f'duration reached after {k} steps; stopping')
