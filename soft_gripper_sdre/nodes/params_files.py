"""Check a node's sections of its ``--params-file`` files against the parameters it declares.

rcl merges the files of a command line into one value per parameter. When two files give one
parameter values of different types (the shipped ``q_pos: 1000000.0``, then a user's
``q_pos: abc``), the merged value keeps both and rclpy takes the first type it looks at: the
double wins and the user's string is dropped without a word. So each node reads its own sections
of every file itself, before it declares anything (:func:`file_problems`, called by
:func:`soft_gripper_sdre.nodes.params.declare_all`), with rcl's own reading of each scalar
(:func:`rcl_value`: ``2e6`` is a double there, ``'2e6'`` a string, ``010`` the integer 8):

* a value that cannot be taken as the parameter's type (a string for a float, a float for an
  integer, a list of integers for a list of floats) is refused naming the parameter, the node,
  the file and its section, wherever it stands in the order of files;
* a key of a section that names the node (``/**/controller``, ``/controller``,
  ``/left_hand/controller``) that the node does not declare is refused the same way: rcl would
  hand it to the node, which would ignore it;
* a key of a wildcard section (``/**``, ``/*/*``) applies to every node, so one file may hold the
  whole graph's settings: a key that another node of the package declares is taken as meant for
  that node; one that no node of the package declares (the shipped ``config/*.yaml`` list them
  all) is warned about, naming it, since the file may also serve nodes of other packages.

ROS's own parameters (``use_sim_time``, ``qos_overrides.…``) are always accepted. A section
applies to a node as rcl decides it: the key's tokens against the node's fully qualified name,
``*`` one token, ``**`` any number of them, a key without a leading ``/`` taken from the root.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
import re
from typing import Any, Iterable

import yaml

#: parameters every rclpy node has besides its own, and prefixes of those it may have
ROS_PARAMETERS = ('use_sim_time', 'start_type_description_service')
ROS_PARAMETER_PREFIXES = ('qos_overrides.',)

#: rcl's booleans (rcl_yaml_param_parser, unquoted scalars only)
_TRUE = {'Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on', 'On', 'ON'}
_FALSE = {'N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off', 'Off', 'OFF'}
#: C strtol with base 0: decimal, 0x hex, leading-0 octal
_INT = re.compile(r'\s*([+-]?)(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
#: C strtod: decimal with an optional exponent, inf, infinity, nan
_FLOAT = re.compile(r'\s*[+-]?(([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?|inf(inity)?|nan)',
                    re.IGNORECASE)
#: YAML's special floats, which rcl reads too
_SPECIAL = {'.nan': math.nan, '.NaN': math.nan, '.NAN': math.nan, '.inf': math.inf,
            '.Inf': math.inf, '.INF': math.inf, '+.inf': math.inf, '+.Inf': math.inf,
            '+.INF': math.inf, '-.inf': -math.inf, '-.Inf': -math.inf, '-.INF': -math.inf}


#: the tag of a scalar without an explicit one (:class:`_Loader`)
_PLAIN = 'rcl:plain'


class _Loader(yaml.SafeLoader):
    """Composes a file keeping what rcl reads: a scalar without an explicit tag gets the tag
    ``_PLAIN`` instead of the one YAML 1.1 would resolve (``2e6`` a string there)."""

    def resolve(self, kind, value, implicit):
        if kind is yaml.ScalarNode:
            return _PLAIN
        return super().resolve(kind, value, implicit)


@dataclass(frozen=True)
class Problem:
    """One finding about a parameters file: ``refuse`` ends the node's start, else a warning."""

    message: str
    refuse: bool


def compose(text: str) -> yaml.Node:
    """The node tree of a parameters file's text, for :func:`rcl_value` (scalars keep an explicit
    tag only)."""
    return yaml.compose(text, Loader=_Loader)


def rcl_value(node: yaml.Node) -> Any:
    """The value rcl reads from a scalar or sequence node of :func:`compose`: bool, int, float,
    str or a list of one of them (a mixed list raises ValueError, as rcl refuses it)."""
    if isinstance(node, yaml.SequenceNode):
        items = [rcl_value(item) for item in node.value]
        if len({type(v) for v in items}) > 1:
            raise ValueError('a list of mixed types')
        return items
    if not isinstance(node, yaml.ScalarNode):
        raise ValueError('not a value')
    text = node.value
    if node.style in ("'", '"') or node.tag == 'tag:yaml.org,2002:str':
        return text
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    m = _INT.fullmatch(text)
    if m:
        sign, digits = m.groups()
        octal = len(digits) > 1 and digits[1] not in 'xX'
        return int(sign + digits, 8 if octal else 0)
    if text in _SPECIAL:
        return _SPECIAL[text]
    if _FLOAT.fullmatch(text):
        return float(text)
    return text


def section_applies(key: str, node_fqn: str) -> bool:
    """Whether the section ``key`` of a parameters file applies to the node ``node_fqn`` (rcl's
    rule: ``*`` one name token, ``**`` any number, a key without a leading ``/`` from the
    root)."""
    tokens = key.strip('/').split('/')
    pattern = ''
    for token in tokens:
        if token == '**':
            pattern += '(/[^/]+)*'
        else:
            pattern += '/' + re.escape(token).replace(r'\*', '[^/]*')
    return re.fullmatch(pattern, node_fqn) is not None


