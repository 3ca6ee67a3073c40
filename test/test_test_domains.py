"""The test suite's own isolation: every process that runs tests is on a ROS domain no other
test process of this machine uses, in a run of one process and in a parallel run (``make test``
runs its parallel part on two pytest-xdist workers)."""
import os
from pathlib import Path
import shutil
import subprocess
import sys

HERE = Path(__file__).resolve().parent

PROBE = '''
import os
from pathlib import Path


def test_{name}():
    out = Path(os.environ['SGS_DOMAIN_PROBE'])
    worker, domain = os.environ['PYTEST_XDIST_WORKER'], os.environ['ROS_DOMAIN_ID']
    (out / '{name}').write_text(worker + ' ' + domain)
'''


def test_each_parallel_worker_claims_a_domain_of_its_own(tmp_path):
    """Two xdist workers inherit the starting process's ROS_DOMAIN_ID (set here, as a caller's);
    each claims another, and not the same one (their graphs would hear each other)."""
    suite = tmp_path / 'suite'
    suite.mkdir()
    for name in ('conftest.py', 'faults_common.py'):
        shutil.copy(HERE / name, suite / name)
    for name in ('a', 'b'):
        (suite / f'test_{name}.py').write_text(PROBE.format(name=name))
    seen = tmp_path / 'seen'
    seen.mkdir()
    env = {**os.environ, 'ROS_DOMAIN_ID': os.environ['ROS_DOMAIN_ID'],
           'SGS_DOMAIN_PROBE': str(seen), 'PYTHONPATH': str(suite)}
    r = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', '-n', '2',
                        '--dist', 'loadfile', str(suite)], env=env, cwd=suite,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    workers = dict(p.read_text().split() for p in seen.iterdir())
    assert len(workers) == 2, workers                       # one test file on each worker
    domains = set(workers.values())
    assert len(domains) == 2 and os.environ['ROS_DOMAIN_ID'] not in domains, workers
