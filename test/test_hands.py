"""Two hands on one ROS domain at once: each graph in its own namespace with its own clock.

Ten node processes (two recorders, estimators, trajectory nodes, controllers and simulators) in
lockstep; the two hands run different grasps (fingers 0 and 2 close on the left, 1 and 3 on the
right), so a message of one hand taken by the other would show in the tracking as well as in the
counters. The simulators wait patiently for their commands
(:data:`~soft_gripper_sdre.tools.graph.hands.PATIENT_LOCKSTEP`): ten processes on two shared cores
can starve one for longer than the default lockstep timeout at start-up, and the test then demands
no timeout at all. Slow: tens of seconds of wall time.
"""
from __future__ import annotations

from multi_graph import DURATION, SHORT_GRASP, TARGET_PCT, worst_pct
import pytest

from soft_gripper_sdre.analysis.bag import read_bag, topic_counts
from soft_gripper_sdre.nodes.graph import RECORDED_BEFORE_START, grasp_graph
from soft_gripper_sdre.tools.graph.hands import (
    PATIENT_LOCKSTEP,
    published_and_recorded,
    run_graphs,
    trouble,
)
from soft_gripper_sdre.tools.graph.procs import ros_env
from soft_gripper_sdre.tools.judging.report import report

pytestmark = [pytest.mark.ros, pytest.mark.slow]

GRASPING = {'left_hand': [0, 2], 'right_hand': [1, 3]}


@pytest.mark.timeout(240)
def test_two_hands_on_one_domain_each_track_their_own_grasp(tmp_path):
    specs = [grasp_graph(hand, parameters={
        'recorder': {'output': str(tmp_path / hand / 'bag')},
        'simulator': {'duration': DURATION, 'seed': seed, **PATIENT_LOCKSTEP['simulator']},
        'controller': PATIENT_LOCKSTEP['controller'],
        'trajectory': {**SHORT_GRASP, 'grasp_fingers': fingers}})
        for seed, (hand, fingers) in enumerate(GRASPING.items())]
    runs = run_graphs(specs, ros_env(), tmp_path / 'logs', timeout=150.0,
                      monitor_name='hands_test_monitor')
    steps = int(round(DURATION / 1e-3))
    for run in runs:
        hand = run.spec.namespace.strip('/')
        assert all(code == 0 for code in run.exit_codes.values()), (hand, run.exit_codes)
        # no message of the other hand accepted: nothing refused, late, stale or reset, every step
        # taken on a command of this hand's controller, every command answering this simulator
        assert trouble(run) == {}, (hand, trouble(run))
        assert (run.value('simulator', 'steps') == steps
                and run.value('simulator', 'commands') == steps)
        assert run.value('controller', 'commands') in (steps, steps + 1)
        assert run.value('estimator', 'estimates') in (steps + 1, steps)
        # each loop topic has exactly one publisher in the hand's namespace, its own node's
        recorder = run.during_run['recorder']
        for topic in ('tip_positions', '/clock', *RECORDED_BEFORE_START):
            assert recorder[f'publishers {run.spec.topic(topic)}'] == '1', (hand, topic, recorder)
        counts = topic_counts(run.bag)
        assert {t for t in counts if t != '/diagnostics'} <= {
            run.spec.topic(t) for t in ('/clock', 'tip_positions', 'state_estimate',
                                        'grasp_reference', 'torque_commands', 'joint_states',
                                        'cube_pose', 'cube_contacts')}
        # the bag holds what the hand published (a recorder starved of CPU for longer than a
        # topic's 50-message history, ten processes on two cores, may lose a burst of the oldest)
        lost = {t: n - got for t, (n, got) in published_and_recorded(run).items()}
        assert all(0 <= v < 0.02 * steps for v in lost.values()), (hand, lost)
        # its own grasp, on target: the grasping fingers travel ~25 mm, the others open ~4 mm
        fingers = report(run.bag, tmp_path / hand)['fingers']
        assert worst_pct(fingers) <= TARGET_PCT, (hand, fingers)
        for i, finger in enumerate(fingers.values()):
            assert (finger['excursion_mm'] > 20) == (i in GRASPING[hand]), (hand, i, finger)
        print(f'{hand}: worst finger {worst_pct(fingers):.2f} %, '
              f'{run.value("simulator", "real_time_factor"):.2f}× '
              f'real time, loop latency p50 {run.value("simulator", "loop_latency_us_p50"):.0f} µs')
    # /diagnostics is shared, and each status names its node with the hand's namespace
    statuses = {s.name for _, msg in read_bag(runs[0].bag, ['/diagnostics'])['/diagnostics']
                for s in msg.status}
    assert {'/left_hand/simulator', '/right_hand/simulator', '/left_hand/controller',
            '/right_hand/controller'} <= statuses