def names_the_node(key: str) -> bool:
    """Whether the section ``key`` names one node (its last token has no wildcard)."""
    return '*' not in key.strip('/').split('/')[-1]


def _flatten(mapping: yaml.MappingNode, prefix: str = '') -> Iterable[tuple[str, yaml.Node]]:
    """(dotted parameter name, value node) of a ``ros__parameters`` mapping, as rcl names nested
    keys."""
    for key, value in mapping.value:
        name = prefix + str(key.value)
        if isinstance(value, yaml.MappingNode):
            yield from _flatten(value, name + '.')
        else:
            yield name, value


#: the default :func:`type_problem` is given for a dynamically typed parameter: any value fits
ANY_TYPE = object()


def type_problem(value: Any, default: Any) -> str | None:
    """Why ``value`` (rcl's reading) cannot be a parameter whose default is ``default``, or
    None. A whole number is a float (nodes/params.py), a list must hold the default's element
    type (an empty default list takes strings); every value fits :data:`ANY_TYPE`."""
    if default is ANY_TYPE:
        return None
    def fits(v, d) -> bool:
        if isinstance(d, bool):
            return isinstance(v, bool)
        if isinstance(d, int):
            return isinstance(v, int) and not isinstance(v, bool)
        if isinstance(d, float):
            return isinstance(v, (int, float)) and not isinstance(v, bool)
        if isinstance(d, str):
            return isinstance(v, str)
        return False

    if isinstance(default, (list, tuple)):
        if not isinstance(value, list):
            return f'{value!r} is not a list'
        element = default[0] if default else ''
        if isinstance(element, float):
            ok = all(isinstance(v, float) for v in value)     # rclpy keeps [1, 2] integers
        else:
            ok = all(fits(v, element) for v in value)
        return None if ok else (f'{value!r} is not a list of {type(element).__name__} '
                                '(write floats with a decimal point: [1.0, 2.0])'
                                if isinstance(element, float) else
                                f'{value!r} is not a list of {type(element).__name__}')
    if isinstance(value, list) or not fits(value, default):
        return f'{value!r} is not a {type(default).__name__}'
    return None


def _is_ros_parameter(name: str) -> bool:
    return name in ROS_PARAMETERS or name.startswith(ROS_PARAMETER_PREFIXES)


def file_problems(node_fqn: str, declared: dict[str, Any], path: str,
                  package_names: Iterable[str] = ()) -> list[Problem]:
    """What is wrong with ``path``'s sections that apply to the node ``node_fqn``, whose
    parameters and their defaults are ``declared`` (module doc); ``package_names`` are the
    parameters of every node of the package. A file that cannot be read is left to the command
    line's own check (:func:`soft_gripper_sdre.nodes.cli.params_file_problem`)."""
    try:
        root = compose(Path(path).read_text(encoding='utf-8'))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return []
    if not isinstance(root, yaml.MappingNode):
        return []
    package_names = set(package_names)
    node_name = node_fqn.rsplit('/', 1)[-1]
    out = []
    for key_node, section in root.value:
        key = str(key_node.value)
        if not section_applies(key, node_fqn) or not isinstance(section, yaml.MappingNode):
            continue
        params = next((v for k, v in section.value if k.value == 'ros__parameters'), None)
        if not isinstance(params, yaml.MappingNode):
            continue
        where = f'in {path} (section {key!r}, line {{line}})'
        for name, value_node in _flatten(params):
            at = where.format(line=value_node.start_mark.line + 1)
            if _is_ros_parameter(name):
                continue
            if name not in declared:
                if names_the_node(key):
                    out.append(Problem(f'unknown parameter {name!r} for node {node_fqn} {at} '
                                       f'(the {node_name} node has: {", ".join(declared)})',
                                       refuse=True))
                elif name not in package_names:
                    out.append(Problem(f'parameter {name!r} {at} is not a parameter of any node '
                                       f'of this package; {node_fqn} ignores it', refuse=False))
                continue
            try:
                value = rcl_value(value_node)
            except ValueError as exc:
                out.append(Problem(f'parameter {name!r} for node {node_fqn} {at}: {exc}',
                                   refuse=True))
                continue
            why = type_problem(value, declared[name])
            if why:
                out.append(Problem(f'parameter {name!r} for node {node_fqn} {at}: {why}, as '
                                   f'declared (default {declared[name]!r})', refuse=True))
    return out


def package_parameter_names() -> set[str]:
    """Every parameter name of the package's nodes, from the shipped ``config/*.yaml`` (each
    lists its node's parameters with their defaults) of the source tree or the install."""
    from soft_gripper_sdre.nodes.graph import default_params_file

    names: set[str] = set()
    shipped = default_params_file('controller')
    if shipped is None:
        return names
    for path in shipped.parent.glob('*.yaml'):
        try:
            doc = yaml.safe_load(path.read_text(encoding='utf-8'))
        except (OSError, yaml.YAMLError):
            continue
        for section in (doc or {}).values():
            if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
                names.update(section['ros__parameters'])
    return names
