"""Where the excitation's limit comes from (nodes/excitation.py, "Limit"; nodes/driver_limits.py),
over real DDS with real nodes: taken from the driver's bounds on /diagnostics when none is given
(plant_driver's ± torques, its one-chamber and three-tendon presets, the hand's simulator node),
a given limit winning over the driver's, a given limit wider than the driver's refused, no driver
a fault at driver_bounds_timeout naming what to give, a bounds report that does not read ignored
with a warning, and the new parameters' bad values refused (exit 2)."""
import os
import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
import pytest
from rosutil import Probe, deep, drain, overrides, ros_context, spin_until
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.driver_limits import reported_bounds
from soft_gripper_sdre.nodes.excitation import ExcitationNode
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.nodes.plant_driver import PlantDriverNode
from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, LOOP_QOS, STREAM_QOS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.excitation import ExcitationPlan
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.sim.signal_specs import builtin_signal

pytestmark = pytest.mark.ros

NAMES = ['index', 'thumb']
#: the presets' bounds (sim/plants/presets.py), as plant_driver reports them
PRESETS = {'tendon3': (200.0, InputBounds([-0.02, -0.02], [0.02, 0.02])),
           'pneumatic1': (100.0, InputBounds([0.0], [60000.0])),
           'trunk3': (250.0, InputBounds([0.0] * 3, [4.0] * 3))}


def driver(ctx, plant: str) -> PlantDriverNode:
    return PlantDriverNode(context=ctx, parameter_overrides=overrides(
        finger_names=NAMES, plant=plant, rate=PRESETS[plant][0], command_timeout=0.5))


def excitation(ctx, **params) -> ExcitationNode:
    base = dict(finger_names=NAMES, signals=['x1'], duration=1.0, settle_time=0.3,
                settle_samples=10, min_command_subscribers=1, tips_reliability='best_effort')
    return ExcitationNode(context=ctx, parameter_overrides=overrides(**(base | params)))


class StandIn(Probe):
    """A driver's /diagnostics only: publishes the statuses the test gives, under its name."""

    def __init__(self, ctx, name: str = 'lab_driver', namespace: str = '') -> None:
        super().__init__(ctx, name)
        if namespace:
            self._full = f'/{namespace}/{name}'
        else:
            self._full = self.get_fully_qualified_name()
        self.pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)

    def report(self, **values) -> None:
        status = DiagnosticStatus(name=self._full, level=DiagnosticStatus.OK, message='ok')
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        self.pub.publish(DiagnosticArray(status=[status]))


@pytest.mark.parametrize('plant', ['tendon3', 'pneumatic1', 'trunk3'])
def test_without_a_limit_the_excitation_plays_within_the_drivers_bounds(plant, capfd):
    """No torque_limit, no input bounds: the driver's reported bounds are the limit (the ±
    torques the hand's way, one chamber, three tendons), which /diagnostics and the start-up line
    say; the run ends with nothing clipped."""
    bounds = PRESETS[plant][1]
    with ros_context('events') as (ctx, executor):
        drv = driver(ctx, plant)
        executor.add_node(drv)
        node = excitation(ctx)
        executor.add_node(node)
        assert node.run is None and node.diag.values['limit_source'] == 'driver'
        assert node.sub_tips is None                   # not listening before it has a limit
        assert spin_until(executor, lambda: node.done, 40.0), node.diag.values
        drain(executor, 1.5)                           # the driver's last report
        assert node.exit_code == 0, node.diag.message
        assert node.limit_driver == drv.get_fully_qualified_name()
        assert node.diag.values['limit_source'] == 'driver'
        assert node.diag.values['limit'] == str(bounds)
        assert node.m == bounds.m
        if plant == 'tendon3':                         # the hand's path: ±torque_limit on two
            assert node.run.plan.map is None and node.run.plan.torque_limit == 0.02
        else:
            assert node.run.plan.map.bounds == bounds
        assert drv.diag.counters.get('clipped_commands', 0) == 0
        assert drv.diag.counters.get('bad_commands', 0) == 0
        # the 1.3 s run answers the driver's tips at its rate (100 to 250 Hz); beside two busy
        # test workers the starved 100 Hz driver heard 34 commands
        assert drv.diag.counters['commands'] > 20
    log = capfd.readouterr().err
    assert f'within {bounds} (limit_source driver: the bounds of /plant_driver)' in log or (
        '|u| <= 0.02 N·m (limit_source driver: the bounds of /plant_driver)' in log), log


