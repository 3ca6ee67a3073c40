"""The deployment benchmark measures what it claims: a driver process over DDS with the real
estimator, trajectory and controller processes, figures from the driver and /proc; and the floor
rows' arithmetic."""
import os

import numpy as np
import pytest

from soft_gripper_sdre.tools.benchmarks.bench import floor_rows
from soft_gripper_sdre.tools.benchmarks.bench_deploy import (
    describe,
    driver_prefix,
    loop_specs,
    main,
    replay_tips,
    run_deploy,
    summary,
    variant_settings,
)
from soft_gripper_sdre.tools.benchmarks.deploy_driver import slow_ticks

# late periods and CPU per period, measured: alone, after the parallel tests (Makefile)
pytestmark = pytest.mark.serial


@pytest.fixture(scope='module')
def tips(tmp_path_factory):
    return replay_tips(4.0, tmp_path_factory.mktemp('deploy') / 'tips.npy')


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_separate_and_composed_loops_answer_every_tick_and_composed_costs_less_cpu(tips):
    # three interleaved rounds: CPU per period is compared on each layout's smallest figure, as a
    # busy host inflates a run's CPU time (cache and wake-up contention; on a slower host one
    # layout's two runs both were, once in two suites) but not every round's
    rounds = [{v: run_deploy(2e-3, 1.0, tips, variant=v) for v in ('base', 'composed')}
              for _ in range(3)]
    for runs in rounds:
        for name, r in runs.items():
            # measured from the first tick after the warm-up (a late wake-up can skip past it)
            assert 450 <= r['periods'] <= 500 and r['ticks'] + r['skipped'] >= r['periods'], name
            assert r['matched'] == [2, 1], name      # estimator + trajectory; the controller
            assert r['unanswered'] <= r['ticks'] // 20, name
            assert 0 < r['latency_p50'] <= r['latency_p99'] <= r['latency_max'], name
            assert r['cpu_us']['driver'] > 0 and r['cpu_us']['trajectory'] >= 0, name
        separate, composed = runs['base']['cpu_us'], runs['composed']['cpu_us']
        assert separate['estimator'] > 0 and separate['controller'] > 0
        assert 'estimator' not in composed and composed['controller'] > 0
    separate = min(r['base']['cpu_us']['estimator'] + r['base']['cpu_us']['controller']
                   for r in rounds)
    composed = min(r['composed']['cpu_us']['controller'] for r in rounds)
    # one DDS hop and one process fewer per period, measured in the same test
    assert composed < separate, (composed, separate)
    runs = rounds[0]
    mid = summary([runs['base'], {**runs['base'], 'late_pct': runs['base']['late_pct'] + 1}])
    assert mid['repeats'] == 2 and mid['late_pct'] == pytest.approx(runs['base']['late_pct'] + 0.5)


def test_the_pinned_variant_starts_the_loop_and_the_driver_on_their_cpus_the_trajectory_free():
    cpus = {'simulator': 4, 'estimator': 7, 'controller': 7}
    _, _, options = variant_settings('composed+fifo+hold+pinned')
    composed, trajectory = loop_specs({'control_period': 1e-3}, options, cpus)
    assert composed.command('python')[:6] == ['taskset', '-c', '7', 'chrt', '-f', '50']
    assert composed.hosted[0].name == 'estimator' and trajectory.command('python')[0] == 'python'
    assert driver_prefix(options, cpus) == ['taskset', '-c', '4', 'chrt', '-f', '50']
    _, _, options = variant_settings('pinned')
    estimator, controller, trajectory = loop_specs({'control_period': 1e-3}, options, cpus)
    assert [s.cpus for s in (estimator, controller, trajectory)] == [(7,), (7,), ()]
    assert driver_prefix(options, cpus) == ['taskset', '-c', '4']
    _, _, options = variant_settings('composed+fifo')          # not pinned: anywhere
    assert all(not s.cpus for s in loop_specs({}, options, None))
    assert driver_prefix(options, None) == ['chrt', '-f', '50']


def test_variants_join_their_settings():
    what, env, options = variant_settings('composed+shm')
    assert env == {'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'} and options == {'composed': True}
    assert 'one process' in what and 'shared memory' in what


def test_the_floor_is_the_sum_in_lockstep_and_the_larger_branch_pipelined():
    figures = {'lockstep_rtf': 0.5, 'pipelined_rtf': 0.8, 'pipelined_cpu_us': 1800.0}
    (_, floor, parts), (_, graph, _), (_, pipe_floor, note), (_, pipe, pipe_note) = floor_rows(
        600e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6)
    assert floor.startswith('1250 µs (0.80× real time)')          # 600 + 3 × 200 + 50
    # the grasp's physics counts, the scene at rest's is only shown
    assert parts.startswith("physics 600 µs (the grasp's torques replayed; 450 µs at rest)")
    assert graph == '2000 µs = 1.60× the floor'
    assert pipe_floor.startswith('650 µs (1.54× real time)')      # max(600, 3 × 200 + 50)
    assert pipe == '1250 µs = 1.92× the floor' and 'period is 1.60× this one' in pipe_note
    assert f'needs at least {1800 / os.cpu_count():.0f} µs' in note  # 1800 µs of CPU over the cores
    (_, pipe_floor, _) = floor_rows(900e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6)[2]
    assert pipe_floor.startswith('900 µs')                        # the physics is the longer branch
    assert len(floor_rows(600e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6,
                          scheduled=[('at SCHED_FIFO 50', 100.0, 'lockstep_fifo')])) == 4   # no run


