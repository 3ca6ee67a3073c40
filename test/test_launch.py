"""launch/grasp.launch.py: its node list is the graph's description, without the launch packages.

The launch file imports ``launch``/``launch_ros`` only inside ``generate_launch_description``, so
these tests load it in the project's environment (which has neither) and compare what it would
start with :func:`soft_gripper_sdre.nodes.graph.grasp_graph`.
"""
import ast
from pathlib import Path

import pytest

from soft_gripper_sdre.nodes.graph import grasp_graph

LAUNCH_FILE = Path(__file__).resolve().parents[1] / 'launch' / 'grasp.launch.py'


def _as_launched(graph_spec) -> list[dict]:
    """What launch_ros would get for each node of the description."""
    return [{'package': 'soft_gripper_sdre', 'executable': n.executable, 'name': n.name,
             'namespace': n.namespace.lstrip('/') or None,
             'parameters': [str(f) for f in (n.params_file, *n.more_params_files)]
             + ([dict(n.parameters)] if n.parameters else []),
             'remappings': list(n.remappings)} for n in graph_spec.nodes]


def test_the_launch_packages_are_imported_only_when_launching():
    tree = ast.parse(LAUNCH_FILE.read_text(encoding='utf-8'))
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert [getattr(n, 'module', None) for n in top] == ['soft_gripper_sdre.nodes.graph']
    generate = next(n for n in tree.body if isinstance(n, ast.FunctionDef)
                    and n.name == 'generate_launch_description')
    inside = {n for n in ast.walk(generate) if isinstance(n, ast.ImportFrom)}
    launch = {n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
              and n.module.split('.')[0] in ('launch', 'launch_ros')}
    assert launch <= inside and {n.module.split('.')[0] for n in launch} == {'launch', 'launch_ros'}


def test_default_launch_is_the_root_graph_without_recorder(launch_module):
    nodes = launch_module.grasp_nodes()
    assert nodes == _as_launched(grasp_graph(record=False, parameters={
        'simulator': {'duration': 6.0, 'startup_timeout': 300.0}}))
    assert [n['executable'] for n in nodes] == ['estimator', 'trajectory', 'controller',
                                                'simulator']
    assert all(Path(n['parameters'][0]).is_file() and n['remappings'] == [] for n in nodes)
    defaults = {name: default for name, default, _ in launch_module.ARGUMENTS}
    assert launch_module.grasp_nodes(**defaults) == nodes


def test_a_hand_in_a_namespace_with_every_argument(launch_module):
    nodes = launch_module.grasp_nodes(namespace='left_hand', duration='2.5', law='sdre',
                                      noise='0.2', seed='7', record='true',
                                      output='/tmp/left_bag', startup_timeout='60')
    expected = grasp_graph('left_hand', parameters={
        'simulator': {'duration': 2.5, 'startup_timeout': 60.0, 'noise_std': 0.2e-3, 'seed': 7},
        'controller': {'law': 'sdre'},
        'recorder': {'output': '/tmp/left_bag'}})
    assert nodes == _as_launched(expected)
    assert {n['namespace'] for n in nodes} == {'left_hand'}
    assert all(n['remappings'] == [('/clock', 'clock')] for n in nodes)
    simulator = nodes[-1]['parameters'][1]
    assert simulator == {'duration': 2.5, 'startup_timeout': 60.0, 'noise_std': pytest.approx(2e-4),
                         'seed': 7, 'min_tip_subscribers': 3,
                         'wait_for_nodes': 'recorder,estimator,trajectory,controller'}