def test_the_hands_simulator_reports_its_limit_and_the_excitation_plays_the_same_torques():
    """The simulator node in lockstep reports ±torque_limit (0.1 N·m) as its bounds; an
    excitation without a limit takes them and answers each tips with exactly the torque of the
    plan at 0.1 N·m, as with torque_limit 0.1 given."""
    from soft_gripper_sdre.nodes.simulator import SimulatorNode
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=overrides(
            scene='finger', finger_names=['finger_0'], hand_fingers=[0], startup_timeout=20.0))
        assert reported_bounds(sim.diag.values['bounds']) == InputBounds.symmetric(0.1, 2)
        probe = Probe(ctx)
        probe.listen(JointState, TORQUE_COMMANDS, deep(LOOP_QOS))
        node = ExcitationNode(context=ctx, parameter_overrides=overrides(
            finger_names=['finger_0'], signals=['u1'], duration=0.3, settle_time=0.05,
            settle_samples=0, min_command_subscribers=1, amplitude=3.0))
        for n in (sim, probe, node):
            executor.add_node(n)
        assert spin_until(executor, lambda: node.done, 60.0), node.diag.values
        drain(executor, 0.3)
        assert node.exit_code == 0 and node.diag.values['limit_source'] == 'driver'
        assert node.run.plan.map is None and node.run.plan.torque_limit == 0.1
        got = [cv.msg_to_torques(m, 1) for m in probe.received[TORQUE_COMMANDS]]
    plan = ExcitationPlan([builtin_signal('u1', 0.3)], 0.05, 1, torque_limit=0.1, amplitude=3.0)
    start = node.start_ns
    played = [(s, u) for s, u in got if s >= start][:-1]          # the last is the final zero
    assert len(played) > 200
    for s, u in played:
        np.testing.assert_array_equal(u, plan.torques((s - start) / 1e9))
    assert np.abs(np.concatenate([u for _, u in played])).max() == 0.1     # at the clip


def test_a_given_limit_wins_over_the_drivers_wider_one(capfd):
    with ros_context('events') as (ctx, executor):
        drv = driver(ctx, 'tendon3')
        node = excitation(ctx, torque_limit=0.01, signals=['u1'])
        executor.add_node(drv)
        executor.add_node(node)
        assert node.run is not None and node.diag.values['limit_source'] == 'parameter'
        assert spin_until(executor, lambda: node.done, 40.0)
        drain(executor, 1.5)
        assert node.exit_code == 0 and node.run.plan.torque_limit == 0.01
        assert node.driver_limits.reported and not node.driver_limits.refused
        assert node.diag.values['driver_bounds'].startswith('ax0 [-0.02, 0.02]')
        assert drv.diag.counters.get('clipped_commands', 0) == 0
    assert '|u| <= 0.01 N·m (limit_source parameter)' in capfd.readouterr().err


@pytest.mark.parametrize('given, named', [
    (dict(torque_limit=0.1), ['ax0 [-0.1, 0.1]', 'ax0 [-0.02, 0.02]', 'torque_limit']),
    (dict(input_lower=[0.0], input_upper=[0.02]),
     ['takes 2 input(s)', 'sends 1', 'input_lower / input_upper']),
])
def test_a_given_limit_the_driver_does_not_take_is_refused_naming_both(given, named):
    """The driver would clip what is sent (or reject it): the node stops as a fault, exit 1,
    naming both limits and the parameter; with a settle phase longer than the driver's first
    report it never sent a non-zero command, so the driver clipped nothing."""
    with ros_context('events') as (ctx, executor):
        drv = driver(ctx, 'tendon3')
        node = excitation(ctx, settle_time=3.0, **given)
        executor.add_node(drv)
        executor.add_node(node)
        assert spin_until(executor, lambda: node.done, 20.0)
        drain(executor, 1.2)
        assert node.exit_code == 1 and node.driver_limits.refused
        for text in named:
            assert text in node.diag.message, node.diag.message
        assert drv.diag.counters.get('clipped_commands', 0) == 0


