"""What the documents say about the code follows the code: every documented ``ros2 param set``
value parses to its parameter's type as ros2param reads it (YAML 1.1: ``2e6`` is a string there),
and docs/deployment.md's counts and lists of the launch arguments and the graph's nodes are the
code's."""
import importlib
import inspect
from pathlib import Path
import re
import shlex

import pytest
import yaml

from soft_gripper_sdre.nodes.graph import GRASP_NODES, grasp_graph
from soft_gripper_sdre.nodes.params_files import type_problem

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENT = ROOT / 'docs' / 'deployment.md'
#: where a command may be documented: the documents and the code's docstrings
DOCUMENTS = sorted([ROOT / 'README.md', *(ROOT / 'docs').rglob('*.md'),
                    *(ROOT / 'soft_gripper_sdre').rglob('*.py'), *(ROOT / 'launch').glob('*.py')])
PARAM_SET = re.compile(r'ros2 param set ([^`\n]*)')


def documented_param_sets() -> list[tuple[str, str]]:
    """(where, the arguments) of every ``ros2 param set`` with arguments in the documents."""
    out = []
    for path in DOCUMENTS:
        for n, line in enumerate(path.read_text(encoding='utf-8').splitlines(), 1):
            for args in PARAM_SET.findall(line):
                if args.strip():
                    out.append((f'{path.relative_to(ROOT)}:{n}', args.strip()))
    return out


def param_set_problem(args: str) -> str | None:
    """Why ``ros2 param set <args>`` would not set the parameter, or None: the value as ros2param
    reads it (``yaml.safe_load``, YAML 1.1) must be of the parameter's type and within its
    limits, and the parameter must be one that changes at runtime."""
    try:
        node, name, value = shlex.split(args)
    except ValueError:
        return f'expected "<node> <parameter> <value>", got {args!r}'
    module = importlib.import_module(f'soft_gripper_sdre.nodes.{node.rsplit("/", 1)[-1]}')
    param = next((p for p in module.PARAMS if p.name == name), None)
    if param is None:
        return f'{node} has no parameter {name!r}'
    if param.read_only:
        return f'{name} is read-only'
    parsed = yaml.safe_load(value)
    return type_problem(parsed, param.default) or param.check(parsed)


def test_every_documented_param_set_value_parses_to_its_parameters_type():
    found = documented_param_sets()
    assert found, 'no documented ros2 param set found: the extraction is broken'
    problems = [f'{where}: ros2 param set {args}: {param_set_problem(args)}'
                for where, args in found if param_set_problem(args)]
    assert not problems, '\n'.join(problems)


@pytest.mark.parametrize('args, problem', [
    ('/controller q_pos 2e6', "'2e6' is not a float"),
    ('/controller q_pos 2.0e+6', None),
    ('/controller q_pos 2000000', None),
    ('/left_hand/controller r 1.0', None),
    ('/controller q_pos -1.0', 'q_pos must be >='),
    ('/controller finger_names [a]', 'read-only'),
    ('/controller q_poss 1.0', "no parameter 'q_poss'"),
    ('/controller q_pos', 'expected'),
])
def test_the_rule_refuses_what_ros2param_would_not_set(args, problem):
    why = param_set_problem(args)
    assert (why is None) if problem is None else (problem in why), why


# -- docs/deployment.md ----------------------------------------------------------------------

def test_every_count_of_the_launch_arguments_is_theirs(launch_module):
    text = DEPLOYMENT.read_text()
    counts = [int(n) for n in re.findall(r'the (\d+) (?:launch )?arguments', text)]
    assert counts, 'docs/deployment.md no longer counts the launch arguments: update this test'
    assert set(counts) == {len(launch_module.ARGUMENTS)}


def test_the_argument_table_lists_each_argument_with_its_default(launch_module):
    rows = re.findall(r'^\| `(\w+)` \| ([^|]+) \|', DEPLOYMENT.read_text(), re.MULTILINE)
    table = {name: default.strip() for name, default in rows}
    names = [name for name, _, _ in launch_module.ARGUMENTS]
    assert [name for name, _ in rows if name in names] == names
    for name, default, _ in launch_module.ARGUMENTS:
        shown = table[name]
        if default:
            assert shown == f'`{default}`', (name, shown, default)
        else:
            assert shown == "`''`" or shown.startswith('config'), (name, shown)


def test_the_node_list_functions_signatures_are_the_codes(launch_module):
    text = ' '.join(DEPLOYMENT.read_text().split())
    documented = re.search(r'`grasp_nodes\(([^)]*)\)`', text).group(1)
    assert [a.strip() for a in documented.split(',')] == list(
        inspect.signature(launch_module.grasp_nodes).parameters)
    assert [name for name, _, _ in launch_module.ARGUMENTS] == list(
        inspect.signature(launch_module.grasp_nodes).parameters)
    documented = re.search(r'`grasp_graph\(([^`]*)\)` returns', text).group(1)
    keywords = [a.split('=')[0].strip() for a in re.split(r',\s*(?![^{]*})', documented)]
    assert keywords == list(inspect.signature(grasp_graph).parameters)


def test_the_start_order_and_the_simulators_peers_are_the_graphs():
    text = ' '.join(DEPLOYMENT.read_text().split())
    order = re.search(r'in start order: ([a-z, ]+)\.', text).group(1)
    assert tuple(order.split(', ')) == GRASP_NODES
    peers = re.search(r'`wait_for_nodes` parameter \(`([a-z,]+)`\)', text).group(1)
    simulator = grasp_graph().node('simulator')
    assert peers == simulator.parameters['wait_for_nodes']


def test_the_launch_files_usage_shows_every_argument(launch_module):
    usage = launch_module.__doc__.split('Starts the recorder')[0]
    for name, _, _ in launch_module.ARGUMENTS:
        assert f'[{name}:=' in usage, name
