"""Shared test set-up: DDS stays on loopback, each test session gets its own domain, the compiled
kernels are in numba's cache before any test starts, and the fault tests' outcome records go to a
directory of the session's own; ``run_main`` runs a command line in the test's process;
``launch_module`` is the launch file loaded without the launch packages."""
import fcntl
import importlib.util
import os
from pathlib import Path
import random
import subprocess

from faults_common import RECORDS_ENV
import pytest

#: the domain IDs a session picks from: those whose DDS ports stay clear of Linux's ephemeral port
#: range (32768-60999) with the default port mapping, 0-101 and 215-232 (0 left to users)
DOMAIN_IDS = (*range(1, 102), *range(215, 233))
#: one lock file per domain ID, held (flock) by the session using it until its process exits
DOMAIN_LOCK = '/tmp/soft_gripper_sdre_ros_domain_{}.lock'


def _lock_domain(domain_id: int) -> int | None:
    """The descriptor of the lock file of ``domain_id``, exclusively locked, or None if another
    session holds it (or it cannot be opened). The lock goes with the descriptor: released at this
    process's exit, however it ends, and not passed to subprocesses (Python's descriptors are not
    inherited)."""
    try:         # (read-only: flock needs no write access, so another user's file serves too)
        fd = os.open(DOMAIN_LOCK.format(domain_id), os.O_RDONLY | os.O_CREAT, 0o644)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def claim_domain_id() -> tuple[int, int]:
    """A domain ID no other test session on this machine uses, and its held lock: the IDs of
    :data:`DOMAIN_IDS` in random order, the first whose lock is free.

    Raises:
        RuntimeError: every one is taken.
    """
    ids = list(DOMAIN_IDS)
    random.SystemRandom().shuffle(ids)
    for domain_id in ids:
        lock = _lock_domain(domain_id)
        if lock is not None:
            return domain_id, lock
    raise RuntimeError(f'every ROS domain ID a test session may use is taken (all {len(ids)} locks '
                       f'{DOMAIN_LOCK.format("*")} are held); set ROS_DOMAIN_ID to choose one')


# Must be set before any rclpy.init(); subprocesses started by tests inherit them. A
# ROS_DOMAIN_ID set by the caller is used as it is (and locked when free, so no other session
# picks it meanwhile) in a run of one process. Each worker of a parallel run (pytest-xdist, which
# sets PYTEST_XDIST_WORKER before this file loads) claims a domain of its own instead: it inherits
# the starting process's ROS_DOMAIN_ID, and two workers' graphs on one domain hear each other.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
if os.environ.get('ROS_DOMAIN_ID', '').isdigit() and not os.environ.get('PYTEST_XDIST_WORKER'):
    _DOMAIN_LOCK = _lock_domain(int(os.environ['ROS_DOMAIN_ID']))
else:
    _domain_id, _DOMAIN_LOCK = claim_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(_domain_id)
os.environ.setdefault('OMP_NUM_THREADS', '1')


def pytest_sessionstart(session):
    """Compile the control kernels and the closed-loop check's into numba's on-disk cache, or
    load them from it, before the first test: outside every test's time limit, and before the
    node processes that graph tests start, which then load them from the cache instead of each
    compiling them."""
    from soft_gripper_sdre.control.kernels import warm_up, warm_up_check_loop
    warm_up()
    warm_up_check_loop()


@pytest.fixture(scope='session', autouse=True)
def fault_records_dir(tmp_path_factory):
    """Where :func:`faults_common.record` writes: ``$FAULTS_OUT`` if set (to keep the records),
    else a fresh temporary directory, so no test run writes into the source tree."""
    if os.environ.get(RECORDS_ENV):
        yield Path(os.environ[RECORDS_ENV])
        return
    with pytest.MonkeyPatch.context() as patch:
        directory = tmp_path_factory.mktemp('faults')
        patch.setenv(RECORDS_ENV, str(directory))
        yield directory


@pytest.fixture(scope='session')
def launch_module():
    """launch/grasp.launch.py loaded as a module (it imports the launch packages only inside
    ``generate_launch_description``, so its node list and checks load without them)."""
    spec = importlib.util.spec_from_file_location(
        'grasp_launch', Path(__file__).resolve().parents[1] / 'launch' / 'grasp.launch.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def run_main(capsys):
    """Run a command line's ``main(argv)`` in the test's own process, for the checks of its
    arguments: no interpreter to start and nothing to import again for each case (each test file
    still runs its tool once as ``python -m``). Returns a CompletedProcess with the exit status,
    stdout and stderr ``python -m`` would give; an exception escaping ``main`` (a traceback under
    ``python -m``) fails the test."""
    def run(main, *argv) -> subprocess.CompletedProcess:
        args = [str(a) for a in argv]
        capsys.readouterr()
        try:
            code = main(args)
        except SystemExit as exc:
            code = exc.code
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out, err)
    return run
