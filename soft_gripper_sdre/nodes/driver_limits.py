"""Where a node's input limits come from, and what the driver takes against them.

The bounds parameters (:func:`given_bounds`): ``input_lower`` / ``input_upper``, one value per
input in the input's SI unit (N·m, Pa, N), read the same way by the excitation node and by
``plant_driver``.

The driver's bounds on /diagnostics: a driver reports the interval each input of each finger is
clipped to as ``bounds``, ``ax0 [lower, upper], ax1 [lower, upper], …`` per finger, the fingers
joined by ``;`` (``plant_driver``; the simulator node reports ±``torque_limit`` on the hand's two
torques the same way), and the count of the commands it clipped as ``clipped_commands``. Only
the nodes in this node's namespace count as its driver (the topics it reads and writes resolve
there). :class:`DriverLimits` reads these reports for the excitation node:

* While the node has no limit of its own (none given as a parameter), the first driver's bounds
  that read (:func:`parse_bounds`: the tightest interval of each input over the fingers) are
  handed to ``take``: the excitation's limit is the driver's.
* Once it has a limit, a driver whose bounds do not contain it (or that has another number of
  inputs) is handed to ``refuse``, with a message naming both and the parameter to change (the
  excitation stops as a fault): the driver would clip the signals into other signals than the
  ones recorded as sent, and the level search would probe amplitudes the finger never received.
  A driver wider than the limit is fine (the limit is the user's choice). The newest bounds read
  are ``driver_bounds`` in /diagnostics.
* A ``bounds`` value that does not read is ignored with one WARN per driver and value: the node
  goes on waiting, or keeps its limit.
* The driver's ``clipped_commands`` rising: a WARN with the count (at most one per
  :data:`WARN_PERIOD`), and ``driver_clipped`` in /diagnostics.

A driver that reports no bounds is not checked: the excitation's limit is then the user's to
match to it.
"""
from __future__ import annotations

import re
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rclpy.node import Node

from soft_gripper_sdre.nodes.common import Diagnostics
from soft_gripper_sdre.nodes.params import ParameterError, numbers
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS
from soft_gripper_sdre.sim.shape import InputBounds, ShapeError

#: the least time between two warnings about clipped commands [s]
WARN_PERIOD = 5.0
#: the two bounds parameters, as errors name them
BOUNDS_PARAMS = "parameters 'input_lower', 'input_upper'"
_BOUND = re.compile(r'ax(\d+) \[([^,\]]+), ([^\]]+)\]')


def given_bounds(p: dict, m: int | None = None, neither: str = '',
                 context: str = '') -> InputBounds | None:
    """The bounds ``input_lower`` / ``input_upper`` of the parameters ``p`` give: for ``m``
    inputs, or (None) for as many as the lists hold; None when both are empty.

    Args:
        p: the node's parameters.
        m: the number of inputs the lists must hold (None: any from 1 to 4, the same in both).
        neither: what the node uses when both are empty, for the error about one of them empty.
        context: appended to the parameters' names in the errors of the bounds themselves
            (e.g. " (plant 'tendon3')").

    Raises:
        ParameterError: a list that is not numbers, one list empty and the other not, not one
            value per input, or an empty interval (the message names the parameters).
    """
    lower, upper = (numbers(p[name], name) for name in ('input_lower', 'input_upper'))
    if lower is None and upper is None:
        return None
    if lower is None or upper is None:
        raise ParameterError(f'{BOUNDS_PARAMS}: give both (one value per input) or neither '
                             f'({neither})')
    if m is None:
        if len(lower) != len(upper):
            raise ParameterError(f'{BOUNDS_PARAMS}: {len(lower)} lower and {len(upper)} upper '
                                 'bound(s); give one of each per input')
        m = len(lower)
    try:
        return InputBounds.parse(lower, upper, m, BOUNDS_PARAMS + context)
    except ShapeError as exc:
        raise ParameterError(str(exc)) from None


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


def reported_bounds(text: str) -> InputBounds | None:
    """A driver's ``bounds`` value as :class:`InputBounds` (the tightest over its fingers), or
    None when it does not read as bounds a finger can have (1 to 4 inputs, finite, non-empty)."""
    got = parse_bounds(text)
    if got is None:
        return None
    try:
        return InputBounds(*got)
    except ShapeError:
        return None


