"""The start rule of the grasp graph (nodes/graph.readiness_problem): as plain data, and on real
processes started all at once, as ``ros2 launch`` starts them (no supervisor waits for anything).

With the rule the simulator steps only once every node has reported and every writer and reader
of the graph has matched its peers, so two runs of one grasp give the same torques bit for bit,
no period of the start times out, and the recorder's bag holds every message from t = 0. A node
that never gets ready makes the simulator give up within its ``startup_timeout`` with exit status
1, naming what it waited for.
"""
from __future__ import annotations

from pathlib import Path
import time

import numpy as np
import pytest

from soft_gripper_sdre.analysis.bag import read_bag
from soft_gripper_sdre.nodes.graph import (
    GRASP_NODES,
    READS,
    WRITES,
    grasp_graph,
    readiness_problem,
    wiring_key,
)
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env

RUN = 0.3           # s of sim time per run


def _wired(spec) -> dict[str, dict[str, str]]:
    """Each node's report with every count the rule asks for met exactly."""
    reports = {}
    for node in spec.names:
        others = [n for n in spec.names if n != node]
        values = {}
        for role, mine, theirs in (('readers', WRITES, READS), ('writers', READS, WRITES)):
            for name in mine[node]:
                need = sum(name in theirs[o] for o in others)
                values[wiring_key(role, spec.topic(name))] = str(need)
        reports[node] = values
    return reports


def test_a_fully_wired_graph_is_ready_in_any_namespace():
    for spec in (grasp_graph(), grasp_graph('left_hand'), grasp_graph(record=False)):
        assert readiness_problem(spec.names, _wired(spec), spec.topic) is None


def test_the_rule_names_what_is_missing():
    spec = grasp_graph('left_hand')
    reports = _wired(spec)
    reports['controller'] = None
    reports['estimator'][wiring_key('readers', '/left_hand/state_estimate')] = '1'
    reports['simulator'][wiring_key('readers', '/left_hand/clock')] = '1'
    problem = readiness_problem(spec.names, reports, spec.topic)
    assert 'nothing heard from the controller yet' in problem
    # the estimator's writer must have matched the controller and the recorder
    assert 'the estimator has matched 1 of 2 readers of /left_hand/state_estimate' in problem
    # the recorder and the trajectory node read the hand's own clock
    assert 'the simulator has matched 1 of 2 readers of /left_hand/clock' in problem


def test_without_a_recorder_the_streams_need_no_reader():
    spec = grasp_graph(record=False)
    reports = _wired(spec)
    for name in ('joint_states', 'cube_pose', 'cube_contacts'):
        assert reports['simulator'][wiring_key('readers', f'/{name}')] == '0'
    assert reports['controller'][wiring_key('readers', '/torque_commands')] == '1'
    assert readiness_problem(spec.names, reports, spec.topic) is None


def test_a_graph_without_a_node_does_not_wait_for_it():
    spec = grasp_graph().without('recorder')
    assert spec.node('simulator').parameters['wait_for_nodes'] == 'estimator,trajectory,controller'
    alone = grasp_graph().without('recorder', 'estimator', 'trajectory', 'controller')
    assert 'wait_for_nodes' not in alone.node('simulator').parameters


def test_every_written_topic_has_a_reader_in_the_graph_and_the_recorder_reads_them_all():
    written = {t for node in GRASP_NODES for t in WRITES[node]}
    assert set(READS['recorder']) == written
    assert written - set(READS['recorder']) == set()
    for node in GRASP_NODES:
        if node != 'recorder':
            assert set(READS[node]) <= written


def _run_all_at_once(spec, env, log_dir: Path, timeout: float = 120.0) -> dict[str, int]:
    """Start every node of ``spec`` at once, the simulator first (its readiness rule has to hold
    it back), and wait for the simulator; returns the exit codes."""
    with Graph(env, log_dir) as graph:
        for node in (spec.node('simulator'), *[n for n in spec.nodes if n.name != 'simulator']):
            graph.start_node(node)
        code = graph.wait('simulator', timeout)
        assert code == 0, (code, graph.procs['simulator'].log_tail())
        return graph.stop_all()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(400)
