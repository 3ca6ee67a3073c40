"""Start the driver, the recorder and the excitation node in any order: every bag holds its
settle phase (the excitation waits for the recorder's report of both topics), over real DDS.

A bag of a run that never started is removed when the recorder is told which topic the run
writes (``discard_without``), so the same output can be given again.
"""
import random
import time

from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from rclpy.node import Node
from rosutil import overrides, ros_context, spin_until
from sensor_msgs.msg import JointState
from spring_finger import RATE, SpringDamper

from soft_gripper_sdre.analysis.bag_dataset import read_recording, settle_noise
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.recorder import RecorderNode
from soft_gripper_sdre.nodes.topics import LOOP_QOS, TIP_POSITIONS, TORQUE_COMMANDS

pytestmark = pytest.mark.ros


class Driver(Node):
    """A lab's driver at ``RATE`` on a wall timer: the spring-damper finger's tips stamped with
    wall time (1 % of them lost), the plant stepped with the newest command."""

    def __init__(self, context, plant: SpringDamper, seed: int = 0) -> None:
        super().__init__('lab_driver', context=context)
        self.plant = plant
        self.rng = np.random.default_rng(seed)
        self.u = np.zeros(2)
        self.pub = self.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        self.create_subscription(JointState, TORQUE_COMMANDS, self._on_command, LOOP_QOS)
        self.create_timer(1.0 / RATE, self._tick)

    def _on_command(self, msg) -> None:
        self.u = cv.msg_to_torques(msg, 1)[1][0]

    def _tick(self) -> None:
        if self.rng.random() >= 0.01:
            self.pub.publish(cv.tips_to_msg(time.time_ns(), self.plant.tips()))
        self.plant.step(self.u)


SETTLE_SAMPLES = 60
NODES = ('driver', 'recorder', 'excitation')


def build(name: str, ctx, bag, seed: int):
    if name == 'driver':
        return Driver(ctx, SpringDamper(), seed)
    if name == 'recorder':
        return RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(bag), topics=['tip_positions', 'torque_commands'],
            discard_without='torque_commands'))
    return ExcitationNode(context=ctx, parameter_overrides=overrides(
        finger_names=['finger_0'], signals=['u1'], torque_limit=0.1, duration=1.0, settle_time=0.2,
        settle_samples=SETTLE_SAMPLES, amplitude=0.1, tips_timeout=5.0))


def record_once(tmp_path, rng: random.Random, k: int):
    """One recording with the nodes started in a random order with random delays; the bag."""
    bag = tmp_path / f'bag{k}'
    order = rng.sample(NODES, 3)
    with ros_context() as (ctx, executor):
        nodes = {}
        for name in order:
            spin_until(executor, lambda: False, rng.uniform(0.0, 0.4))
            nodes[name] = build(name, ctx, bag, k)
            executor.add_node(nodes[name])
        exc, rec = nodes['excitation'], nodes['recorder']
        assert spin_until(executor, lambda: exc.done, 30.0), (order, exc.diag.values)
        assert exc.exit_code == 0, (order, exc.diag.message)
        sent = exc.diag.counters['commands']
        spin_until(executor, lambda: rec.counts['/torque_commands'] >= sent, 5.0)
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()
    return order, read_recording(bag)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_twenty_recordings_started_in_random_orders_all_hold_their_settle_phase(tmp_path):
    rng = random.Random(20)
    for k in range(20):
        order, rec = record_once(tmp_path, rng, k)
        _, _, n = settle_noise(rec, 0)            # raises for a bag without a settle phase
        assert n >= SETTLE_SAMPLES, (k, order, n)
        first = np.flatnonzero(np.any(rec.torques[:, 0] != 0.0, axis=1))
        assert first.size, (k, order)


@pytest.mark.timeout(120)
def test_three_recordings_in_random_orders_hold_their_settle_phase(tmp_path):
    rng = random.Random(3)
    for k in range(3):
        order, rec = record_once(tmp_path, rng, k)
        assert settle_noise(rec, 0)[2] >= SETTLE_SAMPLES, (k, order)


@pytest.mark.timeout(60)
def test_the_run_waits_for_the_recorders_report_and_fails_naming_it(tmp_path):
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        exc = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=['finger_0'], signals=['u1'], torque_limit=0.1, duration=0.3,
            startup_timeout=1.5, min_command_subscribers=2, recorder_node='bag_writer'))
        # a recorder of another name: its commands reader counts, its report is not the one
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(tmp_path / 'bag'), topics=['tip_positions', 'torque_commands']))
        for node in (driver, exc, rec):
            executor.add_node(node)
        assert spin_until(executor, lambda: exc.done, 20.0)
        assert exc.start_ns is None and exc.exit_code == 1
        assert 'the recorder /bag_writer to receive' in exc.diag.message
        assert exc.diag.counters['commands'] == 0 and np.all(driver.u == 0.0)
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()