def test_no_driver_is_a_fault_at_driver_bounds_timeout_naming_what_to_give():
    with ros_context() as (ctx, executor):
        node = excitation(ctx, driver_bounds_timeout=1.0)
        executor.add_node(node)
        assert node.diag.values['signal'] == "waiting for the driver's bounds"
        assert spin_until(executor, lambda: node.done, 10.0)
        assert node.exit_code == 1 and node.run is None
        for text in ('no driver reported its bounds', 'driver_bounds_timeout (1 s)',
                     'torque_limit', 'input_lower / input_upper'):
            assert text in node.diag.message, node.diag.message


def test_the_wait_for_the_driver_logs_what_it_waits_for_and_exits_1():
    """As a process: the start-up line, a line every 5 s while it waits, then the error and exit
    status 1 at driver_bounds_timeout."""
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.excitation',
                           '--ros-args', '-p', 'driver_bounds_timeout:=5.5',
                           '-r', '__ns:=/nobody_here'],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ))
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "waiting for the driver's bounds on /diagnostics (a node in the namespace " \
           "/nobody_here reporting 'bounds'" in out
    assert "still waiting for the driver's bounds on /diagnostics after 5 s" in out
    assert 'give torque_limit (± torques on two inputs) or input_lower / input_upper' in out
    assert 'within driver_bounds_timeout (5.5 s)' in out and 'Traceback' not in out


def test_a_bounds_report_that_does_not_read_is_ignored_with_a_warning_then_good_ones_taken():
    with ros_context() as (ctx, executor):
        other = StandIn(ctx, 'other_driver', namespace='elsewhere')
        lab = StandIn(ctx)
        node = excitation(ctx, driver_bounds_timeout=0.0)
        for n in (other, lab, node):
            executor.add_node(n)
        assert spin_until(executor, lambda: other.pub.get_subscription_count() > 0
                          and lab.pub.get_subscription_count() > 0, 10.0)
        other.report(bounds='ax0 [-0.5, 0.5], ax1 [-0.5, 0.5]')    # not this namespace's
        for bad in ('ax0 [a, 1]', 'ax0 [1, 0]', 'ax0 [0, 1], ax1 [0, 1]; ax0 [0, 1]',
                    'ax0 [nan, 1]', 'ax0 [0, 1], ax1 [0, 1], ax2 [0, 1], ax3 [0, 1], ax4 [0, 1]'):
            lab.report(bounds=bad, clipped_commands='x')
            drain(executor, 0.1)
            assert node.run is None and not node.done
            assert node.diag.values['driver_bounds_ignored'].endswith(repr(bad))
        assert len(node.driver_limits.malformed) == 5
        lab.report(bounds='ax0 [0, 60000]; ax0 [0, 50000]')
        assert spin_until(executor, lambda: node.run is not None, 5.0)
        assert node.m == 1 and node.run.plan.map.bounds == InputBounds([0.0], [50000.0])
        assert node.limit_driver == lab.get_fully_qualified_name()
        assert node.sub_tips is not None and not node.done


def test_a_driver_clipping_commands_is_warned_about_with_its_count():
    with ros_context() as (ctx, executor):
        lab = StandIn(ctx)
        node = excitation(ctx, torque_limit=0.02)
        executor.add_node(lab)
        executor.add_node(node)
        assert spin_until(executor, lambda: lab.pub.get_subscription_count() > 0, 10.0)
        lab.report(bounds='ax0 [-0.02, 0.02], ax1 [-0.02, 0.02]', clipped_commands=3)
        drain(executor, 0.2)
        assert 'driver_clipped' not in node.diag.values          # the count before the run
        lab.report(bounds='ax0 [-0.02, 0.02], ax1 [-0.02, 0.02]', clipped_commands=7)
        assert spin_until(executor, lambda: node.diag.values.get('driver_clipped') == '7', 5.0)
        assert not node.driver_limits.refused and not node.done


