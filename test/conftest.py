"""Shared test set-up: DDS stays on loopback, each test session gets its own domain, the compiled
kernels are in numba's cache before any test starts, and the fault tests' outcome records go to a
directory of the session's own."""
import os
from pathlib import Path
import random

import pytest

from faults_common import RECORDS_ENV

# Must be set before any rclpy.init(); subprocesses started by tests inherit them.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault(
    'ROS_DOMAIN_ID', str(random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), 'little')).randint(1, 101))
)
os.environ.setdefault('OMP_NUM_THREADS', '1')


def pytest_sessionstart(session):
    """Compile the control kernels into numba's on-disk cache, or load them from it, before the
    first test: outside every test's time limit, and before the node processes that graph tests
    start, which then load them from the cache instead of each compiling them."""
    from soft_gripper_sdre.control.compiled import warm_up
    warm_up()


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
