"""The excitation node's start and level over real DDS (loopback): it starts only once the driver
and the recorder hear its commands, so the recorded bag holds the settle phase training takes the
noise level from; a bag without one is refused by name. A test driver stands in for a lab's:
200 Hz, wall-stamped tips, 1 % lost, 0.05 mm noise, a spring–damper finger."""
import time

from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rclpy.node import Node
from rosutil import Probe, deep, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from spring_finger import NOISE, RATE, REST, SpringDamper

from soft_gripper_sdre.analysis.bag_dataset import (
    MIN_SETTLE_SAMPLES,
    BagDataError,
    read_recording,
    settle_estimates,
    settle_noise,
)
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.recorder import RecorderNode
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS, TORQUE_COMMANDS

pytestmark = pytest.mark.ros


class Driver(Node):
    """A driver at ``RATE`` on a wall timer: publishes the plant's tips stamped with wall time
    (1 % of them lost) and steps the plant with the newest command."""

    def __init__(self, context, plant: SpringDamper, seed: int = 0) -> None:
        super().__init__('lab_driver', context=context)
        self.plant = plant
        self.rng = np.random.default_rng(seed)
        self.u = np.zeros(2)
        self.sent = 0
        self.pub = self.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        self.create_subscription(JointState, TORQUE_COMMANDS, self._on_command, LOOP_QOS)
        self.create_timer(1.0 / RATE, self._tick)

    def _on_command(self, msg) -> None:
        self.u = cv.msg_to_torques(msg, 1)[1][0]

    def _tick(self) -> None:
        if self.rng.random() >= 0.01:
            self.pub.publish(cv.tips_to_msg(time.time_ns(), self.plant.tips()))
            self.sent += 1
        self.plant.step(self.u)


def excitation(ctx, **params):
    # tips_timeout above the default 1 s: the driver ticks in the test's own executor, which a
    # loaded machine can stall for a second or more
    base = dict(finger_names=['finger_0'], signals=['u1'], duration=1.0, settle_time=0.5,
                amplitude=0.1, tips_timeout=5.0, torque_limit=0.1)
    base.update(params)
    return ExcitationNode(context=ctx, parameter_overrides=overrides(**base))


def recorder(ctx, path):
    return RecorderNode(context=ctx, parameter_overrides=overrides(
        output=str(path), topics=['tip_positions', 'torque_commands']))


def test_the_node_waits_for_the_recorder_so_the_bag_holds_the_settle_phase(tmp_path):
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        node = excitation(ctx)                          # min_command_subscribers: 2 by default
        executor.add_node(driver)
        executor.add_node(node)
        # the driver alone: every tip is answered with zero, the run does not start
        assert spin_until(executor, lambda: node.diag.counters['tips'] >= 150, 20.0)
        assert node.start_ns is None and node.pub_cmd.get_subscription_count() == 1
        assert np.all(driver.u == 0.0) and node.diag.values['signal'].startswith('waiting for 2')
        rec = recorder(ctx, tmp_path / 'bag')           # the recorder comes late
        executor.add_node(rec)
        assert spin_until(executor, lambda: node.done, 30.0)
        assert node.exit_code == 0
        assert node.run.settle.zero_answers >= node.p['settle_samples'] == 100
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()          # (ros_context destroys only the executor's nodes)
    bag = read_recording(tmp_path / 'bag')
    rest, sigma, n = settle_noise(bag, 0)
    assert n >= 4 * MIN_SETTLE_SAMPLES
    assert sigma == pytest.approx(NOISE, rel=0.25)
    np.testing.assert_allclose(rest, REST, atol=3e-5)
    first = np.flatnonzero(np.any(bag.torques[:, 0] != 0.0, axis=1))[0]
    assert (bag.cmd_ns[first] - bag.cmd_ns[0]) / 1e9 >= 0.49


def test_a_run_started_before_the_recorder_loses_the_settle_phase_and_training_says_so(tmp_path):
    """The lab's failure: the plan ran before the recorder heard the commands (here allowed by
    min_command_subscribers 1); the bag's first command is already the signal."""
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        node = excitation(ctx, min_command_subscribers=1)
        executor.add_node(driver)
        executor.add_node(node)
        assert spin_until(executor, lambda: node.run.settle.excited, 20.0)
        assert spin_until(executor, lambda: node.diag.values.get('plan_time', '') > '0.6', 20.0)
        rec = recorder(ctx, tmp_path / 'bag')
        executor.add_node(rec)
        assert spin_until(executor, lambda: node.done, 30.0)
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()          # (ros_context destroys only the executor's nodes)
    bag = read_recording(tmp_path / 'bag', min_duration=0.2)
    assert settle_estimates(bag, 0)[1] is None          # what training took as σ = 0
    with pytest.raises(BagDataError) as info:
        settle_noise(bag, 0)
    message = str(info.value)
    assert message.startswith(f'bag {tmp_path / "bag"}: finger_0: no settle phase of zero torque '
                              'before the first non-zero torque')
    assert f'{MIN_SETTLE_SAMPLES} needed' in message
    assert "record with the excitation node's settle_time > 0, or give --meas-std" in message


