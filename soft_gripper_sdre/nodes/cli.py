"""What a node's command line settles before anything starts: ``--help``, bad parameter files
and unknown parameters.

``ros2 run soft_gripper_sdre <node> --help`` prints the node's parameters and exits 0 without
touching ROS. A ``--params-file`` that is missing or is not a ROS parameters file is refused with
a message naming the file and the problem and exit status 2, before ``rclpy.init`` (whose own
parser would end in a traceback). So is a ``-p NAME:=VALUE`` that names no parameter of the node:
ROS would ignore it without a word, and the node would run on the default. The files' contents
are checked against each node's own parameters once the node is made
(:func:`soft_gripper_sdre.nodes.params.check_params_files`).
"""
from __future__ import annotations

from pathlib import Path
import sys
from typing import Iterable, TextIO

import yaml

from soft_gripper_sdre.nodes.params import Param, use_params_files
from soft_gripper_sdre.nodes.params_files import ROS_PARAMETER_PREFIXES, ROS_PARAMETERS

HELP_FLAGS = ('-h', '--help')
#: exit status of a refused command line
USAGE_ERROR = 2


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(user arguments, ROS arguments) of a node's command line (without the program name).

    ROS arguments are those between ``--ros-args`` and ``--`` (or the end); there may be several
    such sections.
    """
    user, ros = [], []
    inside = False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
        elif arg == '--' and inside:
            inside = False
        elif inside:
            ros.append(arg)
        else:
            user.append(arg)
    return user, ros


def params_files(ros_args: list[str]) -> list[str]:
    """Every file named by ``--params-file FILE`` among the ROS arguments."""
    return [ros_args[i + 1] for i, arg in enumerate(ros_args[:-1]) if arg == '--params-file'] + (
        [''] if ros_args[-1:] == ['--params-file'] else [])


def parameter_assignments(ros_args: list[str]) -> list[str]:
    """The NAME of every ``-p NAME:=VALUE`` / ``--param NAME:=VALUE`` among the ROS arguments."""
    return [ros_args[i + 1].split(':=', 1)[0] for i, arg in enumerate(ros_args[:-1])
            if arg in ('-p', '--param') and ':=' in ros_args[i + 1]]


def unknown_parameter_problem(name: str, params: Iterable[Param]) -> str | None:
    """Why ``-p name:=…`` cannot be meant for this node, or None."""
    known = [p.name for p in params]
    if name in known or name in ROS_PARAMETERS or name.startswith(ROS_PARAMETER_PREFIXES):
        return None
    return f'unknown parameter {name!r} (this node has: {", ".join(known)})'


def params_file_problem(path: str) -> str | None:
    """Why ``path`` is not a usable ROS parameters file, or None."""
    if not path:
        return '--params-file needs a file name'
    p = Path(path)
    if not p.is_file():
        return (f'parameters file {path} does not exist' if not p.exists()
                else f'{path} is not a file')
    try:
        doc = yaml.safe_load(p.read_text(encoding='utf-8'))
    except (OSError, UnicodeDecodeError) as exc:
        return f'cannot read parameters file {path}: {exc}'
    except yaml.YAMLError as exc:
        where = getattr(exc, 'problem_mark', None)
        at = f' (line {where.line + 1}, column {where.column + 1})' if where is not None else ''
        return f'parameters file {path} is not valid YAML{at}: {getattr(exc, "problem", exc)}'
    if not isinstance(doc, dict) or not doc:
        return f'parameters file {path} must map node names to {{ros__parameters: {{...}}}}'
    for node, section in doc.items():
        if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
            return f'parameters file {path}: entry {node!r} must hold a ros__parameters mapping'
    return None


def format_help(executable: str, summary: str, params: Iterable[Param]) -> str:
    """The ``--help`` text: usage, what the node does, and every parameter with its default."""
    lines = [f'usage: ros2 run soft_gripper_sdre {executable} [--help] '
             '[--ros-args [--params-file FILE] [-p NAME:=VALUE ...] [-r FROM:=TO ...]]', '']
    if summary:
        lines += [summary, '']
    lines.append('parameters (default; units; range or choices):')
    for p in params:
        limits = []
        if p.units:
            limits.append(p.units)
        if p.min is not None or p.max is not None:
            lo = '-inf' if p.min is None else f'{p.min:g}'
            hi = 'inf' if p.max is None else f'{p.max:g}'
            limits.append(f'[{lo}, {hi}]')
        if p.choices:
            limits.append('one of ' + ', '.join(map(str, p.choices)))
        extra = f'; {"; ".join(limits)}' if limits else ''
        lines.append(f'  {p.name} = {p.default!r}{extra}')
        lines.append(f'      {p.description}{" (read-only)" if p.read_only else ""}')
    return '\n'.join(lines) + '\n'


def settle_command_line(argv: list[str], executable: str, summary: str, params: Iterable[Param],
                        out: TextIO = sys.stdout, err: TextIO = sys.stderr) -> int | None:
    """Handle ``--help`` and refuse bad parameter files and unknown ``-p`` parameters; the exit
    status, or None to go on."""
    params = list(params)
    user, ros = split_ros_args(argv)
    if any(a in HELP_FLAGS for a in user):
        out.write(format_help(executable, summary, params))
        return 0
    for name in parameter_assignments(ros):
        problem = unknown_parameter_problem(name, params)
        if problem:
            err.write(f'{executable}: {problem}\n')
            return USAGE_ERROR
    for path in params_files(ros):
        problem = params_file_problem(path)
        if problem:
            err.write(f'{executable}: {problem}\n')
            return USAGE_ERROR
    use_params_files(params_files(ros))
    return None
