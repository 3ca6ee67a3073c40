"""The documents' recipe blocks run as written: README's "Use with your own gripper" block, the
block of docs/identification.md and the deploy block of docs/own_gripper.md are taken from the
files, and each of their command lines is run by bash exactly as it stands (quoting and bash
arrays included) against the ``plant_driver`` node (tendon3, 200 Hz, best-effort tips stamped
with wall time), over DDS on loopback in the session's own domain (conftest.py); so are README's
``ros2 param set`` example, against a running controller, and the ``ros2 run`` lines of its
"Running it on a ROS 2 Jazzy install" block.

Only what a lab's machine provides is stood in for: there is no ros2 CLI here, so a ``ros2`` of
the test's own is first on PATH (``ros2 run soft_gripper_sdre <exe> ARGS`` executes the package's
console script ``<exe>`` as ``python -m <its module> ARGS``; ``ros2 param set NODE NAME VALUE``
reads VALUE with YAML 1.1 as ros2param does and calls the node's ``set_parameters`` service;
``ros2 pkg prefix`` names an install prefix holding the repository's config/; ``ros2 topic echo``
is the package's echo tool), and ``python`` is the environment's interpreter (an activated
virtual environment). Long-running lines (the driver, the recorder, the nodes of a graph) run in
the background and are stopped with SIGINT, as Ctrl-C would; nothing waits by sleeping: the
excitation node waits for the driver and the recorder, the simulator for its graph, and
``ros2 param set`` for the node's service."""
import json
import os
from pathlib import Path
import re
import signal
import subprocess
import sys

from deploy_params import params_file
import pytest
from rcl_interfaces.srv import GetParameters
import rclpy
from rosutil import ros_context, spin_until
import yaml

from soft_gripper_sdre.analysis.bag_dataset import read_recording, settle_noise
from soft_gripper_sdre.tools.learning.train import NOT_FIT

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
IDENTIFICATION = ROOT / 'docs' / 'identification.md'
OWN_GRIPPER = ROOT / 'docs' / 'own_gripper.md'
#: a fenced bash block: its text
BASH_BLOCK = re.compile(r'^```bash\n(.*?)^```', re.S | re.M)
#: the console scripts setup.py installs for nodes: executable -> module
CONSOLE_NODES = dict(re.findall(r"'(\w+)': 'soft_gripper_sdre\.nodes\.(\w+):main'",
                                (ROOT / 'setup.py').read_text(encoding='utf-8')))
#: the driver a lab has running: two tendon3 fingers, index and thumb, at 200 Hz, ±0.02 N·m,
#: best-effort wall-stamped tips (plant_driver's defaults, spelled out)
DRIVER = ('ros2 run soft_gripper_sdre plant_driver --ros-args -p plant:=tendon3 -p rate:=200.0 '
          '-p "finger_names:=[index,thumb]"')
#: how long one recipe line may take [s]: an excitation run with its level search, a deployment
LINE_TIMEOUT = 600

