"""``torque_commands`` for fingers of m inputs: the efforts named ``<finger>/ax<k>`` for k < m
(sim/shape.py's ``FingerShape.input_names``), in the input's SI unit (N·m, Pa, N); and the
``input_lower`` / ``input_upper`` parameters that bound them.

:func:`inputs_codec` is the raw-CDR codec of :mod:`soft_gripper_sdre.nodes.cdr` for (n, m)
efforts: for m = 2 it is ``cdr.torques_codec`` itself (the hand's messages, byte for byte);
for other m the same :class:`~soft_gripper_sdre.nodes.cdr.LoopCodec` with m names per finger.
A message whose names are not exactly these (unknown, missing, duplicate) or whose efforts are
not finite does not decode (:class:`~soft_gripper_sdre.nodes.conversions.MessageError`).
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.params import Param, ParameterError
from soft_gripper_sdre.nodes.topics import TORQUE_COMMANDS
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds, ShapeError

#: the value of ``input_lower`` and ``input_upper`` that means "not given" (an empty interval,
#: which no actuator has): ROS cannot type an empty list as floats
UNSET = [0.0]


def bounds_params(unset_means: str) -> tuple[Param, Param]:
    """``input_lower`` and ``input_upper``: per input k the interval of the command
    [input_lower[k], input_upper[k]] in the input's unit; both [0.0] (the default) is
    ``unset_means``."""
    what = ('per input k the {} bound of the command in its unit (N·m, Pa, N); one value per '
            f'input; input_lower and input_upper both [0.0] (the default): {unset_means}')
    return (Param('input_lower', list(UNSET), what.format('lower'), read_only=True),
            Param('input_upper', list(UNSET), what.format('upper'), read_only=True))


def given_bounds(p: dict) -> InputBounds | None:
    """The bounds ``input_lower`` / ``input_upper`` give, or None when both are unset.

    Raises:
        ParameterError: different lengths, not 1 to 4 inputs, a bound not finite, or an
            interval that is empty (the message names both parameters).
    """
    lower, upper = list(p['input_lower']), list(p['input_upper'])
    if lower == UNSET and upper == UNSET:
        return None
    try:
        return InputBounds.parse(lower, upper, len(lower), "parameters 'input_lower', "
                                 "'input_upper'")
    except ShapeError as exc:
        raise ParameterError(str(exc)) from None


def input_names(fingers: cv.Fingers, m: int) -> list[str]:
    """``<finger>/ax0`` … ``<finger>/ax<m−1>`` for each finger, in the order of u.ravel()."""
    shape = FingerShape(2, m)
    return [name for finger in cv.finger_names(fingers) for name in shape.input_names(finger)]


def inputs_to_msg(ns: int, u: np.ndarray, fingers: cv.Fingers) -> cv.JointState:
    """(n, m) inputs → JointState named <finger>/ax<k> with efforts."""
    u = np.asarray(u, dtype=float)
    msg = cv.JointState()
    cv.set_time(msg.header.stamp, ns)
    msg.name = input_names(fingers, u.shape[1])
    msg.effort = u.ravel().tolist()
    return msg


def msg_to_inputs(msg: cv.JointState, fingers: cv.Fingers, m: int) -> tuple[int, np.ndarray]:
    """JointState → (stamp ns, (n, m) inputs), ordered by name whatever the message order.

    Raises:
        conversions.MessageError: names ≠ efforts, unknown, missing or duplicate names, NaN/Inf.
    """
    names = cv.finger_names(fingers)
    if len(msg.effort) != len(msg.name):
        raise cv.MessageError(f'{TORQUE_COMMANDS}: {len(msg.name)} names but {len(msg.effort)} '
                              'efforts')
    idx = cv._order(msg.name, input_names(names, m), TORQUE_COMMANDS)
    effort = np.asarray(msg.effort, dtype=float)[idx].reshape(len(names), m)
    return cv.from_time(msg.header.stamp), cv.check_finite(effort, cv.TORQUES_WHAT)


def inputs_codec(fingers: cv.Fingers, m: int) -> cdr.LoopCodec:
    """The ``torque_commands`` codec for (n, m) efforts (module doc)."""
    if m == 2:
        return cdr.torques_codec(fingers)
    names = cv.finger_names(fingers)
    order = input_names(names, m)

    def refill(msg, ns: int, u: np.ndarray) -> None:
        cv.set_time(msg.header.stamp, ns)
        effort = list(msg.effort)
        for name, value in zip(order, u.ravel().tolist()):
            effort[list(msg.name).index(name)] = value
        msg.effort = effort

    return cdr.LoopCodec(TORQUE_COMMANDS, cv.JointState,
                         lambda ns, u: inputs_to_msg(ns, u, names),
                         lambda msg: msg_to_inputs(msg, names, m), (len(names), m),
                         cv.TORQUES_WHAT, refill=refill)
