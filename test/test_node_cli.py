"""Node command lines: --help prints the parameters and starts nothing; bad parameter files and
ROS arguments exit 2 with a message naming the problem and no traceback (real processes)."""
import os
import subprocess
import sys

import pytest

from soft_gripper_sdre.nodes.cli import params_files, split_ros_args

NODES = ('simulator', 'estimator', 'controller', 'trajectory', 'recorder', 'excitation',
         'plant_driver', 'mocap_tips')


def _run(node, *args, tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.nodes.{node}', *args],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize('node, flag', [(node, '--help') for node in NODES] + [('simulator', '-h')])
def test_help_lists_every_parameter_and_exits_zero(node, flag, tmp_path):
    import importlib
    params = importlib.import_module(f'soft_gripper_sdre.nodes.{node}').PARAMS
    out = _run(node, flag, tmp_path=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f'usage: ros2 run soft_gripper_sdre {node} ')
    for p in params:
        assert f'  {p.name} = {p.default!r}' in out.stdout
    assert 'Traceback' not in out.stderr
    assert not list(tmp_path.iterdir()), ('help must not start the node (the recorder would '
                                          'write a bag)')


@pytest.mark.parametrize('content, expected', [
    (None, 'does not exist'),
    ('a: [1\n', 'is not valid YAML (line 2'),
    ('just a string\n', 'must map node names'),
    ('/**/controller:\n  law: pd\n', "entry '/**/controller' must hold a ros__parameters mapping"),
])
def test_bad_params_file_exits_2_naming_the_problem(content, expected, tmp_path):
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    out = _run('controller', '--ros-args', '--params-file', str(path), tmp_path=tmp_path)
    assert out.returncode == 2
    assert 'controller: ' in out.stderr and expected in out.stderr and str(path) in out.stderr
    assert 'Traceback' not in out.stderr


def test_bad_ros_argument_exits_2_without_traceback(tmp_path):
    out = _run('estimator', '--ros-args', '-r', ':=bad', tmp_path=tmp_path)
    assert out.returncode == 2
    assert ('estimator: cannot start with these arguments' in out.stderr
            and "remap rule" in out.stderr)
    assert 'Traceback' not in out.stderr


def test_bad_parameter_value_exits_2_naming_the_parameter(tmp_path):
    out = _run('controller', '--ros-args', '-p', 'law:=nonsense', tmp_path=tmp_path)
    assert out.returncode == 2
    assert 'law' in out.stderr and 'nonsense' in out.stderr
    assert 'Traceback' not in out.stderr


def test_ros_args_sections_are_told_apart_from_user_args():
    user, ros = split_ros_args(['--help', '--ros-args', '--params-file', 'a.yaml', '--', 'x',
                                '--ros-args', '-p', 'n:=1'])
    assert user == ['--help', 'x']
    assert ros == ['--params-file', 'a.yaml', '-p', 'n:=1']
    assert params_files(ros) == ['a.yaml']
    assert params_files(['--params-file']) == ['']


@pytest.mark.parametrize('node', ['estimator', 'controller'])
def test_unknown_parameter_exits_2_listing_the_nodes_parameters(node, tmp_path):
    out = _run(node, '--ros-args', '-p', 'n_fingers:=2', tmp_path=tmp_path)
    assert out.returncode == 2
    assert f"{node}: unknown parameter 'n_fingers'" in out.stderr and 'finger_names' in out.stderr
    assert 'Traceback' not in out.stderr
    assert not list(tmp_path.iterdir())


def test_rclpy_own_parameters_are_not_unknown():
    from soft_gripper_sdre.nodes.cli import unknown_parameter_problem
    from soft_gripper_sdre.nodes.controller import PARAMS
    for name in ('use_sim_time', 'qos_overrides./tip_positions.subscription.depth', 'law'):
        assert unknown_parameter_problem(name, PARAMS) is None
    assert 'unknown parameter' in unknown_parameter_problem('lwa', PARAMS)