def limit_parameter(bounds: InputBounds) -> str:
    """The parameter(s) that give ``bounds`` to the excitation node."""
    if bounds.m == 2 and bounds.symmetric_limit is not None:
        return "torque_limit (or input_lower / input_upper)"
    return 'input_lower / input_upper'


class DriverLimits:
    """The driver's bounds and clipped commands for a node sending inputs within ``bounds``
    (module doc), reporting on ``diag``.

    Args:
        node: the node: its namespace, its logger and the subscription to /diagnostics.
        diag: the node's diagnostics.
        bounds: the node's limit; None while it waits for a driver's (then ``take`` gets the
            first driver's that read, and :meth:`use` sets the node's).
        take: called with (the driver's name, its bounds, its text) while ``bounds`` is None.
        refuse: called with the reason once a driver's bounds do not contain ``bounds``.
    """

    def __init__(self, node: Node, diag: Diagnostics, bounds: InputBounds | None, *,
                 take: Callable[[str, InputBounds, str], None],
                 refuse: Callable[[str], None]) -> None:
        self.node, self.diag = node, diag
        self.bounds = bounds
        self.take, self.refuse = take, refuse
        self.refused = False
        #: by driver: its newest bounds text that read (the ones checked)
        self.reported: dict[str, str] = {}
        self.malformed: set[tuple[str, str]] = set()
        self.clipped: dict[str, int] = {}         # by driver: its newest count
        self._last_warn = -np.inf
        self._namespace = node.get_namespace().rstrip('/')
        self._me = node.get_fully_qualified_name()
        self._sub = node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_report,
                                             STREAM_QOS)

    def use(self, bounds: InputBounds) -> None:
        """The node's limit is ``bounds`` (taken from a driver): the other drivers are checked
        against it."""
        self.bounds = bounds

    def _ours(self, name: str) -> bool:
        """Whether the status ``name`` is another node's in this node's namespace."""
        return name != self._me and name.rsplit('/', 1)[0] == self._namespace

    def _on_report(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if not self._ours(status.name):
                continue
            values = {kv.key: kv.value for kv in status.values}
            if 'bounds' in values and not self.refused:
                self._on_bounds(status.name, values['bounds'])
            if 'clipped_commands' in values:
                self._check_clipped(status.name, values['clipped_commands'])

    def _on_bounds(self, driver: str, text: str) -> None:
        if self.reported.get(driver) == text:
            return
        theirs = reported_bounds(text)
        if theirs is None:
            if (driver, text) not in self.malformed:
                self.malformed.add((driver, text))
                self.diag.values['driver_bounds_ignored'] = f'{driver}: {text!r}'
                self.node.get_logger().warn(
                    f'the driver {driver} reports bounds {text!r}, which do not read as '
                    "'ax0 [lower, upper], ax1 [lower, upper], …' per finger joined by ';' (1 to "
                    '4 inputs, each lower < upper): ignored')
            return
        self.reported[driver] = text
        self.diag.values['driver_bounds'] = text
        if self.bounds is None:
            self.take(driver, theirs, text)
            return
        why = self._problem(driver, theirs, text)
        if why is not None:
            self.refused = True
            self.refuse(why)

    def _problem(self, driver: str, theirs: InputBounds, text: str) -> str | None:
        """Why the node's limit cannot go to ``driver``, which takes ``theirs`` (``text``); None
        when the driver takes all of it."""
        mine = self.bounds
        if theirs.m != mine.m:
            return (f'the driver {driver} takes {theirs.m} input(s) ({text}), this excitation '
                    f'sends {mine.m} ({mine}): give input_lower / input_upper for its '
                    f'{theirs.m} input(s), or leave torque_limit 0 and input_lower / input_upper '
                    "'' to take the driver's")
        tol = 1e-9 * np.maximum(1.0, mine.upper - mine.lower)
        if np.all(theirs.lower <= mine.lower + tol) and np.all(theirs.upper >= mine.upper - tol):
            return None
        return (f'the driver {driver} takes {text}, narrower than the limit given to this '
                f'excitation ({mine}, {limit_parameter(mine)}): the driver would clip the '
                'signals and the level probes, and the bag would record commands the finger '
                f'never received. Give {limit_parameter(mine)} within the driver\'s, or leave '
                "torque_limit 0 and input_lower / input_upper '' to take the driver's")

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
