"""Real-time priority and CPUs for the loop's processes (nodes/scheduling.py, graph.pinned_cpus):
the check the tools run before they start anything agrees with the kernel, a refusal says how to
get the permission, a node started at a priority and on a CPU runs there with every thread, holds
the CPU wake-up latency and says so on /diagnostics, and the tools, the launch file and the nodes
refuse a bad priority, latency or pinning."""
import os
import struct
import subprocess
import sys

import pytest

from soft_gripper_sdre.nodes import scheduling
from soft_gripper_sdre.nodes.graph import (
    NodeSpec,
    default_params_file,
    grasp_graph,
    pinned_cpus,
    pinning_problem,
)


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


def _device_latency() -> int | None:
    """The machine's CPU wake-up latency request now [µs] (None: the device is not readable)."""
    try:
        with open(scheduling.CPU_LATENCY_DEVICE, 'rb') as f:
            return struct.unpack('i', f.read(4))[0]
    except OSError:
        return None


@pytest.mark.parametrize('text, us', [(None, None), ('', None), ('off', None), ('OFF', None),
                                      ('0', 0), (' 25 ', 25), ('2000000000', 2_000_000_000)])
def test_the_latency_is_held_only_when_the_environment_asks(text, us):
    env = {} if text is None else {scheduling.CPU_LATENCY_ENV: text}
    assert scheduling.cpu_latency_request(env) == us


@pytest.mark.parametrize('text', ['-1', 'abc', '1.5', '2000000001', '0x10'])
def test_a_bad_latency_is_refused_naming_the_variable(text):
    with pytest.raises(ValueError, match=f'{scheduling.CPU_LATENCY_ENV}={text!r}: expected off'):
        scheduling.cpu_latency_request({scheduling.CPU_LATENCY_ENV: text})


def test_a_hold_keeps_the_request_while_open_and_lets_go_when_closed():
    if _device_latency() is None:
        pytest.skip(f'{scheduling.CPU_LATENCY_DEVICE} is not readable here')
    with scheduling.CpuLatencyHold(7) as hold:
        assert hold.held and _device_latency() <= 7       # the machine's: the least of all holds
    assert not hold.held
    hold.close()                                            # twice is harmless
    hold, said = scheduling.hold_cpu_latency({scheduling.CPU_LATENCY_ENV: '9'})
    assert said == '9 µs, held by this process' and _device_latency() <= 9
    hold.close()
    for env in ({}, {scheduling.CPU_LATENCY_ENV: 'off'}):
        assert scheduling.hold_cpu_latency(env) == (
            None, f'not asked for ({scheduling.CPU_LATENCY_ENV} unset or off)')


def test_a_missing_device_is_reported_not_raised(tmp_path):
    missing = tmp_path / 'no_such_device'
    assert scheduling.hold_cpu_latency({scheduling.CPU_LATENCY_ENV: '0'}, device=str(missing)) == (
        None, f'not held: {missing}: No such file or directory')
    assert not missing.exists()


@pytest.mark.skipif(os.geteuid() != 0, reason='needs root to drop to an unprivileged user')
def test_an_unprivileged_user_is_told_how_to_hold_the_latency():
    code = ('import os\n'
            'from soft_gripper_sdre.nodes.scheduling import hold_cpu_latency\n'
            'os.setgroups([]); os.setgid(65534); os.setuid(65534)\n'
            f'print(hold_cpu_latency({{"{scheduling.CPU_LATENCY_ENV}": "0"}})[1])\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60,
                         cwd='/')
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == (f'not held: {scheduling.CPU_LATENCY_DEVICE} is not writable for '
                                  f'this user; {scheduling.LATENCY_HOW}')


def test_a_process_at_ordinary_priority_holds_nothing():
    assert scheduling.process_cpu_latency() is None


def test_a_node_refuses_a_bad_latency_with_status_2_at_any_priority():
    env = dict(os.environ, **{scheduling.CPU_LATENCY_ENV: 'soon'})
    out = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.estimator'], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and 'Traceback' not in out.stderr
    assert out.stderr.strip() == (f"estimator: cannot start: {scheduling.CPU_LATENCY_ENV}='soon': "
                                  'expected off or an integer number of microseconds from 0 to '
                                  '2000000000')


def test_the_graph_runs_the_loops_processes_behind_chrt_and_the_others_as_they_are():
    spec = grasp_graph(realtime=50)
    for node in spec.nodes:
        want = ['chrt', '-f', '50'] if node.name in ('simulator', 'estimator', 'controller') else []
        assert node.command('python')[:len(want) + 1] == [*want, 'python'], node.name
    composed = grasp_graph(realtime=30, composed=True).node('controller')
    assert composed.command('python')[:4] == ['chrt', '-f', '30', 'python']
    assert all(n.command('python')[0] == 'python' for n in grasp_graph().nodes)


