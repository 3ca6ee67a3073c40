"""The shipped parameter files apply to their node under any namespace (real rclpy, no DDS
traffic)."""
import importlib
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
import yaml

from soft_gripper_sdre.nodes.params import params_file_key

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODE_CLASSES = {
    'simulator': 'SimulatorNode', 'estimator': 'EstimatorNode', 'controller': 'ControllerNode',
    'trajectory': 'TrajectoryNode', 'recorder': 'RecorderNode',
}
#: per node, a parameter whose value the test changes in a copy of the shipped file
CHANGED = {
    'simulator': ('noise_std', 1.5e-4), 'estimator': ('meas_std', 1.5e-4),
    'controller': ('r', 2.0e4), 'trajectory': ('t_hold', 1.5), 'recorder': ('output', 'bag'),
}


@pytest.mark.parametrize('namespace', ['/', '/left_hand', '/lab/right_hand'])
@pytest.mark.parametrize('node', sorted(NODE_CLASSES))
def test_shipped_params_file_applies_under_any_namespace(node, namespace, tmp_path):
    doc = yaml.safe_load((CONFIG / f'{node}.yaml').read_text())
    assert list(doc) == [params_file_key(node)], ('the shipped file must match the node in '
                                                  'every namespace')
    name, value = CHANGED[node]
    if node == 'recorder':                       # a bag directory that does not exist yet
        value = str(tmp_path / value)
    assert doc[params_file_key(node)]['ros__parameters'][name] != value
    doc[params_file_key(node)]['ros__parameters'][name] = value
    params_file = tmp_path / f'{node}.yaml'
    params_file.write_text(yaml.safe_dump(doc))

    module = importlib.import_module(f'soft_gripper_sdre.nodes.{node}')
    ctx = Context()
    rclpy.init(context=ctx, args=['--ros-args', '--params-file', str(params_file)])
    instance = None
    try:
        instance = getattr(module, NODE_CLASSES[node])(context=ctx, namespace=namespace)
        assert instance.get_namespace() == namespace
        assert instance.get_parameter(name).value == value
    finally:
        if instance is not None:
            close = getattr(instance, 'close', None)
            if close is not None:
                close()
            instance.destroy_node()
        rclpy.try_shutdown(context=ctx)