#: the ros2 stand-in (its interpreter line is added when it is written)
ROS2 = r'''
"""ros2 stand-in for the tests: `ros2 run soft_gripper_sdre EXE ARGS...` and
`ros2 param set NODE NAME VALUE` as ros2cli does them, `ros2 pkg prefix soft_gripper_sdre` (an
install prefix whose share/soft_gripper_sdre/config is the repository's config/) and
`ros2 topic echo TOPIC` (the package's echo tool); anything else exits 1."""
import json
import os
import sys

NODES = json.loads(os.environ['SGS_TEST_CONSOLE_NODES'])
args = sys.argv[1:]
if args[:2] == ['run', 'soft_gripper_sdre'] and len(args) >= 3:
    if args[2] not in NODES:
        sys.exit(f"No executable found: soft_gripper_sdre {args[2]}")
    os.execv(sys.executable, [sys.executable, '-m', 'soft_gripper_sdre.nodes.' + NODES[args[2]],
                              *args[3:]])
if args[:2] == ['param', 'set'] and len(args) == 5:
    import rclpy
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    import yaml

    node_name, name, text = args[2:]
    try:                        # ros2param's get_parameter_value: YAML 1.1 (PyYAML)
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    if value is None:
        value = text
    rclpy.init(args=[])
    node = rclpy.create_node('_ros2cli_param_set')
    client = node.create_client(SetParameters, node_name.rstrip('/') + '/set_parameters')
    if not client.wait_for_service(timeout_sec=60.0):
        sys.exit(f'Node not found: {node_name}')
    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=60.0)
    result = future.result().results[0]
    if result.successful:
        print('Set parameter successful')
        sys.exit(0)
    print('Setting parameter failed' + (': ' + result.reason if result.reason else ''),
          file=sys.stderr)
    sys.exit(1)
if args == ['pkg', 'prefix', 'soft_gripper_sdre']:
    print(os.environ['SGS_TEST_PREFIX'])
    sys.exit(0)
if args[:2] == ['topic', 'echo'] and len(args) >= 3:
    os.execv(sys.executable, [sys.executable, '-m', 'soft_gripper_sdre.tools.graph.echo',
                              *args[2:]])
sys.exit('ros2 stand-in: not provided here: ros2 ' + ' '.join(args))
'''


def section(path: Path, heading: str) -> str:
    """The text of ``path`` under the first heading whose title starts with ``heading``, up to
    the next heading of the same or a higher level (lines inside fenced blocks are no
    headings)."""
    lines = path.read_text(encoding='utf-8').splitlines(keepends=True)
    fenced, level, out = False, None, []
    for line in lines:
        if line.startswith('```'):
            fenced = not fenced
        m = None if fenced else re.match(r'(#+) ', line)
        if level is None:
            if m and line[m.end():].startswith(heading):
                level = len(m.group(1))
        elif m and len(m.group(1)) <= level:
            break
        else:
            out.append(line)
    assert level is not None, f'{path.name}: no heading {heading!r}'
    return ''.join(out)


def bash_blocks(text: str) -> list[str]:
    return BASH_BLOCK.findall(text)


def commands(block: str) -> tuple[str, list[str]]:
    """(the block's variable assignments, its command lines), comments and blank lines left
    out: a line is a command when it runs ``ros2`` or ``python``, else an assignment that every
    command line of the block runs after."""
    prelude, lines = [], []
    for line in block.splitlines():
        if not line.strip() or line.lstrip().startswith('#'):
            continue
        (lines if re.match(r'\s*(ros2|python) ', line) else prelude).append(line)
    return '\n'.join(prelude), lines


def the_readme_recipe() -> str:
    blocks = bash_blocks(section(README, 'Use with your own gripper'))
    assert len(blocks) == 1, 'README "Use with your own gripper": expected one bash block'
    return blocks[0]


@pytest.fixture
def lab(tmp_path):
    """(working directory, environment) of a lab's shell: the ros2 stand-in and ``python`` first
    on PATH."""
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    ros2 = bin_dir / 'ros2'
    ros2.write_text(f'#!{sys.executable}' + ROS2, encoding='utf-8')
    python = bin_dir / 'python'
    python.write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n', encoding='utf-8')
    for f in (ros2, python):
        f.chmod(0o755)
    prefix = tmp_path / 'install' / 'soft_gripper_sdre'
    (prefix / 'share' / 'soft_gripper_sdre').mkdir(parents=True)
    (prefix / 'share' / 'soft_gripper_sdre' / 'config').symlink_to(ROOT / 'config')
    env = {**os.environ, 'PATH': f'{bin_dir}{os.pathsep}{os.environ["PATH"]}',
           'PYTHONUNBUFFERED': '1', 'SGS_TEST_CONSOLE_NODES': json.dumps(CONSOLE_NODES),
           'SGS_TEST_PREFIX': str(prefix)}
    work = tmp_path / 'lab'
    work.mkdir()
    return work, env


