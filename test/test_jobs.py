"""The sweeps' jobs (tools.judging.jobs): in this process, on a pool of processes and on a real Ray
instance, with the same numbers; the seed sweep (tools.judging.seeds) end to end; the command lines'
refusals."""
import hashlib
import importlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

import jobs_helpers
from jobs_helpers import draw, fail_on_three
import numpy as np
import pytest

from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.judging import jobs
from soft_gripper_sdre.tools.learning.collect import collect_signal, write_record

RAY_MISSING = jobs.ray_available()
needs_ray = pytest.mark.skipif(RAY_MISSING is not None,
                               reason='ray is not installed: the optional Ray runner is not '
                                      f'tested ({jobs.RAY_INSTALL})')
TOOLS = ('seeds', 'evaluate', 'robustness')
#: the wing of soft_gripper_sdre.tools each tool run here lives in
WING = {'seeds': 'judging', 'evaluate': 'judging', 'robustness': 'judging', 'train': 'learning'}


# -- the runner ------------------------------------------------------------------------------------
def test_in_process_and_pool_give_the_same_results_in_job_order(tmp_path):
    source = tmp_path / 'model.pt'
    source.write_bytes(b'weights' * 1000)
    context = {'scale': 2.5, 'blob': jobs.FileBlob.read(source)}
    serial = jobs.run_jobs(draw, range(6), context, jobs.Runner(1), progress=False)
    pooled = jobs.run_jobs(draw, range(6), context, jobs.Runner(2), progress=False)
    assert [r[:2] for r in serial] == [r[:2] for r in pooled] == [
        (float(np.random.default_rng(j).standard_normal() * 2.5),
         hashlib.sha256(source.read_bytes()).hexdigest())
        for j in range(6)]
    assert {pid for *_, pid in serial} == {os.getpid()}
    assert os.getpid() not in {pid for *_, pid in pooled}
    blob = context['blob'].path()
    assert blob != source and blob.name == 'model.pt' and blob.read_bytes() == source.read_bytes()
    assert blob.parent.parent == jobs.blob_dir()            # one copy per content, every process's


def test_a_failing_job_raises_here():
    for runner in (jobs.Runner(1), jobs.Runner(2)):
        with pytest.raises(ArithmeticError, match='job 3 failed'):
            jobs.run_jobs(fail_on_three, range(5), None, runner, progress=False)


def test_the_workers_get_the_drivers_kernel_variables():
    env = {'OPENBLAS_CORETYPE': 'Haswell', 'ATEN_CPU_CAPABILITY': 'avx2', 'HOME': '/root',
           'PATH': '/bin'}
    assert jobs.worker_env(env) == {'OPENBLAS_CORETYPE': 'Haswell', 'ATEN_CPU_CAPABILITY': 'avx2'}


@pytest.mark.parametrize('workers, ray, why', [(0, None, 'workers'), (1.5, None, 'workers'),
                                               (1, 'not an address', 'ray must be'),
                                               (1, 'host:99999999', 'ray must be')])
def test_runner_refuses_bad_values(workers, ray, why):
    with pytest.raises(ValueError, match=why):
        jobs.Runner(workers, ray)


def test_nothing_listening_at_the_address_is_found_before_ray_is_asked():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]          # bound, not listening: a refused connection
        with pytest.raises(jobs.JobsError, match=f'nothing answers at 127.0.0.1:{port}'):
            jobs._check_reachable(f'127.0.0.1:{port}')


# -- the command lines -----------------------------------------------------------------------------
def run_tool(tool, *args, timeout=60, env=None):
    return subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.{WING[tool]}.{tool}',
                           *args],
                          capture_output=True, text=True, timeout=timeout, env=env)


def refusal(tool, args, capsys) -> str:
    """Run the tool's main in this process on ``args``, which it must refuse with status 2; its
    stderr."""
    module = importlib.import_module(f'soft_gripper_sdre.tools.{WING[tool]}.{tool}')
    try:
        code = module.main(list(args))
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize('tool', TOOLS)
@pytest.mark.parametrize('args, why', [(('--workers', '0'), '--workers must be >= 1'),
                                       (('--ray', 'http://head'),
                                        '--ray must be auto, local, HOST:PORT')])
def test_bad_runner_arguments_exit_2_before_anything_starts(tmp_path, capsys, tool, args, why):
    out = tmp_path / 'out'
    assert why in refusal(tool, ('--out', str(out), *args), capsys)
    assert not out.exists()


def test_a_refusal_is_a_message_without_a_traceback(tmp_path):
    proc = run_tool('seeds', '--out', str(tmp_path / 'out'), '--workers', '0')
    assert (proc.returncode == 2 and '--workers must be >= 1' in proc.stderr
            and 'Traceback' not in proc.stderr)
    assert not (tmp_path / 'out').exists()


@pytest.mark.skipif(RAY_MISSING is None,
                    reason='ray is installed: the refusal without it cannot be seen here')