def test_a_bag_without_the_runs_commands_is_removed_and_the_output_free_again(tmp_path):
    bag = tmp_path / 'bag'
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(bag), topics=['tip_positions', 'torque_commands'],
            discard_without='torque_commands'))
        executor.add_node(driver)
        executor.add_node(rec)
        assert spin_until(executor, lambda: rec.counts['/tip_positions'] > 20, 10.0)
        assert bag.exists()
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()
        assert not bag.exists()
        again = RecorderNode(context=ctx, parameter_overrides=overrides(     # the same output
            output=str(bag), topics=['tip_positions', 'torque_commands']))
        again.close()                       # without discard_without: kept, tips or not
        again.destroy_node()
        assert (bag / 'metadata.yaml').exists()


@pytest.mark.parametrize('params, named', [
    (dict(recorder_node='/recorder'), 'recorder_node'),
    (dict(recorder_node='9r'), 'recorder_node'),
])
def test_bad_recorder_node_is_refused_naming_it(params, named):
    with ros_context() as (ctx, _):
        with pytest.raises(ParameterError, match=named):
            ExcitationNode(context=ctx, parameter_overrides=overrides(**params))


def test_bad_discard_without_is_refused_naming_it(tmp_path):
    with ros_context() as (ctx, _):
        with pytest.raises(ParameterError, match='discard_without'):
            RecorderNode(context=ctx, parameter_overrides=overrides(
                output=str(tmp_path / 'bag'), discard_without='not a topic!'))
        assert not (tmp_path / 'bag').exists()


def test_the_first_message_of_each_topic_is_reported_at_once_and_kept_out_of_its_own_bag(tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from rosutil import Probe, deep

    from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

    bag = tmp_path / 'bag'
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx, parameter_overrides=overrides(
            output=str(bag), topics=['tip_positions', 'torque_commands', '/diagnostics']))
        probe = Probe(ctx)
        reports = probe.listen(DiagnosticArray, DIAGNOSTICS, deep(STREAM_QOS))
        executor.add_node(rec)
        executor.add_node(probe)
        assert spin_until(executor, lambda: reports.get_publisher_count() > 0
                          and rec._subs['/diagnostics'].get_publisher_count() > 0, 10.0)
        got = probe.received[DIAGNOSTICS]
        driver = Driver(ctx, SpringDamper())
        executor.add_node(driver)
        marked = lambda: [kv.value for m in got for s in m.status if s.name == '/recorder'  # noqa
                          for kv in s.values if kv.key == 'report']
        assert spin_until(executor, lambda: marked() == ['first /tip_positions'], 0.5), marked()
        spin_until(executor, lambda: False, 1.2)        # a 1 Hz report of its own too
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()
    with Reader(bag) as reader:
        own = [deserialize_message(raw, DiagnosticArray).status[0]
               for conn, _, raw in reader.messages() if conn.topic == '/diagnostics']
    own = [s for s in own if s.name == '/recorder']
    assert own and not [s for s in own if any(kv.key == 'report' for kv in s.values)]


@pytest.mark.timeout(60)
def test_timer_timing_sends_zero_on_its_timer_while_it_waits_for_the_recorder(tmp_path):
    bag = tmp_path / 'bag'
    with ros_context() as (ctx, executor):
        driver = Driver(ctx, SpringDamper())
        exc = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=['finger_0'], signals=['u1'], torque_limit=0.1, duration=1.0,
            settle_time=0.2, settle_samples=SETTLE_SAMPLES, amplitude=0.1, tips_timeout=5.0,
            timing='timer', period=0.005))
        for node in (driver, exc):
            executor.add_node(node)
        assert spin_until(executor, lambda: exc.diag.counters['tips'] > 20, 10.0)
        spin_until(executor, lambda: False, 0.3)
        assert exc.start_ns is None and 'waiting for 2' in exc.diag.values['signal']
        rec = build('recorder', ctx, bag, 0)
        executor.add_node(rec)
        assert spin_until(executor, lambda: exc.start_ns is not None, 10.0), exc.diag.values
        assert rec.counts['/torque_commands'] > 0           # the zeros sent while it waited
        assert spin_until(executor, lambda: exc.done, 20.0) and exc.exit_code == 0
        spin_until(executor, lambda: False, 0.2)
        executor.remove_node(rec)
        rec.close()
        rec.destroy_node()
    assert settle_noise(read_recording(bag), 0)[2] >= SETTLE_SAMPLES