class Shell:
    """Command lines run by bash in the lab's directory, each after the block's assignments;
    the background ones stopped with SIGINT at the end."""

    def __init__(self, work: Path, env: dict, prelude: str = '') -> None:
        self.work, self.env, self.prelude = work, env, prelude
        self.background: list[tuple[str, subprocess.Popen, Path]] = []
        self.logs = work.parent / 'logs'
        self.logs.mkdir(exist_ok=True)
        self.count = 0

    def _start(self, line: str) -> tuple[subprocess.Popen, Path]:
        self.count += 1
        log = self.logs / f'{self.count:02d}.log'
        with open(log, 'w', encoding='utf-8') as out:
            p = subprocess.Popen(['bash', '-c', f'{self.prelude}\n{line}'], cwd=self.work,
                                 env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                 start_new_session=True)
        return p, log

    def start(self, line: str) -> subprocess.Popen:
        p, log = self._start(line)
        self.background.append((line, p, log))
        return p

    def run(self, line: str, timeout: float = LINE_TIMEOUT) -> tuple[int, str]:
        p, log = self._start(line)
        try:
            rc = p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            pytest.fail(f'{line}: still running after {timeout} s:\n{log.read_text()[-3000:]}')
        self.check_background(line)
        return rc, log.read_text(encoding='utf-8')

    def check_background(self, during: str) -> None:
        for line, p, log in self.background:
            assert p.poll() is None, (f'{line} ended (status {p.returncode}) while '
                                      f'{during} ran:\n{log.read_text()[-3000:]}')

    def stop(self, p: subprocess.Popen) -> tuple[int, str]:
        """SIGINT to the background line's process group (Ctrl-C); its exit status and output."""
        (line, _, log), = [b for b in self.background if b[1] is p]
        self.background = [b for b in self.background if b[1] is not p]
        os.killpg(p.pid, signal.SIGINT)
        try:
            rc = p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            pytest.fail(f'{line}: did not stop on SIGINT:\n{log.read_text()[-3000:]}')
        return rc, log.read_text(encoding='utf-8')

    def close(self) -> None:
        for _, p, _ in self.background:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for _, p, _ in self.background:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        self.background = []


@pytest.fixture
def shell(lab):
    s = Shell(*lab)
    yield s
    s.close()


def identify(shell: Shell, recorder: str, excitation: str) -> tuple[Path, str]:
    """The recorder's line in the background, the excitation line to its end (exit 0), the
    recorder stopped with Ctrl-C (exit 0): the bag (the recorder's ``output:=``) and the
    excitation's output."""
    rec = shell.start(recorder)
    rc, out = shell.run(excitation)
    assert rc == 0, f'{excitation}\nexited {rc}:\n{out[-3000:]}'
    rc_rec, out_rec = shell.stop(rec)
    assert rc_rec == 0, f'{recorder}\nexited {rc_rec} on SIGINT:\n{out_rec[-3000:]}'
    bag = shell.work / re.search(r'output:=(\S+)', recorder).group(1)
    assert (bag / 'metadata.yaml').is_file(), f'{recorder}: no bag in {bag}'
    return bag, out


def assert_settle_phase(bag: Path, names: tuple[str, ...] = ('index', 'thumb')) -> None:
    """The bag trains: both fingers' tips and commands, and before the first non-zero command
    a settle phase of zero torque long enough to measure the driver's noise (0.05 mm)."""
    rec = read_recording(bag)
    assert rec.finger_names == names
    for finger in range(len(names)):
        _, sigma, n = settle_noise(rec, finger)
        assert n >= 90 and 3e-5 < sigma < 7e-5, (bag, finger, n, sigma)


def test_the_blocks_are_where_the_test_takes_them_and_parse():
    """The extraction finds each recipe block and its lines; bash parses every block."""
    prelude, lines = commands(the_readme_recipe())
    assert re.search(r'\bT=\(', prelude) and re.search(r'\bF=\(', prelude)
    assert [re.match(r'\S+ \S+ \S+ (\S+)', line).group(1) for line in lines] == [
        'recorder', 'excitation', '--bag', '--params']
    ident = bash_blocks(IDENTIFICATION.read_text(encoding='utf-8'))[0]
    assert [line.split()[3] for line in commands(ident)[1]] == ['recorder', 'excitation']
    deploy = bash_blocks(section(OWN_GRIPPER, 'Deploying: one command'))
    assert len(deploy) == 1 and len(commands(deploy[0])[1]) == 1
    for block in (the_readme_recipe(), ident, deploy[0]):
        r = subprocess.run(['bash', '-n'], input=block, text=True, capture_output=True)
        assert r.returncode == 0, r.stderr