@pytest.mark.parametrize('tool', TOOLS)
def test_ray_without_ray_installed_is_a_usage_error(tmp_path, capsys, tool):
    err = refusal(tool, ('--out', str(tmp_path / 'out'), '--ray', 'auto'), capsys)
    assert f'--ray needs the optional dependency ray ({jobs.RAY_INSTALL})' in err
    assert not (tmp_path / 'out').exists()


@needs_ray
@pytest.mark.parametrize('tool', TOOLS)
def test_no_ray_cluster_at_the_address_is_a_usage_error(tmp_path, capsys, tool, data_dir):
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
        extra = ('--data', str(data_dir)) if tool == 'seeds' else ()
        err = refusal(tool, ('--out', str(tmp_path / 'out'), '--ray', f'127.0.0.1:{port}',
                             *extra), capsys)
    assert f'--ray: nothing answers at 127.0.0.1:{port}' in err
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('args, why', [(('--seeds', '0'), '--seeds must be in [1, 1000]'),
                                       (('--draws', '-1'), '--draws must be in [0, 1000]'),
                                       (('--jitter', '0'), '--jitter must be in (0, 1e-3)'),
                                       (('--set', 'epochs=0'), '--set epochs must be >= 1'),
                                       (('--set', 'seed=3'),
                                        '--set takes KEY=VALUE with KEY one of'),
                                       (('--set', 'lr=fast'), "--set lr: 'fast' is not a float"),
                                       (('--set', 'sv_penalty=-1'),
                                        'sv_penalty must be finite and >= 0'),
                                       (('--laws', 'mpc'), "invalid choice: 'mpc'"),
                                       (('--duration', '0'), '--duration must be > 0 s'),
                                       (('--domain-id', '300'),
                                        '--domain-id must be a ROS domain ID')])
def test_seeds_refuses_bad_arguments(tmp_path, capsys, data_dir, args, why):
    out = tmp_path / 'out'
    assert why in refusal('seeds', ('--data', str(data_dir), '--out', str(out), *args), capsys)
    assert not out.exists()


def test_seeds_refuses_a_data_directory_without_the_signals(tmp_path, capsys):
    err = refusal('seeds', ('--data', str(tmp_path / 'nothing'), '--out', str(tmp_path / 'out')),
                  capsys)
    assert 'no such dataset file' in err and not (tmp_path / 'out').exists()


# -- the seed sweep end to end ---------------------------------------------------------------------
@pytest.fixture(scope='module')
def data_dir(tmp_path_factory):
    """0.5 s of every signal of the default variant, written as the collect tool writes them."""
    out = tmp_path_factory.mktemp('excitation')
    for i, name in enumerate(DATA_VARIANTS['identifying'] + (VALIDATION,)):
        write_record(out / f'{name}.npz',
                     collect_signal(name, SimConfig(scene='finger', seed=i), duration=0.5))
    return out


#: two seeds, one jittered draw, three epochs, the default law on 0.2 s of the fast grasp
SWEEP = ('--seeds', '2', '--draws', '1', '--set', 'epochs=3', '--laws', 'sdre_ff',
         '--trajectories', 'fast', '--duration', '0.2', '--no-progress')


def sweep_numbers(out) -> dict:
    """Every model's figures and tracking runs from seeds.json, without the wall times."""
    report = json.loads((out / 'seeds.json').read_text())
    tracking = {name: [{k: v for k, v in run.items() if k != 'compute_us'} for run in runs]
                for name, runs in report['tracking'].items()}
    return dict(models=report['models'], tracking=tracking, summary=report['summary'])


