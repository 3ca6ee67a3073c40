"""A node's sections of its parameters files are checked against what it declares: a value of the
wrong type (also one rcl's merge of several files would drop without a word) or an unknown key is
refused at start-up naming the key, the node and the file, exit status 2; a wildcard section's
key no node of the package has is warned about. Real node processes, and rcl's own reading of
the files to check ours against."""
import importlib
import os
from pathlib import Path
import subprocess
import sys

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node

from soft_gripper_sdre.nodes.params import declared_types
from soft_gripper_sdre.nodes.params_files import (
    file_problems,
    package_parameter_names,
    section_applies,
    type_problem,
)

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
NODES = ('simulator', 'estimator', 'controller', 'trajectory', 'recorder', 'excitation',
         'plant_driver', 'mocap_tips')
#: scalars as a parameters file may hold them; rcl reads each as the comment says
SCALARS = ['2e6', '2.0e+6', '0x10', '010', '0', 'yes', 'Y', 'off', '"1.0"', "'abc'", '.inf',
           '-.inf', '.NaN', 'nan', 'inf', '1_000', '+1', '-3', '1.', '.5', '~', '1e3', '0b11',
           '!!str 3', '1:20', '0o7', 'abc', 'True', '1 ', '-0.0']


def _rcl_overrides(path: Path, node_name: str = 'n', namespace: str = '/') -> dict:
    """The values rcl gives the node ``namespace/node_name`` from ``path`` alone."""
    ctx = Context()
    rclpy.init(args=['x', '--ros-args', '--params-file', str(path)], context=ctx)
    try:
        node = Node(node_name, namespace=namespace, context=ctx)
        values = {k: v.value for k, v in node._parameter_overrides.items()}
        node.destroy_node()
        return values
    finally:
        rclpy.try_shutdown(context=ctx)


def test_scalars_are_read_as_rcl_reads_them(tmp_path):
    import math

    from soft_gripper_sdre.nodes.params_files import compose, rcl_value
    lines = ''.join(f'    s{i}: {text}\n' for i, text in enumerate(SCALARS))
    lines += '    l0: [1, 2]\n    l1: [1.0, 2.5]\n    l2: [a, "b"]\n    l3: [true, no]\n'
    path = tmp_path / 'p.yaml'
    path.write_text(f'n:\n  ros__parameters:\n{lines}')
    rcl = _rcl_overrides(path)
    ours = {k.value: rcl_value(v) for k, v in
            compose(path.read_text()).value[0][1].value[0][1].value}
    assert set(ours) == set(rcl)
    for name, value in rcl.items():
        mine = ours[name]
        assert type(mine) is type(value), (name, mine, value)
        if isinstance(value, float) and math.isnan(value):
            assert math.isnan(mine)
        else:
            assert mine == value, (name, mine, value)


@pytest.mark.parametrize('key, fqn', [
    (key, fqn) for key in ('/**', 'n', '/n', '/*/n', '/**/n', '/a/n', '/a/*', '/**/m', 'a/n',
                           '/*', '/a/**', '/**/a/n')
    for fqn in ('/n', '/a/n', '/b/a/n')])
