"""The estimator and the controller as two nodes of one process (``controller --with-estimator``):
the estimate handed over in-process is answered with the same torques as over DDS, and is still
published on state_estimate."""
import os
import signal
import subprocess
import sys
import time

from geometry_msgs.msg import PoseArray
from node_harness import MS, horizon
import numpy as np
import pytest
from rosutil import Probe, deep, linked, ros_context, spin_until
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import wiring
from soft_gripper_sdre.nodes.composition import with_estimator
from soft_gripper_sdre.nodes.controller import ControllerNode
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.topics import (
    GRASP_REFERENCE,
    LOOP_QOS,
    REFERENCE_QOS,
    STATE_ESTIMATE,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)

pytestmark = pytest.mark.ros

PERIODS = 30


def _loop(composed: bool, tips: np.ndarray, rest: np.ndarray):
    """Tips (k, n, 3) through the estimator and the controller, one period at a time: the
    commands and the estimates a probe received, as (stamp, array) lists."""
    with ros_context() as (ctx, executor):
        if composed:
            est, ctl = with_estimator(lambda: ControllerNode(context=ctx,
                                                             subscribe_estimates=False),
                                      lambda controller: controller.take_estimate, context=ctx)
        else:
            est, ctl = EstimatorNode(context=ctx), ControllerNode(context=ctx)
        probe = Probe(ctx)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        probe.listen(MultiDOFJointTrajectory, STATE_ESTIMATE, deep(LOOP_QOS))
        tip_pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        ref_pub = probe.create_publisher(MultiDOFJointTrajectory, GRASP_REFERENCE, REFERENCE_QOS)
        for node in (est, ctl, probe):
            executor.add_node(node)
        readers = (probe,) if composed else (probe, ctl)
        assert spin_until(executor, lambda: linked(tip_pub, est) and linked(ref_pub, ctl)
                          and linked(ctl.pub_cmd, probe) and linked(est.pub, *readers), 20.0)
        ref_pub.publish(horizon(rest, 0)[0])
        assert spin_until(executor, lambda: ctl.diag.counters['references'] == 1)
        for k, z in enumerate(tips):
            tip_pub.publish(cv.tips_to_msg(k * MS, z))
            assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) == k + 1
                              and len(probe.received[STATE_ESTIMATE]) == k + 1, 5.0)
        subscribed = {s.topic_name for s in ctl.subscriptions}
        # the start rule's counts: the estimate's readers (the probe and the controller, over DDS
        # or in-process) and the controller's writers of it, the same in both layouts
        links = {k: v for node in (est, ctl) for k, v in wiring(node).items()
                 if k.endswith(STATE_ESTIMATE)}
        assert links == {f'readers /{STATE_ESTIMATE}': '2', f'writers /{STATE_ESTIMATE}': '1'}
        commands = [cv.msg_to_torques(m, 4) for m in probe.received[TORQUE_COMMANDS]]
        estimates = [cv.msg_to_estimate(m, est.names) for m in probe.received[STATE_ESTIMATE]]
        return commands, estimates, subscribed, dict(ctl.diag.counters)


def test_composed_answers_like_separate_nodes_and_still_publishes_the_estimate():
    rest = np.repeat(SDCModel().rest_tip[None, :2], 4, 0)
    rng = np.random.default_rng(7)
    tips = np.zeros((PERIODS, 4, 3))
    tips[:, :, :2] = rest + rng.normal(scale=5e-5, size=(PERIODS, 4, 2))
    tips[:, :, 1] += np.linspace(0.0, 1e-3, PERIODS)[:, None]
    apart, apart_est, apart_subs, _ = _loop(False, tips, rest)
    together, together_est, together_subs, counters = _loop(True, tips, rest)
    assert [s for s, _ in together] == [k * MS for k in range(PERIODS)]
    for (s0, u0), (s1, u1) in zip(apart, together):
        assert s0 == s1 and np.array_equal(u0, u1)
    for (s0, x0), (s1, x1) in zip(apart_est, together_est):
        assert s0 == s1 and np.array_equal(x0, x1)
    assert '/' + STATE_ESTIMATE in apart_subs and '/' + STATE_ESTIMATE not in together_subs
    assert counters['estimates'] == counters['commands'] == PERIODS


def test_the_controller_process_runs_the_estimator_too_with_the_flag(tmp_path):
    env = dict(os.environ, ROS_DOMAIN_ID=os.environ.get('ROS_DOMAIN_ID', '0'),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    log = tmp_path / 'controller.log'
    with open(log, 'w') as out:
        proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.controller',
                                 '--with-estimator', '--ros-args', '-p', 'control_period:=0.002'],
                                env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and proc.poll() is None:
            text = log.read_text()
            if '[estimator]: 4 fingers' in text and '[controller]: model ' in text:
                break
            time.sleep(0.2)
        text = log.read_text()
        assert '[estimator]: 4 fingers' in text and 'nominal period 2 ms' in text, text
        assert '[controller]: model ' in text, text
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30.0) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_the_composed_command_line_takes_either_nodes_parameters_and_no_other():
    """A ``-p`` reaches both nodes of the process, so ``--with-estimator`` accepts the estimator's
    names beside the controller's and refuses the rest before anything starts; ``--help`` lists
    both."""
    command = [sys.executable, '-m', 'soft_gripper_sdre.nodes.controller', '--with-estimator']
    shown = subprocess.run([*command, '--help'], capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0 and 'q_pos' in shown.stdout and 'max_bridge' in shown.stdout
    refused = subprocess.run([*command, '--ros-args', '-p', 'tips_reliability:=best_effort',
                              '-p', 'max_bridg:=0.02'], capture_output=True, text=True,
                             timeout=60)
    assert refused.returncode == 2 and "unknown parameter 'max_bridg'" in refused.stderr
    assert 'Traceback' not in refused.stderr and 'tips_reliability' not in refused.stderr.split(
        '(this node has')[0]
    alone = subprocess.run([*command[:-1], '--ros-args', '-p', 'max_bridge:=0.02'],
                           capture_output=True, text=True, timeout=60)
    assert alone.returncode == 2 and "unknown parameter 'max_bridge'" in alone.stderr