@pytest.fixture(scope='module')
def pooled_sweep(tmp_path_factory, data_dir):
    out = tmp_path_factory.mktemp('seeds') / 'pool'
    proc = run_tool('seeds', '--data', str(data_dir), '--out', str(out), *SWEEP, '--workers', '2',
                    timeout=300)
    assert proc.returncode == 0, proc.stderr
    return out, proc.stdout


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_seed_sweep_trains_and_scores_every_model_and_the_shipped_one(pooled_sweep, data_dir,
                                                                      tmp_path):
    out, printed = pooled_sweep
    numbers = sweep_numbers(out)
    names = [m['name'] for m in numbers['models']]
    assert names == ['shipped', 'seed0', 'seed0_draw1', 'seed1', 'seed1_draw1']
    shas = {m['name']: m['weights_sha256'] for m in numbers['models']}
    assert len(set(shas.values())) == 5  # every seed and every draw is its own model
    for m in numbers['models']:
        assert np.isfinite([m['r2_x'], m['r2_y'], m['g2_01'], m['sdre_ff_fast_rmse_mm']]).all()
        if m['name'] != 'shipped':
            assert (out / m['name'] / 'model.pt').is_file() and m['epochs_run'] == 3
    shipped = next(m for m in numbers['models'] if m['name'] == 'shipped')
    from soft_gripper_sdre.learning.model import DEFAULT_MODEL
    assert (shipped['r2_x']
            == json.loads(DEFAULT_MODEL.with_suffix('.json').read_text())['u4_r2_true']['X'])
    r2x = numbers['summary']['r2_x']
    values = [m['r2_x'] for m in numbers['models'][1:]]
    assert r2x['all']['n'] == 4 and r2x['all']['mean'] == pytest.approx(np.mean(values))
    assert r2x['all']['sd'] == pytest.approx(np.std(values, ddof=1))
    assert r2x['seeds']['n'] == 2 and r2x['shipped']['of'] == 4
    assert ('| u4 R² X |' in printed
            and (out / 'seeds.md').read_text() == printed.rstrip('\n') + '\n')
    # train.py with the same seed, jitter and draw trains the same model, bit for bit
    from soft_gripper_sdre.learning.model import weights_sha256
    proc = run_tool('train', '--data', str(data_dir), '--out', str(tmp_path / 'train'),
                    '--epochs', '3', '--seed', '1', '--jitter', '1e-9', '--jitter-seed', '1',
                    timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert weights_sha256(tmp_path / 'train' / 'model.pt') == shas['seed1_draw1']


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_seed_sweep_gives_the_same_numbers_in_one_process(pooled_sweep, data_dir, tmp_path):
    out, _ = pooled_sweep
    proc = run_tool('seeds', '--data', str(data_dir), '--out', str(tmp_path / 'serial'), *SWEEP,
                    '--workers', '1', timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert sweep_numbers(tmp_path / 'serial') == sweep_numbers(out)


# -- on a real Ray instance ------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture(scope='module')
def ray_head():
    """A Ray head started as a user would (`ray start --head --block`) on a free port of this
    machine, two CPUs, token authentication off (loopback test cluster); its address. SIGTERM to
    the blocking `ray start` process ends every process it started."""
    temp = tempfile.mkdtemp(prefix='sgs-ray-')  # short: Ray's socket paths must fit 107 characters
    port = free_port()
    env = dict(os.environ, RAY_AUTH_MODE='disabled')
    log = open(os.path.join(temp, 'ray_start.log'), 'w')
    head = subprocess.Popen([sys.executable, '-m', 'ray.scripts.scripts', 'start', '--head',
                             '--block', f'--port={port}', '--num-cpus=2',
                             '--include-dashboard=false', '--disable-usage-stats',
                             f'--temp-dir={temp}'], stdout=log, stderr=subprocess.STDOUT, env=env,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                socket.create_connection(('127.0.0.1', port), timeout=1).close()
                break
            except OSError:
                if head.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError('ray start did not come up: '
                                       f'{open(log.name).read()[-2000:]}')
                time.sleep(0.5)
        yield f'127.0.0.1:{port}', env
    finally:
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)     # the session this fixture started, by its id
            head.wait(10)
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


@needs_ray
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_seed_sweep_on_a_ray_cluster_gives_the_pool_numbers(pooled_sweep, data_dir, tmp_path,
                                                            ray_head):
    address, env = ray_head
    out, _ = pooled_sweep
    proc = run_tool('seeds', '--data', str(data_dir), '--out', str(tmp_path / 'ray'), *SWEEP,
                    '--ray', address, timeout=500, env=env)
    assert proc.returncode == 0, proc.stderr
    assert f'jobs on the Ray cluster at {address}' in proc.stdout
    assert sweep_numbers(tmp_path / 'ray') == sweep_numbers(out)


@needs_ray
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_evaluate_and_robustness_on_a_ray_cluster_give_the_pool_numbers(tmp_path, ray_head):
    address, env = ray_head
    for tool, args, result, key in (
            ('evaluate', ('--laws', 'sdre_ff', 'pd', '--trajectories', 'fast', '--duration', '0.3',
                          '--no-model-score'), 'evaluate.json', 'runs'),
            ('robustness', ('--laws', 'sdre_ff', '--variations', 'nominal', 'delay_2ms',
                            '--trajectories', 'fast', '--duration', '0.3'),
             'robustness.json', 'runs')):
        numbers = []
        for where in (('--workers', '2'), ('--ray', address)):
            out = tmp_path / f'{tool}{where[0]}'
            proc = run_tool(tool, '--out', str(out), *args, *where, timeout=500, env=env)
            assert proc.returncode == 0, proc.stderr
            runs = json.loads((out / result).read_text())[key]
            numbers.append([{k: v for k, v in r.items() if k != 'compute_us'} for r in runs])
        assert numbers[0] == numbers[1] and len(numbers[0]) == 2, tool


@needs_ray
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_local_ray_instance_runs_the_jobs_in_its_own_workers(monkeypatch):
    from ray import cloudpickle
    cloudpickle.register_pickle_by_value(jobs_helpers)      # the helpers travel with their jobs
    runner = jobs.Runner(2, 'local')
    temp = tempfile.mkdtemp(prefix='sgs-ray-')       # the instance's session files, removed after
    monkeypatch.setenv('RAY_TMPDIR', temp)
    try:
        with jobs.session(runner):
            on_ray = jobs.run_jobs(draw, range(4), {'scale': 2.5}, runner, progress=False)
    finally:
        shutil.rmtree(temp, ignore_errors=True)
    here = jobs.run_jobs(draw, range(4), {'scale': 2.5}, progress=False)
    assert [r[:2] for r in on_ray] == [r[:2] for r in here]
    assert os.getpid() not in {pid for *_, pid in on_ray}