def test_pinning_puts_the_simulator_on_one_cpu_and_the_loops_other_processes_on_another():
    assert pinned_cpus([5, 3, 9]) == {'simulator': 3, 'estimator': 5, 'controller': 5}
    with pytest.raises(ValueError, match=r'two CPUs of their own; this process may run on 1 \(2\)'):
        pinned_cpus([2])
    assert pinning_problem([2]) == ('pinning puts the simulator and the loop on two CPUs of their '
                                    'own; this process may run on 1 (2)')
    assert pinning_problem([5, 3]) is None      # the same rule as pinned_cpus (taskset is here)
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip('one CPU here')
    cpus = pinned_cpus()
    spec = grasp_graph(realtime=50, pin=True)
    for node in spec.nodes:
        want = ['taskset', '-c', str(cpus[node.name])] if node.name in cpus else []
        if node.name in ('simulator', 'estimator', 'controller'):
            want += ['chrt', '-f', '50']
        assert node.command('python')[:len(want) + 1] == [*want, 'python'], node.name
    composed = grasp_graph(pin=True, composed=True).node('controller')
    assert composed.cpus == (cpus['controller'],) and composed.hosted[0].name == 'estimator'


def test_the_launch_file_and_the_demo_refuse_pinning_on_one_cpu(launch_module, tmp_path):
    with pytest.raises(ValueError, match="pin_cores:='maybe' must be 'true' or 'false'"):
        launch_module.grasp_nodes(pin_cores='maybe')
    code = ('import os, sys\n'
            'os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n'
            'from soft_gripper_sdre.tools.graph.demo import main\n'
            'sys.argv[0] = "demo"\n'
            f'sys.exit(main(["--out", {str(tmp_path / "demo")!r}, "--pin"]))\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and 'Traceback' not in out.stderr
    assert '--pin: pinning puts the simulator and the loop on two CPUs of their own' in out.stderr
    assert not any(tmp_path.iterdir())
    code = ('import os, runpy\n'
            'os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n'
            f'launch = runpy.run_path({str(launch_module.__file__)!r})\n'
            'try:\n'
            '    launch["grasp_nodes"](pin_cores="true")\n'
            'except ValueError as exc:\n'
            '    print(exc)\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert out.stdout.startswith("launch argument pin_cores:='true': pinning puts"), out.stderr


def test_the_launch_file_pins_the_loop_before_its_priority(launch_module):
    if len(os.sched_getaffinity(0)) < 2 or scheduling.fifo_problem(40):
        pytest.skip('needs two CPUs and SCHED_FIFO')
    cpus = pinned_cpus()
    nodes = {n['executable']: n
             for n in launch_module.grasp_nodes(realtime_priority='40', pin_cores='true')}
    assert {k: n.get('prefix') for k, n in nodes.items()} == {
        'simulator': f'taskset -c {cpus["simulator"]} chrt -f 40',
        'estimator': f'taskset -c {cpus["estimator"]} chrt -f 40',
        'trajectory': None,
        'controller': f'taskset -c {cpus["controller"]} chrt -f 40'}


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


def test_deploy_refuses_a_cpu_it_may_not_run_on_with_status_2(tmp_path):
    out = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.graph.deploy', '--params',
                          str(tmp_path / 'params.yaml'), '--cpu', '4096'],
                         capture_output=True, text=True, timeout=120)
    allowed = ', '.join(map(str, sorted(os.sched_getaffinity(0))))
    assert out.returncode == 2 and 'Traceback' not in out.stderr
    assert f'--cpu 4096: not a CPU this process may run on ({allowed})' in out.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.ros
def test_a_node_started_at_a_priority_runs_there_with_every_thread_and_reports_it(tmp_path):
    if scheduling.fifo_problem(20):
        pytest.skip(scheduling.fifo_problem(20))
    cpu = max(os.sched_getaffinity(0))
    from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, Graph, ros_env
    env = ros_env()
    monitor = DiagnosticsMonitor(env, 'scheduling_monitor')
    env[scheduling.CPU_LATENCY_ENV] = '0'           # the estimator asks for the wake-up latency
    try:
        with Graph(env, tmp_path / 'logs') as graph:
            proc = graph.start_node(NodeSpec('estimator', 'estimator',
                                             params_file=default_params_file('estimator'),
                                             realtime=20, cpus=(cpu,)))
            # inside the suite's 60 s limit, so that a node that stays silent shows its log
            assert monitor.spin_until(lambda: 'scheduling' in monitor.values.get('estimator', {}),
                                      45.0), (f'running: {proc.alive()}, '
                                              f'exit status: {proc.popen.returncode}, '
                                              f'log: {proc.log_tail()!r}')
            assert monitor.values['estimator']['scheduling'] == 'SCHED_FIFO 20'
            assert monitor.values['estimator']['cpu_latency'] == '0 µs, held by this process'
            assert _device_latency() in (0, None)           # (None: not readable here)
            pid = proc.popen.pid
            threads = os.listdir(f'/proc/{pid}/task')
            assert len(threads) > 1                         # rclpy's and Fast DDS's threads
            assert {scheduling.describe(int(t)) for t in threads} == {'SCHED_FIFO 20'}
            assert {frozenset(os.sched_getaffinity(int(t))) for t in threads} == {
                frozenset({cpu})}
    finally:
        monitor.close()
