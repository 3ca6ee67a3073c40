"""The graph's description (nodes/graph.py): command lines, namespaces and the clock remapping,
checked as data and against rcl's own name resolution (real rclpy, no DDS traffic)."""
import ast
from pathlib import Path
import sys

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node

from soft_gripper_sdre.nodes import graph
from soft_gripper_sdre.nodes.graph import (
    GRASP_NODES,
    NodeSpec,
    default_params_file,
    grasp_graph,
    normalize_namespace,
)
from soft_gripper_sdre.nodes.topics import CLOCK, TOPIC_TYPES


def test_the_description_imports_no_ros_client_library():
    """A launch file, a test or a supervisor in another network namespace reads it without rclpy."""
    tree = ast.parse(Path(graph.__file__).read_text(encoding='utf-8'))
    modules = {a.name.split('.')[0]
               for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    modules |= {n.module.split('.')[0]
                for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert modules <= {'__future__', 'dataclasses', 'os', 'pathlib', 're', 'shutil', 'sys',
                       'typing', 'ament_index_python'}, modules
    assert graph.CLOCK == CLOCK


def test_root_graph_command_lines_are_those_ros2_run_takes():
    """The root namespace adds nothing: the params file, then each override (the demo's nodes)."""
    spec = grasp_graph(parameters={'recorder': {'output': '/tmp/bag'},
                                   'simulator': {'duration': 6.0, 'min_tip_subscribers': 3,
                                                 'noise_std': 1e-4},
                                   'controller': {'law': 'sdre'}})
    assert spec.names == GRASP_NODES and spec.lead == 'simulator'
    commands = {n.name: n.command('python') for n in spec.nodes}
    assert commands['simulator'] == ['python', '-m', 'soft_gripper_sdre.nodes.simulator',
                                     '--ros-args', '--params-file',
                                     str(default_params_file('simulator')), '-p', 'duration:=6.0',
                                     '-p', 'min_tip_subscribers:=3', '-p', 'noise_std:=0.0001',
                                     '-p',
                                     'wait_for_nodes:=recorder,estimator,trajectory,controller']
    assert commands['estimator'] == ['python', '-m', 'soft_gripper_sdre.nodes.estimator',
                                     '--ros-args', '--params-file',
                                     str(default_params_file('estimator'))]
    assert commands['controller'][-2:] == ['-p', 'law:=sdre']
    assert all(n.params_file is not None and n.params_file.is_file() for n in spec.nodes)


def test_the_simulator_waits_for_the_tip_readers_the_graph_has():
    assert grasp_graph().node('simulator').parameters['min_tip_subscribers'] == 3
    assert grasp_graph(record=False).node('simulator').parameters['min_tip_subscribers'] == 2
    assert (grasp_graph(parameters={'simulator': {'min_tip_subscribers': 5}})
            .node('simulator').parameters['min_tip_subscribers'] == 5)
    assert 'recorder' not in grasp_graph(record=False).names


def test_a_hand_in_a_namespace_gets_its_own_clock():
    spec = grasp_graph('left_hand', parameters={'trajectory': {'grasp_fingers': [1, 3]}})
    assert spec.namespace == '/left_hand'
    for node in spec.nodes:
        args = node.ros_arguments()
        assert (args[:3] == ['--ros-args', '-r', '__ns:=/left_hand']
                and args[-2:] == ['-r', '/clock:=clock'])
        assert node.full_name == f'/left_hand/{node.name}'
    assert '-p' in spec.node('trajectory').ros_arguments()
    assert 'grasp_fingers:=[1,3]' in spec.node('trajectory').ros_arguments()
    assert spec.topic('/clock') == '/left_hand/clock'
    assert spec.topic('tip_positions') == '/left_hand/tip_positions'
    assert spec.topic('/diagnostics') == '/diagnostics'
    shared = grasp_graph('left_hand', clock='/clock')  # one simulator per domain: the usual /clock
    assert shared.remappings == () and shared.topic('/clock') == '/clock'
    assert grasp_graph().topic('/clock') == '/clock' and grasp_graph().remappings == ()


@pytest.mark.parametrize('text, expected', [('', ''), ('/', ''), ('left_hand', '/left_hand'),
                                            ('/left_hand/', '/left_hand'),
                                            ('robot1/hand_2', '/robot1/hand_2')])
def test_namespaces_are_normalised(text, expected):
    assert normalize_namespace(text) == expected


@pytest.mark.parametrize('text', ['2hand', 'left hand', 'left-hand', 'a//b'])
def test_bad_namespaces_are_refused_with_the_token(text):
    with pytest.raises(ValueError, match='is not a valid name token'):
        grasp_graph(text)


def test_parameters_for_a_node_the_graph_lacks_are_refused():
    with pytest.raises(ValueError, match=r"parameters for \['recorder'\]"):
        grasp_graph(record=False, parameters={'recorder': {'output': 'x'}})
    with pytest.raises(KeyError):
        grasp_graph().with_parameters('planner', x=1)


def test_one_control_period_reaches_every_node_that_declares_one():
    import importlib
    declares = {name for name in GRASP_NODES
                if any(p.name == 'control_period'
                       for p in importlib.import_module(f'soft_gripper_sdre.nodes.{name}').PARAMS)}
    assert declares == set(graph.PERIOD_NODES)
    spec = grasp_graph(control_period=0.005, parameters={'controller': {'law': 'sdre'}})
    assert {n.name: n.parameters.get('control_period') for n in spec.nodes} == {
        'recorder': None, 'estimator': 0.005, 'trajectory': None, 'controller': 0.005,
        'simulator': 0.005}
    assert spec.node('controller').parameters['law'] == 'sdre'
    assert ('-p' in spec.node('estimator').ros_arguments()
            and 'control_period:=0.005' in spec.node('estimator').ros_arguments())
    with pytest.raises(ValueError,
                       match='control_period 0.005 s for the graph, but 0.002 s in the estimator'):
        grasp_graph(control_period=0.005, parameters={'estimator': {'control_period': 0.002}})


def test_a_renamed_node_says_so_on_its_command_line():
    spec = NodeSpec('recorder_left', 'recorder', parameters={'topics': ['tip_positions', '/clock']})
    assert spec.ros_arguments() == ['--ros-args', '-r', '__node:=recorder_left', '-p',
                                    "topics:=['tip_positions','/clock']"]
    assert spec.command()[:3] == [sys.executable, '-m', 'soft_gripper_sdre.nodes.recorder']


@pytest.mark.parametrize('namespace', ['', 'left_hand'])
def test_rcl_resolves_every_topic_as_the_description_says(namespace):
    """Each node's own ROS arguments, parsed by rcl: its name and namespace, and every topic of
    the graph (the clock remapped) where :meth:`GraphSpec.topic` puts it."""
    spec = grasp_graph(namespace)
    for node_spec in spec.nodes:
        ctx = Context()
        rclpy.init(args=['node', *node_spec.ros_arguments()], context=ctx)
        try:
            node = Node(node_spec.executable, context=ctx)
            assert node.get_fully_qualified_name() == node_spec.full_name
            for topic in TOPIC_TYPES:
                assert node.resolve_topic_name(topic) == spec.topic(topic), (node_spec.name, topic)
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)


def test_a_composed_graph_runs_the_estimator_in_the_controllers_process():
    """``composed``: no estimator process; the controller's takes ``--with-estimator``, both
    nodes' shipped files, then the user's, then the overrides; the estimator is still a node of
    the graph (the simulator waits for it)."""
    mine = Path('/tmp/mine.yaml')
    spec = grasp_graph(composed=True, control_period=0.002, params_files=[mine])
    assert [n.name for n in spec.nodes] == ['recorder', 'trajectory', 'controller', 'simulator']
    assert spec.names == ('recorder', 'trajectory', 'controller', 'estimator', 'simulator')
    assert spec.node('estimator').executable == 'estimator'
    assert 'estimator' in spec.node('simulator').parameters['wait_for_nodes'].split(',')
    command = spec.node('controller').command('python')
    assert command[:5] == ['python', '-m', 'soft_gripper_sdre.nodes.controller',
                           '--with-estimator', '--ros-args']
    files = [command[i + 1] for i, a in enumerate(command) if a == '--params-file']
    assert files == [str(default_params_file('controller')),
                     str(default_params_file('estimator')), str(mine)]
    assert command[-2:] == ['-p', 'control_period:=0.002']
    tuned = spec.with_parameters('estimator', max_bridge=0.02)
    assert tuned.node('estimator').parameters['max_bridge'] == 0.02
    assert tuned.node('controller').command('python')[-2:] == ['-p', 'max_bridge:=0.02']
    assert [n.name for n in spec.without('recorder').nodes] == ['trajectory', 'controller',
                                                                'simulator']


def test_composing_refuses_what_one_process_cannot_hold():
    with pytest.raises(ValueError, match='set control_period to different values'):
        grasp_graph(parameters={'estimator': {'control_period': 0.001},
                                'controller': {'control_period': 0.002}}, composed=True)
    with pytest.raises(ValueError, match='needs the nodes estimator and controller'):
        grasp_graph().without('estimator').composed()


def test_rcl_gives_each_node_of_the_composed_process_its_own_parameters(tmp_path):
    """The composed command's ROS arguments, parsed by rcl with the two nodes in one context:
    each takes its own section of each file, the user's file after the shipped ones."""
    mine = tmp_path / 'mine.yaml'
    mine.write_text('/**/estimator:\n  ros__parameters:\n    max_bridge: 0.02\n'
                    '/**/controller:\n  ros__parameters:\n    law: sdre\n')
    host = grasp_graph('left_hand', composed=True, params_files=[mine]).node('controller')
    ctx = Context()
    rclpy.init(args=['node', *host.ros_arguments()], context=ctx)
    try:
        estimator = Node('estimator', context=ctx)
        controller = Node('controller', context=ctx)
        assert estimator.declare_parameter('max_bridge', 0.0).value == 0.02
        assert estimator.declare_parameter('meas_std', 0.0).value == 5e-5     # estimator.yaml
        assert controller.declare_parameter('law', '').value == 'sdre'
        assert controller.declare_parameter('max_bridge', 0.0).value == 0.0   # not its section
        assert controller.get_fully_qualified_name() == '/left_hand/controller'
        for node in (estimator, controller):
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
