"""Independent jobs of a sweep, run on this machine's cores or on a Ray cluster, with the same
results.

The sweeps (:mod:`~soft_gripper_sdre.tools.judging.seeds`,
:mod:`~soft_gripper_sdre.tools.judging.evaluate`,
:mod:`~soft_gripper_sdre.tools.judging.robustness`) are lists of jobs that do not depend on each
other: a training run, a closed-loop run of one law. :func:`run_jobs` runs ``fn(context, job)`` for
every job and returns the results in the order of the jobs:

* ``Runner(workers=1)``: one after the other in this process;
* ``Runner(workers=N)``: on a pool of N spawned worker processes of this machine;
* ``Runner(ray=ADDRESS)``: as Ray tasks (``ray.remote``, one CPU each) on the Ray cluster at
  ADDRESS, or on a new Ray instance of this machine with ``ray='local'``.

A job's result depends on the job and the context only (each job seeds what it draws and builds its
own simulator, law or network), so the three give the same numbers, bit for bit, on machines of one
kind: the environment variables that choose the math kernels and their threads
(:data:`KERNEL_ENV`, e.g. the pinned kernels of ``make model``) go with the jobs, to the pool's
workers by inheritance and to Ray's through the job's ``runtime_env``. Every node of a cluster
needs this package installed at the same version (the workers import ``fn`` by name); the
context and the jobs travel by value (files as :class:`FileBlob`), so no node needs the driver's
files.

Ray is optional (``pip install ray==2.60.0``, :data:`RAY_INSTALL`); ``--ray`` without it is refused
as a usage error.
"""
from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
import hashlib
import multiprocessing
import os
from pathlib import Path
import re
import socket
import sys
import tempfile
from typing import Any, Callable, Iterator, Sequence

from soft_gripper_sdre.tools.graph.procs import PINNED_KERNELS

#: the Ray release the sweeps were tested with (README "Dependencies")
RAY_VERSION = '2.60.0'
RAY_INSTALL = f'pip install ray=={RAY_VERSION}'
#: variables that choose numpy's, torch's and numba's CPU kernels or their threads: a job's bits
#: can depend on them, so the workers run with the driver's values
KERNEL_ENV = (*PINNED_KERNELS, 'NPY_DISABLE_CPU_FEATURES', 'NUMBA_CPU_NAME', 'NUMBA_CPU_FEATURES',
              'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')
#: a Ray address: auto, local, host:port or ray://host:port
_ADDRESS = re.compile(r'^(auto|local|(ray://)?[A-Za-z0-9._-]+:\d{1,5})$')


class JobsError(RuntimeError):
    """The jobs cannot be run where they were sent (Ray missing, no cluster at the address)."""


@dataclass(frozen=True)
class Runner:
    """Where the jobs run: ``workers`` processes of this machine (1: in this process), or the Ray
    cluster at ``ray`` (``'local'``: a new Ray instance of this machine with ``workers`` CPUs)."""

    workers: int = 1
    ray: str | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.workers, int) and self.workers >= 1):
            raise ValueError(f'workers must be an int >= 1, got {self.workers!r}')
        if self.ray is not None and not _ADDRESS.match(self.ray):
            raise ValueError('ray must be auto, local, HOST:PORT or ray://HOST:PORT, '
                             f'got {self.ray!r}')

    def describe(self) -> str:
        if self.ray == 'local':
            return f'a local Ray instance ({self.workers} CPUs)'
        if self.ray is not None:
            return f'the Ray cluster at {self.ray}'
        return 'this process' if self.workers == 1 else f'{self.workers} worker processes'


def ray_available() -> str | None:
    """None when ``import ray`` works, else why not."""
    try:
        import ray  # noqa: F401
    except ImportError as exc:
        return f'{exc}'
    return None


def add_arguments(parser: argparse.ArgumentParser, default_workers: int | None = None) -> None:
    """``--workers N`` (default: every core) and ``--ray ADDRESS`` on ``parser``."""
    default = default_workers or os.cpu_count() or 1
    parser.add_argument('--workers', type=int, default=default,
                        help='worker processes of this machine (default: every core, %(default)s; '
                             '1 runs the jobs in this process); with --ray local, the CPUs of the '
                             'Ray instance')
    parser.add_argument('--ray', metavar='ADDRESS', default=None,
                        help='run the jobs as Ray tasks instead: on the cluster at ADDRESS (auto: '
                             'the one this machine joined with `ray start`; HOST:PORT; '
                             'ray://HOST:PORT) or on a new '
                             f'Ray instance of this machine (local); needs ray ({RAY_INSTALL})')


def runner_from_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Runner:
    """The :class:`Runner` of ``--workers``/``--ray``; a bad value, or ``--ray`` without ray
    installed, is a usage error (exit 2, nothing started)."""
    if args.workers < 1:
        parser.error(f'--workers must be >= 1, got {args.workers}')
    if args.ray is not None:
        if not _ADDRESS.match(args.ray):
            parser.error('--ray must be auto, local, HOST:PORT or ray://HOST:PORT, '
                         f'got {args.ray!r}')
        missing = ray_available()
        if missing is not None:
            parser.error(f'--ray needs the optional dependency ray ({RAY_INSTALL}): {missing}')
    return Runner(args.workers, args.ray)


def worker_env(environ=os.environ) -> dict[str, str]:
    """The :data:`KERNEL_ENV` variables set in ``environ``."""
    return {key: environ[key] for key in KERNEL_ENV if key in environ}