def test_two_runs_started_at_once_give_the_same_torques_and_bags_from_t_0(tmp_path):
    env = ros_env()
    monitor = DiagnosticsMonitor(env, 'readiness_test_monitor')
    torques, first = [], []
    try:
        for run in range(2):
            bag = tmp_path / f'bag{run}'
            spec = grasp_graph(parameters={'recorder': {'output': str(bag)},
                                           'simulator': {'duration': RUN,
                                                         # monitor, recorder
                                                         'min_diagnostics_subscribers': 2}})
            codes = _run_all_at_once(spec, env, tmp_path / f'logs{run}')
            assert all(c == 0 for c in codes.values()), codes
            monitor.poll()
            sim = monitor.values['simulator']
            steps = int(round(RUN / 1e-3))
            assert int(sim['steps']) == steps and int(sim.get('timeouts', 0)) == 0, sim
            topics = ('/torque_commands', '/tip_positions', '/state_estimate', '/clock',
                      '/joint_states')
            msgs = read_bag(bag, [*topics, '/grasp_reference'])
            assert len(msgs['/grasp_reference']) == 1
            # every message from t = 0: the whole loop, the clock and the streams
            for topic in topics:
                stamp = _stamp(msgs[topic][0][1])
                assert stamp == 0, (topic, stamp)
            assert len(msgs['/torque_commands']) in (steps, steps + 1)
            assert len(msgs['/tip_positions']) == steps + 1
            torques.append(np.array([m.effort for _, m in msgs['/torque_commands']]))
            first.append(float(monitor.values['simulator']['first_command_after_tips_ms']))
    finally:
        monitor.close()
    a, b = torques
    assert a.shape == b.shape and np.array_equal(a, b)
    # the first period is answered at once, not after a lockstep timeout (0.5 s)
    assert max(first) < 400.0, first


def _stamp(msg) -> int:
    stamp = msg.clock if hasattr(msg, 'clock') else msg.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_a_node_that_never_gets_ready_makes_the_simulator_give_up_naming_it(tmp_path):
    """The controller fails at start-up (a corrupt model, exit 2): the simulator waits its
    startup_timeout, takes no step, and exits with status 1 naming the silent controller."""
    bad = tmp_path / 'model.pt'
    bad.write_text('not a checkpoint')
    spec = grasp_graph(record=False, parameters={
        'controller': {'model_path': str(bad)},
        'simulator': {'duration': RUN, 'startup_timeout': 3.0}})
    with Graph(ros_env(), tmp_path / 'logs') as graph:
        for node in spec.nodes:
            graph.start_node(node)
        start = time.monotonic()
        code = graph.procs['simulator'].popen.wait(60)
        waited = time.monotonic() - start
        controller = graph.procs['controller'].popen.wait(30)
        log = graph.procs['simulator'].log_tail()
    assert controller == 2
    assert code == 1 and waited < 30, (code, waited)
    assert 'the graph was not ready within startup_timeout (3 s)' in log, log
    assert 'nothing heard from the controller yet' in log, log


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_the_simulators_own_readiness_reader_does_not_count_as_a_diagnostics_reader(tmp_path):
    """The simulator reads /diagnostics itself while it waits for the graph; that reader must not
    stand in for the monitor ``min_diagnostics_subscribers`` asks for (a short run would end before
    the monitor matched and its final counters would be lost). No other reader: it gives up."""
    spec = grasp_graph(record=False, parameters={
        'simulator': {'duration': RUN, 'startup_timeout': 3.0, 'min_diagnostics_subscribers': 1}})
    with Graph(ros_env(), tmp_path / 'logs') as graph:
        for node in spec.nodes:
            graph.start_node(node)
        code = graph.procs['simulator'].popen.wait(60)
        log = graph.procs['simulator'].log_tail()
    assert code == 1, (code, log)
    assert '0 of 1 /diagnostics readers' in log, log
