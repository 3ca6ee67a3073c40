"""A whole number for a floating-point parameter is that float (ROS types ``0`` as an integer), on
the command line, in a parameters file and in a runtime change; a string for one is still refused,
naming the parameter. Real node processes over DDS (loopback)."""
import os
import subprocess
import sys

from node_harness import MS
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import Probe, deep, overrides, ros_context, spin_until
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.topics import GRASP_REFERENCE, REFERENCE_QOS

pytestmark = pytest.mark.ros

REST = '0.0, -0.0105, 0.0, -0.0105, 0.0, -0.0105, 0.0, -0.0105'


def _trajectory(*ros_args):
    return subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.trajectory',
                             '--ros-args', '-p', f'rest_pose:={REST}', *ros_args],
                            env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize('how', ['command_line', 'params_file'])
def test_a_node_started_with_integers_for_float_parameters_takes_them(tmp_path, how):
    """t_start 0, t_hold 0 and t_close 1 as integers: the plan is 1 s closing + 2 s opening."""
    if how == 'command_line':
        args = ['-p', 't_start:=0', '-p', 't_hold:=0', '-p', 't_close:=1']
    else:
        path = tmp_path / 'trajectory.yaml'
        path.write_text('/**/trajectory:\n  ros__parameters:\n    t_start: 0\n    t_hold: 0\n'
                        '    t_close: 1\n')
        args = ['--params-file', str(path)]
    proc = _trajectory(*args)
    try:
        with ros_context() as (ctx, executor):
            probe = Probe(ctx)
            probe.listen(MultiDOFJointTrajectory, GRASP_REFERENCE, deep(REFERENCE_QOS))
            executor.add_node(probe)
            plans = probe.received[GRASP_REFERENCE]
            assert spin_until(executor, lambda: plans or proc.poll() is not None, 30.0)
            assert plans, proc.communicate(timeout=5)[1]
        stamp, times, pos, _, _ = cv.msg_to_reference(plans[0], 4)
        assert stamp == 0 and times[-1] == 3000 * MS             # 0 + 1 + 0 + 2 s (t_open)
        assert np.all(pos[0] == pos[-1]) and np.any(pos[200] != pos[0])
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


@pytest.mark.parametrize('how', ['command_line', 'params_file'])
def test_a_string_for_a_float_parameter_is_refused_naming_it(tmp_path, how):
    if how == 'command_line':
        args = ['-p', 't_hold:=long']
    else:
        path = tmp_path / 'trajectory.yaml'
        path.write_text("/**/trajectory:\n  ros__parameters:\n    t_hold: 'long'\n")
        args = ['--params-file', str(path)]
    proc = _trajectory(*args)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert "parameter 't_hold'" in err


def test_a_runtime_change_to_a_whole_number_is_taken_as_the_float():
    with ros_context() as (ctx, executor):
        node = EstimatorNode(context=ctx, parameter_overrides=overrides(max_bridge=1))
        assert node.p['max_bridge'] == 1.0 and isinstance(node.p['max_bridge'], float)
        res = node.set_parameters([Parameter('reset_on_jump', value=1)])[0]
        assert res.successful, res.reason
        assert node.get_parameter('reset_on_jump').value == 1.0 and node.jump_ns == cv.NS
        assert node.get_parameter('reset_on_jump').type_ is Parameter.Type.DOUBLE
        res = node.set_parameters([Parameter('reset_on_jump', value='long')])[0]
        assert not res.successful and node.jump_ns == cv.NS