# -- files that travel with the jobs ------------------------------------------------------------
@dataclass(frozen=True)
class FileBlob:
    """A file's bytes, to hand a job a file the worker's machine may not have (a model checkpoint):
    :meth:`path` writes it, once per machine and content, to :func:`blob_dir` and returns that
    path."""

    name: str
    data: bytes

    @classmethod
    def read(cls, path: Path | str) -> 'FileBlob':
        path = Path(path)
        return cls(path.name, path.read_bytes())

    @property
    def digest(self) -> str:
        return hashlib.sha256(self.data).hexdigest()

    def path(self) -> Path:
        target = blob_dir() / self.digest[:16] / self.name
        if not target.is_file():
            target.parent.mkdir(parents=True, exist_ok=True)
            partial = target.with_name(f'{target.name}.{os.getpid()}.part')    # one per writer
            partial.write_bytes(self.data)
            partial.replace(target)
        return target


def blob_dir() -> Path:
    """Where :class:`FileBlob` writes, content-addressed and shared by this user's processes on
    the machine: a worker ended without its exit clean-up (Ray ends its workers so) leaves no
    directory of its own behind, and each distinct file is written once, then reused."""
    return Path(tempfile.gettempdir()) / f'sgs-jobs-{os.getuid()}'


# -- running ------------------------------------------------------------------------------------
def run_jobs(fn: Callable[[Any, Any], Any], jobs: Sequence, context: Any = None,
             runner: Runner = Runner(), desc: str = 'jobs', progress: bool = True) -> list:
    """``[fn(context, job) for job in jobs]``, run where ``runner`` says; the results in the order
    of ``jobs``.

    ``fn`` must be a module-level function (the workers import it by name); ``context`` (shared by
    every job, sent once per worker) and the jobs must pickle. An exception in a job is raised here
    (catch it inside ``fn`` to keep the other jobs' results). ``progress``: a bar on stderr.

    Raises:
        JobsError: ray is not installed, or there is no Ray cluster at the address.
    """
    jobs = list(jobs)
    bar = _bar(len(jobs), desc, progress)
    try:
        if runner.ray is not None:
            return _run_ray(fn, jobs, context, runner, bar)
        if runner.workers == 1 or len(jobs) <= 1:
            out = []
            for job in jobs:
                out.append(fn(context, job))
                bar.update(1)
            return out
        return _run_pool(fn, jobs, context, runner.workers, bar)
    finally:
        bar.close()


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _bar(total: int, desc: str, progress: bool):
    if not progress:
        return _NoBar()
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit='job', file=sys.stderr)


#: the context of this worker process (set once by :func:`_start_worker`)
_worker_context: Any = None


def _start_worker(context) -> None:
    global _worker_context
    _worker_context = context


def _call_in_worker(fn, job):
    return fn(_worker_context, job)


def _run_pool(fn, jobs: list, context, workers: int, bar) -> list:
    from concurrent.futures import as_completed
    results: list = [None] * len(jobs)
    mp = multiprocessing.get_context('spawn')
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=mp,
                             initializer=_start_worker, initargs=(context,)) as pool:
        futures = {pool.submit(_call_in_worker, fn, job): i for i, job in enumerate(jobs)}
        for future in as_completed(futures):
            results[futures[future]] = future.result()
            bar.update(1)
    return results


def _ray_task(fn, context, job):
    return fn(context, job)


@contextmanager
def ray_session(runner: Runner) -> Iterator[Any]:
    """Connected to ``runner.ray`` (the connection this process has already, else a new one, shut
    down on leaving); yields the ``ray`` module.

    Raises:
        JobsError: ray is not installed, or there is no Ray cluster at the address.
    """
    missing = ray_available()
    if missing is not None:
        raise JobsError(f'ray is not installed ({RAY_INSTALL}): {missing}')
    import ray
    if ray.is_initialized():
        yield ray
        return
    _check_reachable(runner.ray)
    env = worker_env()
    options = dict(runtime_env={'env_vars': env} if env else None, log_to_driver=False,
                   configure_logging=False)
    if runner.ray == 'local':
        options.update(num_cpus=runner.workers, include_dashboard=False)
    try:
        ray.init(address=runner.ray, **options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise JobsError(f'no Ray cluster at {runner.ray}: {exc}') from None
    try:
        yield ray
    finally:
        ray.shutdown()


@contextmanager
def session(runner: Runner) -> Iterator[None]:
    """The whole of a sweep: for a Ray runner, connected once (:func:`ray_session`) so that every
    :func:`run_jobs` inside reuses the connection and a missing cluster is found before any work;
    nothing for a pool.

    Raises:
        JobsError: as :func:`ray_session`.
    """
    if runner.ray is None:
        yield
        return
    with ray_session(runner):
        yield


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """For a HOST:PORT or ray://HOST:PORT address, that something listens there (``ray.init`` keeps
    retrying an address where nothing does, for many minutes)."""
    if address in ('auto', 'local'):
        return
    host, _, port = address.removeprefix('ray://').rpartition(':')
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as exc:
        raise JobsError(f'nothing answers at {address} ({exc.strerror or exc}); start the head '
                        'there with `ray start --head`, or give its address') from None


def _run_ray(fn, jobs: list, context, runner: Runner, bar) -> list:
    with ray_session(runner) as ray:
        task = ray.remote(num_cpus=1)(_ray_task)
        shared = ray.put(context)
        refs = [task.remote(fn, shared, job) for job in jobs]
        index = {ref: i for i, ref in enumerate(refs)}
        results: list = [None] * len(jobs)
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                results[index[ref]] = ray.get(ref)
                bar.update(1)
        return results