def test_the_stand_in_runs_only_the_package_console_scripts(lab):
    work, env = lab
    assert set(CONSOLE_NODES) >= {'recorder', 'excitation', 'plant_driver', 'controller'}
    r = subprocess.run(['bash', '-c', 'ros2 run soft_gripper_sdre bogus_node'], cwd=work,
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and 'No executable found: soft_gripper_sdre bogus_node' in r.stderr
    r = subprocess.run(['bash', '-c', 'ros2 run soft_gripper_sdre excitation --help'], cwd=work,
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and 'max_excursion' in r.stdout


@pytest.mark.ros
@pytest.mark.timeout(900)
def test_the_identification_block_records_a_bag_with_its_settle_phase(shell):
    """docs/identification.md's block, its two lines as written, beside the driver."""
    prelude, (recorder, excitation) = commands(bash_blocks(
        IDENTIFICATION.read_text(encoding='utf-8'))[0])
    shell.prelude = prelude
    shell.start(DRIVER)
    bag, _ = identify(shell, recorder, excitation)
    assert bag == shell.work / 'bags' / 'train' / 'u1'
    assert_settle_phase(bag)


@pytest.mark.ros
def test_the_documented_param_set_changes_the_running_controller(shell):
    """README's ``ros2 param set /controller q_pos …`` as written sets the running controller's
    gain; the same value in a spelling YAML 1.1 reads as a string (2e6) is refused by the node
    and changes nothing."""
    readme = README.read_text(encoding='utf-8')
    documented = re.findall(r'`(ros2 param set /controller q_pos [^`]+)`', readme)
    assert documented, 'README: no `ros2 param set /controller q_pos …` found'
    controller = shell.start('ros2 run soft_gripper_sdre controller')
    for line in documented:
        value = float(line.split()[-1])
        assert value != controller_q_pos(), 'the documented value is the default: proves nothing'
        rc, out = shell.run(line, timeout=180)
        assert rc == 0 and 'Set parameter successful' in out, out
        assert controller_q_pos() == value
    rc, out = shell.run('ros2 param set /controller q_pos 2e6', timeout=180)
    assert rc == 1 and 'Setting parameter failed' in out, out
    assert controller_q_pos() == value
    rc, out = shell.stop(controller)
    assert rc == 0, out[-3000:]


def controller_q_pos() -> float:
    """The running ``/controller``'s q_pos, from its get_parameters service."""
    with ros_context() as (ctx, executor):
        node = rclpy.create_node('readme_param_get', context=ctx)
        executor.add_node(node)
        client = node.create_client(GetParameters, '/controller/get_parameters')
        assert client.wait_for_service(timeout_sec=120.0), 'no /controller/get_parameters'
        future = client.call_async(GetParameters.Request(names=['q_pos']))
        assert spin_until(executor, future.done, timeout=60.0)
        return future.result().values[0].double_value


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.timeout(2400)
def test_the_readme_recipe_identifies_trains_and_deploys_as_written(shell):
    """README's own-gripper block, every line as written: step 1 records bags/train/u1 (and, as
    its comment says, u4 into bags/val/u4 the same way: the two lines with the signal and the
    bag's name changed, nothing else), each with its settle phase; step 2 trains on those two
    bags, as written (two bags instead of six: the shortest data that still runs every stage of
    training; its verdict on so little data may be "not fit"); step 3 deploys, as written, on
    training's params.yaml, or when training judged the model unfit, on a params.yaml standing in
    for it (the package's model on tendon3, a short plan: test/deploy_params.py's); then
    docs/own_gripper.md's deploy line, as written, on the same file."""
    prelude, (recorder, excitation, train, deploy) = commands(the_readme_recipe())
    shell.prelude = prelude
    shell.start(DRIVER)
    bag, _ = identify(shell, recorder, excitation)
    assert bag == shell.work / 'bags' / 'train' / 'u1'
    assert_settle_phase(bag)
    val, _ = identify(shell, recorder.replace('bags/train/u1', 'bags/val/u4'),
                      excitation.replace('signals:=[u1]', 'signals:=[u4]'))
    assert val == shell.work / 'bags' / 'val' / 'u4'
    assert_settle_phase(val)

    rc, out = shell.run(train, timeout=1500)
    params = shell.work / 'runs' / 'mine' / 'params.yaml'
    # 3: the model written and judged not fit to control, no params.yaml
    assert rc == (0 if params.exists() else NOT_FIT) and 'Traceback' not in out, out[-3000:]
    assert (params.parent / 'model.pt').is_file() and (params.parent / 'metrics.json').is_file()
    if not params.exists():                 # judged unfit on two bags: said, nothing derived
        assert 'THE MODEL IS NOT FIT TO CONTROL' in out and 'params.yaml was not written' in out
        params_file(params)

    rc, out = shell.run(deploy)
    assert rc == 0, out[-3000:]
    assert_scored(params.parent / 'deploy_sdre_ff', params)
    (own,) = commands(bash_blocks(section(OWN_GRIPPER, 'Deploying: one command'))[0])[1]
    rc, out = shell.run(own)
    assert rc == 0, out[-3000:]
    assert_scored(params.parent / 'grasp', params)


def assert_scored(out: Path, params: Path) -> None:
    """A deployment's directory: its bag, and its score of the law over the plan of
    ``params`` with no command outside the controller's or the driver's bounds."""
    score = json.loads((out / 'score.json').read_text(encoding='utf-8'))
    plan = yaml.safe_load(params.read_text(encoding='utf-8'))['/**/trajectory']['ros__parameters']
    assert score['law'] == 'sdre_ff'
    assert score['plan_seconds'] == pytest.approx(
        sum(plan[k] for k in ('t_start', 't_close', 't_hold', 't_open')))
    assert score['commands'] > 0 and score['samples'] > 0
    assert score['outside_bounds'] == 0 == score['outside_plant_bounds']
    assert (out / 'bag' / 'metadata.yaml').is_file()


@pytest.mark.ros
@pytest.mark.timeout(900)
def test_the_jazzy_install_block_runs_the_graph_as_written(shell):
    """README "Running it on a ROS 2 Jazzy install": from ``P=$(ros2 pkg prefix …)`` on, every
    line as written (the workspace's clone, pip and colcon lines before it are a ROS install's:
    test_package.py builds the package with colcon). The estimator, trajectory node, controller
    and the echo run in the background, the simulator's 6 s to its end (exit 0); the echo prints
    the controller's torques; every node stops cleanly on Ctrl-C."""
    (block,) = bash_blocks(section(README, 'Running it on a ROS 2 Jazzy install'))
    lines = [line for line in block.splitlines() if line.strip()]
    start = next(i for i, line in enumerate(lines) if line.startswith('P=$(ros2 pkg prefix'))
    shell.prelude = lines[start]
    runs = lines[start + 1:]
    assert [line.split()[:3] for line in runs] == [
        ['ros2', 'run', 'soft_gripper_sdre']] * 4 + [['ros2', 'topic', 'echo']]
    (simulator,) = [line for line in runs if ' simulator ' in line]
    background = [shell.start(line) for line in runs if line != simulator]
    rc, out = shell.run(simulator)
    assert rc == 0, out[-3000:]
    outputs = [shell.stop(p) for p in background]
    assert all(rc == 0 for rc, _ in outputs), [o[-2000:] for _, o in outputs]
    echoed = outputs[-1][1]
    assert echoed.count('finger_0/ax0') > 100 and 'effort' in echoed, echoed[-2000:]