def test_too_few_command_subscribers_within_startup_timeout_is_a_fault():
    with ros_context() as (ctx, executor):
        node = excitation(ctx, startup_timeout=1.0, min_command_subscribers=3)
        probe = Probe(ctx)
        pub = probe.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        executor.add_node(node)
        executor.add_node(probe)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0)
        stamp = [0]

        def tick() -> bool:
            """One tip message per poll until the node gives up (whenever the machine lets it)."""
            stamp[0] += 5_000_000
            pub.publish(cv.tips_to_msg(stamp[0], REST[None, :]))
            return node.done
        assert spin_until(executor, tick, 20.0)
        assert spin_until(executor, lambda: len(probe.received[TORQUE_COMMANDS]) > 0, 5.0)
        assert node.exit_code == 1 and node.start_ns is None
        assert ('torque_commands has 1 matched subscriber(s) after startup_timeout (1 s); '
                'min_command_subscribers is 3') in node.diag.message
        got = [cv.msg_to_torques(m, 1)[1] for m in probe.received[TORQUE_COMMANDS]]
        assert all(np.all(u == 0.0) for u in got)


def test_level_auto_probes_the_finger_then_plays_the_signal_near_the_target(tmp_path):
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        node = excitation(ctx, amplitude=1.0, level='auto', max_excursion=0.02, signals=['x1'],
                          duration=3.0, min_command_subscribers=2)
        rec = recorder(ctx, tmp_path / 'bag')
        for n in (driver, node, rec):
            executor.add_node(n)
        assert spin_until(executor, lambda: node.done, 90.0)
        assert node.exit_code == 0, node.diag.message
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()          # (ros_context destroys only the executor's nodes)
    search = node.run.search
    assert search.done and len(search.probes) >= 2
    assert node.diag.values['amplitude'] == f'{search.amplitude:.6g}'
    assert float(node.diag.values['clip_share']) == 0.0
    bag = read_recording(tmp_path / 'bag')
    rest, sigma, n = settle_noise(bag, 0)             # the settle phase before the first probe
    assert n >= 4 * MIN_SETTLE_SAMPLES and sigma == pytest.approx(NOISE, rel=0.25)
    first = np.flatnonzero(np.any(bag.torques[:, 0] != 0.0, axis=1))[0]
    assert (bag.cmd_ns[first] - bag.cmd_ns[0]) / 1e9 >= 0.49
    # the signal's stretch of the bag: from the plan's first signal sample on
    t = (bag.tip_ns - bag.cmd_ns[0]) / 1e9
    start = search.end + 0.5
    played = t >= start
    excursion = np.linalg.norm(bag.tips[played, 0] - rest, axis=-1).max()
    goal = 0.5 * 0.02
    assert goal / 1.5 <= excursion <= goal * 1.5, (search.probes, search.amplitude, excursion)
    # the commands: probes at rising amplitude, then the signal at the chosen one, never clipped
    cmd_t = (bag.cmd_ns - bag.cmd_ns[0]) / 1e9
    assert np.abs(bag.torques[cmd_t < search.end]).max() > 0
    assert np.abs(bag.torques).max() < 0.1


@pytest.mark.parametrize('params, message', [
    (dict(amplitude=0.0), "parameter 'amplitude'"),
    (dict(amplitude=float('nan')), "parameter 'amplitude'"),
    (dict(level='manual'), "parameter 'level'"),
    (dict(level='auto', level_target=0.0, max_excursion=0.02), "parameter 'level_target'"),
    (dict(level='auto', level_start=0.0, max_excursion=0.02), "parameter 'level_start'"),
    (dict(level='auto', level_probe_time=0.0, max_excursion=0.02), "parameter 'level_probe_time'"),
    (dict(min_command_subscribers=-1), "parameter 'min_command_subscribers'"),
    (dict(level='auto'), "parameter 'max_excursion': level auto needs max_excursion > 0"),
    (dict(level='auto', max_excursion=0.02, settle_time=0.0),
     "parameter 'settle_time': level auto needs settle_time > 0"),
    (dict(level='auto', max_excursion=0.02, amplitude=2.0),
     "parameter 'amplitude': 2 with level auto, which chooses the amplitude itself"),
])
def test_bad_level_and_start_parameters_stop_the_node_at_start_up(params, message):
    with ros_context() as (ctx, _executor):
        with pytest.raises(ParameterError) as info:
            excitation(ctx, **params)
        assert message in str(info.value)
