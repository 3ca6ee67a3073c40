"""Declare every node parameter once: type, default, description, units, range or choices.

A node lists its parameters in a tuple of :class:`Param` and calls :func:`declare_all`. rclpy
rejects out-of-range values itself (``FloatingPointRange`` / ``IntegerRange``); choices and
cross-field checks are ours. Bad values at startup raise :class:`ParameterError`, whose message
names the parameter; ``main()`` logs it and exits non-zero. At runtime a bad value is refused with
its reason and the old value stays in force.

A whole number given for a floating-point parameter (``-p max_excursion:=0``, ``0`` in a parameters
file, or an integer in a runtime change) is taken as that float: ROS types ``0`` as an integer, and
a parameter declared with a float default would refuse it. Any other type is refused.

The node's sections of the command line's parameters files are checked before anything is
declared (:mod:`soft_gripper_sdre.nodes.params_files`): a value of the wrong type or a key the
node does not declare is refused naming the key, the node and the file, since rcl would drop the
one or ignore the other without a word.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
import math
from typing import Any, Callable, Iterable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.nodes.conversions import MAX_FINGERS, finger_names_problem
from soft_gripper_sdre.nodes.params_files import (
    ANY_TYPE,
    file_problems,
    package_parameter_names,
)

#: the ``--params-file`` files of this process's command line, in order (:func:`use_params_files`)
_PARAMS_FILES: list[str] = []


class ParameterError(ValueError):
    """A parameter value is invalid; the message names the parameter."""


@dataclass(frozen=True)
class Param:
    """One parameter: name, default (its type is the parameter's type), meaning and limits."""

    name: str
    default: Any
    description: str
    units: str = ''
    min: float | None = None
    max: float | None = None
    choices: tuple | None = None
    read_only: bool = False
    #: a further check of the value: why it is refused, or None
    rule: Callable[[Any], str | None] | None = field(default=None, compare=False)
    #: a list of numbers given in any form (:func:`numbers_param`): any type is taken at
    #: declaration and read by :func:`numbers`
    dynamic: bool = False

    def descriptor(self) -> ParameterDescriptor:
        text = self.description + (f' [{self.units}]' if self.units else '')
        if self.choices:
            text += f' (one of: {", ".join(map(str, self.choices))})'
        d = ParameterDescriptor(name=self.name, description=text, read_only=self.read_only,
                                dynamic_typing=self.dynamic)
        if self.min is not None or self.max is not None:
            lo = self.min if self.min is not None else -1e300
            hi = self.max if self.max is not None else 1e300
            if isinstance(self.default, bool):
                pass
            elif isinstance(self.default, int):
                d.integer_range = [IntegerRange(from_value=int(max(lo, -2**62)),
                                                to_value=int(min(hi, 2**62)), step=0)]
            elif isinstance(self.default, float):
                d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                             to_value=float(hi), step=0.0)]
        return d

    def check(self, value: Any) -> str | None:
        """Why ``value`` is refused, or None (ranges are also enforced by rclpy)."""
        if self.choices is not None and value not in self.choices:
            return f'{self.name} must be one of {list(self.choices)}, got {value!r}'
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if value != value:  # NaN
                return f'{self.name} must not be NaN'
            if self.min is not None and value < self.min:
                return f'{self.name} must be >= {self.min}, got {value!r}'
            if self.max is not None and value > self.max:
                return f'{self.name} must be <= {self.max}, got {value!r}'
        if self.rule is not None:
            why = self.rule(value)
            if why:
                return f'{self.name}: {why}'
        return None


def finger_names_param(description: str) -> Param:
    """``finger_names``, the same rule in every node: the fingers in message order; their number
    is the number of names (:func:`~soft_gripper_sdre.nodes.conversions.finger_names_problem`)."""
    return Param('finger_names', list(FINGER_NAMES), description + '; as many names as fingers '
                 f'(1 to {MAX_FINGERS}), each a ROS name token', rule=finger_names_problem,
                 read_only=True)


def numbers_param(name: str, description: str, units: str = '') -> Param:
    """A read-only list of numbers, empty by default: given as a YAML or ``-p`` list
    (``[0.0, 1.5]``, whole numbers too), one number (``0``) or a string (``'0, 1.5'``); read with
    :func:`numbers`."""
    return Param(name, '', description, units, read_only=True, dynamic=True)


def numbers(value: Any, name: str) -> list[float] | None:
    """The finite numbers of a :func:`numbers_param` value, or None when it is empty.

    Raises:
        ParameterError: a value that is not numbers, or one that is not finite (naming ``name``).
    """
    if isinstance(value, str):
        if not value.strip():
            return None
        try:
            values = [float(v) for v in value.replace(',', ' ').split()]
        except ValueError:
            raise ParameterError(f'parameter {name!r}: {value!r} is not a list of '
                                 'numbers') from None
    elif isinstance(value, bool):
        raise ParameterError(f'parameter {name!r}: {value!r} is not a list of numbers')
    elif isinstance(value, (int, float)):
        values = [float(value)]
    else:
        items = list(value)
        if not items:
            return None
        if any(isinstance(v, (bool, str, bytes)) for v in items):
            raise ParameterError(f'parameter {name!r}: {items!r} is not a list of numbers')
        values = [float(v) for v in items]
    if not all(math.isfinite(v) for v in values):
        raise ParameterError(f'parameter {name!r}: {value!r} holds a value that is not finite')
    return values


