"""Real-time priority for the loop's processes (nodes/scheduling.py): the check the tools run before
they start anything agrees with the kernel, a refusal says how to get the permission, a node
started at a priority runs there with every thread and says so on /diagnostics, and the tools and
the launch file refuse a bad priority."""
import os
import subprocess
import sys

import pytest

from soft_gripper_sdre.nodes import scheduling
from soft_gripper_sdre.nodes.graph import NodeSpec, default_params_file, grasp_graph


def test_describe_names_the_policy_and_its_priority_or_nice():
    assert scheduling.describe() == f'SCHED_OTHER nice {os.getpriority(os.PRIO_PROCESS, 0)}'
    assert not scheduling.realtime()
    out = subprocess.run(['chrt', '-f', '7', sys.executable, '-c',
                          'from soft_gripper_sdre.nodes import scheduling as s; '
                          'print(s.describe(), s.realtime())'],
                         capture_output=True, text=True, timeout=60)
    if out.returncode != 0:
        pytest.skip(f'chrt -f refused here: {out.stderr.strip()}')
    assert out.stdout.split() == ['SCHED_FIFO', '7', 'True']


@pytest.mark.parametrize('bad', [0, 99, -1, 50.0, True, '50', None])
def test_a_priority_outside_1_to_98_is_refused_naming_the_range(bad):
    assert scheduling.fifo_problem(bad) == (f'real-time priority must be an integer from 1 to 98, '
                                            f'got {bad!r}')


def test_the_check_is_the_kernels_answer_and_leaves_the_caller_as_it_was():
    before = (os.sched_getscheduler(0), os.sched_getparam(0))
    problem = scheduling.fifo_problem(50)
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before
    kernel = subprocess.run(['chrt', '-f', '50', 'true'], capture_output=True, timeout=30)
    assert (problem is None) == (kernel.returncode == 0), (problem, kernel.stderr)


@pytest.mark.skipif(os.geteuid() != 0, reason='needs root to drop to an unprivileged user')
def test_an_unprivileged_user_is_told_how_to_get_the_permission():
    code = ('import os, resource\n'
            'from soft_gripper_sdre.nodes.scheduling import fifo_problem\n'
            'resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))\n'
            'os.setgroups([]); os.setgid(65534); os.setuid(65534)\n'
            'print(fifo_problem(50))\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60,
                         cwd='/')
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ('SCHED_FIFO priority 50 is not permitted for this user: '
                                  + scheduling.HOW)


def test_the_graph_runs_the_loops_processes_behind_chrt_and_the_others_as_they_are():
    spec = grasp_graph(realtime=50)
    for node in spec.nodes:
        want = ['chrt', '-f', '50'] if node.name in ('simulator', 'estimator', 'controller') else []
        assert node.command('python')[:len(want) + 1] == [*want, 'python'], node.name
    composed = grasp_graph(realtime=30, composed=True).node('controller')
    assert composed.command('python')[:4] == ['chrt', '-f', '30', 'python']
    assert all(n.command('python')[0] == 'python' for n in grasp_graph().nodes)


@pytest.mark.parametrize('text, words', [('abc', 'is not a number'),
                                         ('99', 'must be an integer from 1 to 98')])
def test_the_launch_file_refuses_a_bad_priority_before_any_node_starts(launch_module, text,
                                                                        words):
    with pytest.raises(ValueError, match=f'realtime_priority:={text!r}.*{words}'):
        launch_module.grasp_nodes(realtime_priority=text)


def test_the_launch_file_gives_the_loops_processes_the_prefix(launch_module):
    if scheduling.fifo_problem(40):
        pytest.skip(scheduling.fifo_problem(40))
    nodes = {n['executable']: n for n in launch_module.grasp_nodes(realtime_priority='40')}
    assert {k for k, n in nodes.items() if n.get('prefix') == 'chrt -f 40'} == {
        'simulator', 'estimator', 'controller'}
    assert 'prefix' not in nodes['trajectory']
    assert all('prefix' not in n for n in launch_module.grasp_nodes())


@pytest.mark.parametrize('tool', ['deploy', 'demo'])
@pytest.mark.parametrize('value, words', [('0x', 'invalid int value'),
                                          ('99', 'must be an integer from 1 to 98')])
def test_the_tools_refuse_a_bad_priority_with_status_2(tmp_path, tool, value, words):
    args = ['--params', str(tmp_path / 'params.yaml')] if tool == 'deploy' else [
        '--out', str(tmp_path / 'demo')]
    out = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.graph.{tool}', *args,
                          '--realtime', value], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and words in out.stderr and 'Traceback' not in out.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.ros
def test_a_node_started_at_a_priority_runs_there_with_every_thread_and_reports_it(tmp_path):
    if scheduling.fifo_problem(20):
        pytest.skip(scheduling.fifo_problem(20))
    from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env
    env = ros_env()
    monitor = DiagnosticsMonitor(env, 'scheduling_monitor')
    try:
        with Graph(env, tmp_path / 'logs') as graph:
            proc = graph.start_node(NodeSpec('estimator', 'estimator',
                                             params_file=default_params_file('estimator'),
                                             realtime=20))
            assert monitor.spin_until(lambda: 'scheduling' in monitor.values.get('estimator', {}),
                                      120.0), proc.log_tail()
            assert monitor.values['estimator']['scheduling'] == 'SCHED_FIFO 20'
            pid = proc.popen.pid
            threads = os.listdir(f'/proc/{pid}/task')
            assert len(threads) > 1                         # rclpy's and Fast DDS's threads
            assert {scheduling.describe(int(t)) for t in threads} == {'SCHED_FIFO 20'}
    finally:
        monitor.close()