@pytest.mark.parametrize('arguments, needle', [
    ({'duration': 'six'}, "duration:='six' is not a number"),
    ({'seed': '1.5'}, "seed:='1.5' is not a number"),
    ({'record': 'maybe'}, "record:='maybe' must be 'true' or 'false'"),
    ({'namespace': '2nd_hand'}, 'is not a valid name token'),
    ({'control_period': '0.02'}, "control_period:='0.02' must be from 0.001 to 0.01 s"),
    ({'control_period': '5ms'}, "control_period:='5ms' is not a number"),
    ({'law': 'bogus'}, "law:='bogus' is not a law of the controller (sdre, sdre_ff, lqr"),
    ({'law': 'oracle'}, "law:='oracle' is not a law of the controller"),
    ({'noise': '50'}, "noise:='50': noise_std must be <= 0.01"),
    ({'seed': '-1'}, "seed:='-1': seed must be >= 0"),
    ({'mode': 'pipeline'}, "mode:='pipeline': mode must be one of"),
    ({'duration': '-1'}, "duration:='-1': duration must be >= 0"),
    ({'startup_timeout': 'nan'}, "startup_timeout:='nan'"),
    ({'params_file': '/nonexistent/mine.yaml'},
     "params_file:='/nonexistent/mine.yaml': cannot read"),
])
def test_bad_arguments_are_named(launch_module, arguments, needle):
    with pytest.raises(ValueError, match=needle.replace('(', r'\(').replace('.', r'\.')):
        launch_module.grasp_nodes(**arguments)


def test_the_declared_arguments_are_the_ones_grasp_nodes_takes(launch_module):
    """The arguments documented in the launch file are exactly the ones grasp_nodes takes."""
    import inspect
    names = [name for name, _, _ in launch_module.ARGUMENTS]
    assert names == list(inspect.signature(launch_module.grasp_nodes).parameters)
    assert callable(launch_module.generate_launch_description)


def test_control_period_reaches_every_node_of_the_loop(launch_module):
    nodes = {n['name']: n for n in launch_module.grasp_nodes(control_period='0.005')}
    overrides = {name: next((d for d in n['parameters'] if isinstance(d, dict)), {})
                 for name, n in nodes.items()}
    periods = {name: d.get('control_period') for name, d in overrides.items()}
    assert periods == {'estimator': 0.005, 'trajectory': None, 'controller': 0.005,
                       'simulator': 0.005}


def test_the_mode_reaches_the_simulator(launch_module):
    simulator = launch_module.grasp_nodes(mode='pipelined')[-1]
    assert simulator['name'] == 'simulator' and simulator['parameters'][-1]['mode'] == 'pipelined'
    assert 'mode' not in launch_module.grasp_nodes()[-1]['parameters'][-1]


def test_the_law_choices_are_the_controllers_own(launch_module):
    from soft_gripper_sdre.control.laws import GRAPH_LAWS
    from soft_gripper_sdre.nodes.controller import PARAMS
    assert next(p for p in PARAMS if p.name == 'law').choices == GRAPH_LAWS
    for law in GRAPH_LAWS:
        controller = launch_module.grasp_nodes(law=law)[2]
        assert controller['name'] == 'controller' and controller['parameters'][-1] == {'law': law}


def test_a_users_params_file_comes_after_the_shipped_one_and_before_the_arguments(launch_module,
                                                                                 tmp_path):
    mine = tmp_path / 'mine.yaml'
    mine.write_text('/**/controller:\n  ros__parameters:\n    integral_gain: 0.0\n')
    nodes = launch_module.grasp_nodes(params_file=str(mine), law='sdre')
    for node in nodes:
        shipped, users = node['parameters'][:2]
        assert Path(shipped).name == f'{node["name"]}.yaml' and users == str(mine.resolve())
    assert nodes[2]['parameters'][2] == {'law': 'sdre'}