def test_a_graph_period_is_its_pace_from_the_first_command_where_the_run_reports_it():
    figures = {'lockstep_rtf': 0.5, 'lockstep_period_us': 1900.0, 'pipelined_rtf': 0.8,
               'pipelined_cpu_us': 1800.0}
    (_, graph, note) = floor_rows(600e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6)[1]
    assert graph == '1900 µs = 1.52× the floor'                   # not 1 ms / 0.5
    assert 'its real-time factor, 0.50×, also counts the wait' in note
    (_, pipe, _) = floor_rows(600e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6)[3]
    assert pipe.startswith('1250 µs')                             # no pace reported: 1 ms / 0.8


def test_lockstep_run_otherwise_is_held_against_a_floor_measured_the_same_way():
    figures = {'lockstep_rtf': 0.5, 'pipelined_rtf': 0.8, 'pipelined_cpu_us': 1800.0,
               'lockstep_fifo_rtf': 0.8}
    *_, (what, floor, parts), (_, graph, note) = floor_rows(
        600e-6, 200.0, 3e-6, 47e-6, figures, rest=450e-6,
        scheduled=[('at SCHED_FIFO 50', 100.0, 'lockstep_fifo')])
    assert what == 'floor of a lockstep period, at SCHED_FIFO 50' and 'three hops 300 µs' in parts
    assert floor.startswith('950 µs (1.05× real time)')           # 600 + 3 × 100 + 50
    assert graph == '1250 µs = 1.32× the floor'
    assert '1.60× as fast as lockstep at ordinary priority' in note   # 2000 µs against 1250


def _made_run(late: float, p99: float, load: float, cpu: float) -> dict:
    return {'periods': 6000, 'rate_hz': 1000, 'variant': 'composed', 'record': True,
            'late_pct': late, 'slow_pct': late / 2, 'latency_p50': 400.0, 'latency_p99': p99,
            'latency_max': 4000.0,
            'cpu_us': {'controller': cpu, 'recorder': 150.0, 'driver': 80.0},
            'load': load, 'load_before': load - 0.5}


def test_a_row_is_the_median_of_its_runs_with_their_range_and_load_never_the_best():
    runs = [_made_run(0.5, 900.0, 1.0, 300.0), _made_run(3.0, 1500.0, 2.0, 320.0),
            _made_run(1.0, 1000.0, 3.0, 310.0), _made_run(0.2, 800.0, 1.5, 305.0),
            _made_run(9.0, 4000.0, 2.5, 330.0)]
    s = summary(runs)
    assert s['late_pct'] == 1.0 and s['latency_p99'] == 1000.0 and s['repeats'] == 5
    assert s['cpu_us']['controller'] == 310.0 and s['loads'] == [0.5, 1.0, 2.0, 3.0, 1.5, 2.5]
    what, fig, note = describe(s)
    assert fig == ("1.00 % late (0.20–9.00), the loop's own 0.50 % (0.10–4.50); "
                   '400 / 1000 (800–4000) / 4000 µs')
    assert 'with the recorder' in what and 'one process' in what
    assert 'median (min–max) of 5 runs of 6 s (6000 periods)' in note and 'best' not in note
    assert 'load 0.5 before' in note


@pytest.mark.parametrize('args', [['--repeats', '0'], ['--seconds', '-1'], ['--seconds', 'x'],
                                  ['--probe', __file__], ['--rate', 'fast']])
def test_the_command_refuses_bad_arguments_with_status_2(args, capsys):
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert 'usage:' in err and 'Traceback' not in err


def test_the_loops_own_late_ticks_are_the_round_trips_longer_than_a_period():
    """A tick is the loop's own late one when its command came back more than a period after its
    tips, or never; a tick the stand-in skipped (not sent) is not counted."""
    period = 1e-3
    sent = np.array([1.0, 1.001, 0.0, 1.003, 1.004])
    received = np.array([1.0004, 1.0025, 0.0, 0.0, 1.0049])
    ticked = np.flatnonzero(sent > 0)
    assert slow_ticks(sent, received, ticked, period).tolist() == [False, True, True, False]


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_fifo_variant_starts_the_loop_and_the_driver_at_real_time_priority(tips):
    from soft_gripper_sdre.nodes.scheduling import fifo_problem
    refused = fifo_problem(50)
    if refused:
        pytest.skip(refused)
    r = run_deploy(2e-3, 1.0, tips, variant='composed+fifo')
    assert r['fifo_granted'] is True
    assert r['unanswered'] <= r['ticks'] // 20 and r['matched'] == [2, 1]
    assert 0 <= r['slow'] <= r['ticks']