def test_sections_apply_to_the_nodes_rcl_gives_them_to(key, fqn, tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text(f'{key}:\n  ros__parameters:\n    marker: 1\n')
    namespace, name = fqn.rsplit('/', 1)
    assert section_applies(key, fqn) == ('marker' in _rcl_overrides(path, name, namespace or '/'))


@pytest.mark.parametrize('node', NODES)
def test_the_shipped_files_pass_their_own_nodes_check(node):
    params = importlib.import_module(f'soft_gripper_sdre.nodes.{node}').PARAMS
    declared = declared_types(params)
    path = ROOT / 'config' / f'{node}.yaml'
    assert file_problems(f'/{node}', declared, str(path), package_parameter_names()) == []
    assert set(declared) <= package_parameter_names()


@pytest.mark.parametrize('value, default, ok', [
    (1, 1.0, True), (True, 1.0, False), ('abc', 1.0, False), (1.5, 1, False), (1, 1, True),
    ('x', 'y', True), (3, 'y', False), (True, False, True), (1, False, False),
    ([1.0, 2.0], [0.5], True), ([1, 2], [0.5], False), (['a'], ['b'], True), ([1], ['b'], False),
    ([], ['b'], True), ('a', ['b'], False), ([1], 1, False), ([0, 2], [0, 2], True)])
def test_type_rule(value, default, ok):
    assert (type_problem(value, default) is None) == ok


def _run(node, *args, cwd):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.nodes.{node}', *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize('text, needle', [
    # given after the shipped file, whose float rcl's merge would keep
    ('/**/estimator:\n  ros__parameters:\n    max_bridge: abc\n',
     "parameter 'max_bridge' for node /estimator in {path} (section '/**/estimator', line 3): "
     "'abc' is not a float"),
    ('/estimator:\n  ros__parameters:\n    control_period: [0.001]\n',
     "parameter 'control_period' for node /estimator in {path}"),
    ('/**:\n  ros__parameters:\n    finger_names: [1, 2]\n',
     "parameter 'finger_names' for node /estimator in {path} (section '/**', line 3): [1, 2] is "
     'not a list of str'),
    ('/**/estimator:\n  ros__parameters:\n    max_bridg: 0.1\n',
     "unknown parameter 'max_bridg' for node /estimator in {path} (section '/**/estimator', "
     'line 3)'),
    ('estimator:\n  ros__parameters:\n    kf:\n      q: 1.0\n',
     "unknown parameter 'kf.q' for node /estimator in {path} (section 'estimator', line 4)"),
])
def test_a_wrong_typed_or_unknown_key_is_refused_naming_key_node_and_file(text, needle,
                                                                          tmp_path):
    path = tmp_path / 'mine.yaml'
    path.write_text(text)
    out = _run('estimator', '--ros-args', '--params-file', str(ROOT / 'config' / 'estimator.yaml'),
               '--params-file', str(path), cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert needle.format(path=path) in out.stderr
    assert 'Traceback' not in out.stderr


def test_sections_for_other_nodes_and_the_packages_keys_under_a_wildcard_are_taken(tmp_path):
    """One file for the whole graph: the controller's section and its q_pos under /** do not
    concern the recorder; a key no node has is warned about and the recorder records."""
    path = tmp_path / 'graph.yaml'
    path.write_text('/**:\n  ros__parameters:\n    q_pos: 2.0\n    my_own_gain: 3\n'
                    '/**/controller:\n  ros__parameters:\n    q_pos: abc\n'
                    '/**/recorder:\n  ros__parameters:\n    storage: mcap\n')
    bag = tmp_path / 'bag'
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.recorder', '--ros-args',
                             '--params-file', str(path), '-p', f'output:={bag}'], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    import time
    deadline = time.monotonic() + 60
    while not (bag / 'metadata.yaml').exists() and not list(bag.glob('*.mcap')) \
            and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    proc.send_signal(2)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert (f"parameter 'my_own_gain' in {path} (section '/**', line 4) is not a parameter of "
            'any node of this package; /recorder ignores it') in err
    assert 'q_pos' not in err
    assert (bag / 'metadata.yaml').is_file()


def test_a_namespaced_node_is_checked_against_the_sections_that_reach_it(tmp_path):
    path = tmp_path / 'hands.yaml'
    path.write_text('/right_hand/recorder:\n  ros__parameters:\n    storage: 3\n'
                    '/left_hand/recorder:\n  ros__parameters:\n    storag: mcap\n')
    out = _run('recorder', '--ros-args', '-r', '__ns:=/left_hand', '--params-file', str(path),
               '-p', f'output:={tmp_path / "bag"}', cwd=tmp_path)
    assert out.returncode == 2
    assert "unknown parameter 'storag' for node /left_hand/recorder" in out.stderr
    assert 'storage' not in out.stderr.split('has:')[0]
    assert not (tmp_path / 'bag').exists()


def test_each_node_of_a_composed_process_checks_its_own_sections(tmp_path):
    """controller --with-estimator: the estimator refuses a key its section names and the
    controller's section is the controller's."""
    path = tmp_path / 'mine.yaml'
    path.write_text('/**/controller:\n  ros__parameters:\n    law: pd\n'
                    '/**/estimator:\n  ros__parameters:\n    max_bridg: 0.1\n')
    out = _run('controller', '--with-estimator', '--ros-args',
               '--params-file', str(ROOT / 'config' / 'controller.yaml'),
               '--params-file', str(ROOT / 'config' / 'estimator.yaml'),
               '--params-file', str(path), cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert (f"unknown parameter 'max_bridg' for node /estimator in {path} (section "
            "'/**/estimator', line 6)") in out.stderr
    assert 'law' not in out.stderr.split('bad parameter')[-1]