def test_composed_runs_the_estimator_in_the_controllers_process(launch_module, tmp_path):
    """``composed:=true``: three processes without the recorder; the controller's takes
    ``--with-estimator`` and both nodes' files, and has no ``name`` (launch_ros would rename
    every node of the process with it)."""
    mine = tmp_path / 'mine.yaml'
    mine.write_text('/**/estimator:\n  ros__parameters:\n    max_bridge: 0.02\n')
    nodes = launch_module.grasp_nodes(composed='true', control_period='0.002',
                                      params_file=str(mine))
    assert [n['executable'] for n in nodes] == ['trajectory', 'controller', 'simulator']
    host = nodes[1]
    assert host['name'] is None and host['arguments'] == ['--with-estimator']
    assert [Path(f).name for f in host['parameters'][:3]] == ['controller.yaml', 'estimator.yaml',
                                                              'mine.yaml']
    assert host['parameters'][3] == {'control_period': 0.002}
    assert 'arguments' not in nodes[0] and 'arguments' not in launch_module.grasp_nodes()[2]
    with pytest.raises(ValueError, match="composed:='yes please' must be 'true' or 'false'"):
        launch_module.grasp_nodes(composed='yes please')


@pytest.mark.parametrize('text, needle', [('[1, 2]', 'is not a ROS parameters file'),
                                          ('a: [', 'is not YAML')])
def test_a_params_file_that_is_not_one_is_named(launch_module, tmp_path, text, needle):
    bad = tmp_path / 'bad.yaml'
    bad.write_text(text)
    with pytest.raises(ValueError, match=f"params_file:='{bad}'.*{needle}"):
        launch_module.grasp_nodes(params_file=str(bad))


@pytest.mark.parametrize('text, needle', [
    ('/**/controller:\n  ros__parameters:\n    q_pos: abc\n',
     "parameter 'q_pos' for node /left_hand/controller in {path} (section '/**/controller', "
     "line 3): 'abc' is not a float"),
    ('/**/estimator:\n  ros__parameters:\n    q_pos: 2.0\n',
     "unknown parameter 'q_pos' for node /left_hand/estimator in {path}"),
])
@pytest.mark.parametrize('composed', ['false', 'true'])
def test_a_params_file_wrong_for_a_node_is_refused_before_any_starts(launch_module, tmp_path,
                                                                     text, needle, composed):
    """The shipped file comes first, so rcl would keep its float and drop the string unheard."""
    mine = tmp_path / 'mine.yaml'
    mine.write_text(text)
    with pytest.raises(ValueError) as err:
        launch_module.grasp_nodes(namespace='left_hand', params_file=str(mine), composed=composed)
    assert str(err.value).startswith(f"launch argument params_file:='{mine}': ")
    assert needle.format(path=mine.resolve()) in str(err.value)


def test_a_whole_graphs_params_file_is_taken(launch_module, tmp_path):
    mine = tmp_path / 'mine.yaml'
    mine.write_text('/**:\n  ros__parameters:\n    finger_names: [a, b, c, d]\n'
                    '    q_pos: 2.0\n/**/controller:\n  ros__parameters:\n    law: pd\n')
    nodes = launch_module.grasp_nodes(params_file=str(mine), record='true')
    assert all(str(mine.resolve()) in node['parameters'] for node in nodes)


@pytest.mark.parametrize('node, code, shutting_down, verdict', [
    ('simulator', 0, False, ('done', 'the simulator finished')),
    ('simulator', 1, False, ('failed', 'the simulator node exited with status 1')),
    ('controller', 2, False, ('failed', 'the controller node exited with status 2')),
    ('recorder', 0, False, ('failed', 'the recorder node exited with status 0')),
    ('controller', -15, True, None),
    ('simulator', 0, True, None),
])
def test_a_node_that_ends_on_its_own_ends_the_launch(launch_module, node, code, shutting_down,
                                                     verdict):
    """The lead finishing ends the launch cleanly; any other exit before that ends it with an
    error naming the node and its status; exits while it shuts down change nothing."""
    got = launch_module.exit_verdict(node, code, shutting_down)
    if verdict is None:
        assert got is None
    else:
        assert got[0] == verdict[0] and got[1].startswith(verdict[1])