def test_a_spec_file_for_other_inputs_than_the_drivers_ends_the_node_with_status_2(tmp_path):
    path = tmp_path / 's.yaml'
    path.write_text('signals:\n  mine: {kind: chirp, duration: 1.0, '
                    'ax2: {amplitude: 0.5, f0: 1.0, f1: 2.0}}\n')
    with ros_context() as (ctx, executor):
        lab = StandIn(ctx)
        node = excitation(ctx, signals=['mine'], spec_file=str(path))   # for 3 inputs or more
        executor.add_node(lab)
        executor.add_node(node)
        assert spin_until(executor, lambda: lab.pub.get_subscription_count() > 0, 10.0)
        lab.report(bounds='ax0 [0, 60000]')
        assert spin_until(executor, lambda: node.done, 5.0)
        assert node.exit_code == 2 and node.run is None
        assert 'bad parameter' in node.diag.message and 'mine' in node.diag.message


@pytest.mark.parametrize('params, named', [
    (dict(driver_bounds_timeout=-1.0), 'driver_bounds_timeout'),
    (dict(driver_bounds_timeout=float('nan')), 'driver_bounds_timeout'),
    (dict(torque_limit=-0.1), 'torque_limit'),
    (dict(torque_limit=2.0), 'torque_limit'),
])
def test_bad_limit_parameters_are_refused_naming_them(params, named):
    with ros_context() as (ctx, _):
        with pytest.raises(ParameterError, match=named):
            excitation(ctx, **params)


@pytest.mark.parametrize('arg, named', [
    ('driver_bounds_timeout:=-1.0', 'driver_bounds_timeout'),
    ('driver_bounds_timeout:=soon', 'driver_bounds_timeout'),
    ('torque_limit:=-0.02', 'torque_limit'),
])
def test_bad_limit_values_exit_2_naming_them_without_a_traceback(arg, named, tmp_path):
    out = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.excitation',
                          '--ros-args', '-p', arg], capture_output=True, text=True, timeout=60,
                         cwd=tmp_path, env=dict(os.environ))
    assert out.returncode == 2, out.stderr
    assert named in out.stderr and 'Traceback' not in out.stderr
    assert not list(tmp_path.iterdir())            # nothing written


def test_a_spec_file_in_the_drivers_units_waits_for_the_drivers_bounds(tmp_path):
    """A one-chamber spec in Pa (far above any torque) is not refused before the driver's bounds
    are known, and plays within them once they are."""
    path = tmp_path / 'p.yaml'
    path.write_text('signals:\n  puff: {kind: chirp, duration: 1.0, '
                    'ax0: {amplitude: 20000.0, offset: 30000.0, f0: 0.5, f1: 2.0}}\n')
    with ros_context() as (ctx, executor):
        lab = StandIn(ctx)
        node = excitation(ctx, signals=['puff'], spec_file=str(path))
        executor.add_node(lab)
        executor.add_node(node)
        assert spin_until(executor, lambda: lab.pub.get_subscription_count() > 0, 10.0)
        lab.report(bounds='ax0 [0, 60000]; ax0 [0, 60000]')
        assert spin_until(executor, lambda: node.run is not None, 5.0)
        assert not node.done and node.m == 1
        assert node.run.plan.map.bounds == InputBounds([0.0], [60000.0])


def test_driver_bounds_timeout_0_waits_without_end_until_a_driver_reports():
    with ros_context() as (ctx, executor):
        lab = StandIn(ctx)
        node = excitation(ctx, driver_bounds_timeout=0.0)
        node._waiting_since -= 3600.0                 # as if it had waited an hour already
        executor.add_node(lab)
        executor.add_node(node)
        drain(executor, 0.5)
        assert not node.done and node.run is None and node.exit_code == 0
        assert spin_until(executor, lambda: lab.pub.get_subscription_count() > 0, 10.0)
        lab.report(bounds='ax0 [-0.05, 0.05], ax1 [-0.05, 0.05]')
        assert spin_until(executor, lambda: node.run is not None, 5.0)
        assert node.run.plan.map is None and node.run.plan.torque_limit == 0.05
        assert node.diag.values['limit'] == 'ax0 [-0.05, 0.05], ax1 [-0.05, 0.05]'