#: the choices of ``tips_reliability`` (:func:`tips_reliability_param`)
RELIABILITIES = ('reliable', 'best_effort')


def tips_reliability_param() -> Param:
    """``tips_reliability``, the same in every node that reads ``tip_positions``."""
    return Param('tips_reliability', 'reliable', "reliability of the tip_positions "
                 "subscription: 'reliable' (the simulator: lockstep loses no period) or "
                 "'best_effort', which also matches a driver that publishes with the sensor-data "
                 'QoS', choices=RELIABILITIES, read_only=True)


def with_reliability(qos: QoSProfile, reliability: str) -> QoSProfile:
    """A copy of ``qos`` with ``reliability`` ('reliable' or 'best_effort')."""
    out = copy.copy(qos)
    out.reliability = ReliabilityPolicy[reliability.upper()]
    return out


def _is_float(p: Param) -> bool:
    return isinstance(p.default, float)


def _as_float(param: Parameter) -> Parameter:
    """``param`` with an integer value as the same float (other values unchanged)."""
    if param.type_ is Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    return param


def use_params_files(paths: Iterable[str]) -> None:
    """Name the ``--params-file`` files of the process's command line, which :func:`declare_all`
    checks each node's sections of (set by
    :func:`soft_gripper_sdre.nodes.cli.settle_command_line`)."""
    _PARAMS_FILES[:] = [str(p) for p in paths]


def declared_types(params: Iterable[Param]) -> dict[str, Any]:
    """Each parameter's default for the parameters-file check, :data:`ANY_TYPE
    <soft_gripper_sdre.nodes.params_files.ANY_TYPE>` for a dynamically typed one."""
    return {p.name: ANY_TYPE if p.dynamic else p.default for p in params}


def check_params_files(node: Node, params: Iterable[Param],
                       paths: Iterable[str] | None = None) -> None:
    """Refuse a wrong-typed value or an unknown key in ``node``'s sections of ``paths`` (default:
    the files of :func:`use_params_files`), and warn of a wildcard section's key that no node of
    the package declares (:mod:`~soft_gripper_sdre.nodes.params_files`).

    Raises:
        ParameterError: naming the key, the node and the file.
    """
    paths = list(_PARAMS_FILES if paths is None else paths)
    if not paths:
        return
    declared = declared_types(params)
    fqn = node.get_fully_qualified_name()
    package = package_parameter_names()
    for path in paths:
        for problem in file_problems(fqn, declared, path, package):
            if problem.refuse:
                raise ParameterError(problem.message)
            node.get_logger().warning(problem.message)


def declare_all(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node`` (overrides come from --params-file / -p / parameter_overrides)
    and return their values. A whole number given for a float parameter is taken as that float,
    at start-up and in later changes; the parameters files are checked first (module doc).

    Raises:
        ParameterError: a value is out of range, of the wrong type or not an allowed choice; a
            parameters file gives the node a value of the wrong type or a key it does not declare.
    """
    params = list(params)
    check_params_files(node, params)
    floats = {p.name for p in params if _is_float(p)}
    # rclpy keeps the -p / --params-file / parameter_overrides values here until declaration, and
    # has no public way to read them
    overrides = node._parameter_overrides
    for name in floats & set(overrides):
        overrides[name] = _as_float(overrides[name])
    node.add_pre_set_parameters_callback(
        lambda changes: [_as_float(c) if c.name in floats else c for c in changes])
    values = {}
    for p in params:
        try:
            values[p.name] = node.declare_parameter(p.name, p.default, p.descriptor()).value
        except (InvalidParameterValueException, InvalidParameterTypeException,
                ParameterException) as exc:
            raise ParameterError(f'parameter {p.name!r}: {exc}') from None
        reason = p.check(values[p.name])
        if reason:
            raise ParameterError(f'parameter {p.name!r}: {reason}')
    return values


def on_runtime_change(node: Node, params: Iterable[Param],
                      validate: Callable[[dict[str, Any]], str | None] | None = None,
                      apply: Callable[[dict[str, Any]], None] | None = None) -> None:
    """Validate runtime parameter changes: per-parameter checks, then ``validate(new_values)``
    for cross-field checks; refused changes leave the old values in force. Accepted changes are
    passed to ``apply``."""
    table = {p.name: p for p in params}

    def callback(changes) -> SetParametersResult:
        new = {}
        for change in changes:
            spec = table.get(change.name)
            if spec is None:
                continue
            if spec.read_only:
                return SetParametersResult(successful=False, reason=f'{change.name} is read-only')
            reason = spec.check(change.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
            new[change.name] = change.value
        if new and validate is not None:
            reason = validate(new)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        if new and apply is not None:
            apply(new)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(callback)


def to_yaml(node_name: str, params: Iterable[Param]) -> str:
    """The ``ros__parameters`` section of ``node_name`` with every default, for config/*.yaml.

    The key ``/**/<node_name>`` matches the node under any namespace (``-r __ns:=/left_hand``).
    """
    import yaml
    body = {p.name: p.default for p in params}
    return yaml.safe_dump({params_file_key(node_name): {'ros__parameters': body}}, sort_keys=False)


def params_file_key(node_name: str) -> str:
    """The top-level key of a parameters file that applies to ``node_name`` in every namespace."""
    return f'/**/{node_name}'
