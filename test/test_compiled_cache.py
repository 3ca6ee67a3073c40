"""numba's on-disk cache of the kernels held to the kernel modules' sources as a whole
(control/kernels/cache.py): the digest covers every kernel module, an edit of a callee's module
reaches its callers in another module, and an unchanged tree loads from the cache.

The slow tests run fresh interpreters on a copy of the kernel modules in a package tree of their
own, with a kernel pair of two more modules (a caller and, in another file, the callee it calls),
defined with the package's decorator, and NUMBA_CACHE_DIR in a temporary directory: importing
control.kernels there runs the rule as it runs in the package, and only the pair compiles.
"""
import inspect
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

import soft_gripper_sdre.control.kernels  # noqa: F401  (runs the rule)
from soft_gripper_sdre.control.kernels.cache import (
    DIGEST_FILE,
    KERNELS,
    cache_directories,
    kernel_sources,
    read_digest,
    source_digest,
)

CALLEE = '''from soft_gripper_sdre.control.kernels.cache import kernel

OFFSET = {offset}


@kernel
def callee(x):
    return x + OFFSET
'''
CALLER = '''from soft_gripper_sdre.control.kernels.cache import kernel
from soft_gripper_sdre.control.kernels.pair_callee import callee


@kernel
def caller(x):
    return 2.0 * callee(x)
'''
#: in a fresh interpreter: the caller's value at 1 and its cache hits and misses
PROBE = ('import json; from soft_gripper_sdre.control.kernels import pair_caller as m; '
         'value = m.caller(1.0); s = m.caller.stats; '
         'print(json.dumps([value, sum(s.cache_hits.values()), sum(s.cache_misses.values())]))')


def kernel_tree(root: Path, offset: float) -> Path:
    """soft_gripper_sdre/control/kernels under ``root`` with the kernel modules and the pair (the
    callee adding ``offset``); its kernels directory."""
    kernels = root / 'soft_gripper_sdre' / 'control' / 'kernels'
    kernels.mkdir(parents=True)
    for package in (kernels.parent.parent, kernels.parent):
        (package / '__init__.py').write_text('')
    for path in kernel_sources():
        shutil.copyfile(path, kernels / path.name)
    (kernels / 'pair_callee.py').write_text(CALLEE.format(offset=offset))
    (kernels / 'pair_caller.py').write_text(CALLER)
    return kernels


def start(root: Path, cache: Path) -> subprocess.Popen:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(root))
    return subprocess.Popen([sys.executable, '-c', PROBE], cwd=root, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def result(process: subprocess.Popen) -> tuple[float, int, int]:
    """(caller(1.0), cache hits, cache misses) of a process :func:`start` started."""
    out, err = process.communicate(timeout=240)
    assert process.returncode == 0, err[-3000:]
    value, hits, misses = json.loads(out)
    return value, hits, misses


def probe(root: Path, cache: Path) -> tuple[float, int, int]:
    return result(start(root, cache))


def digest_files(cache: Path) -> list[Path]:
    return list(cache.rglob(DIGEST_FILE))


def test_the_digest_covers_every_kernel_module(tmp_path):
    """Every kernel is defined in a module the digest reads, every such module is imported (its
    kernels registered) by control.kernels, and a new kernel module or an edit of one changes the
    digest; a file that is not a module does not."""
    sources = kernel_sources()
    assert {Path(inspect.getfile(k.py_func)) for k in KERNELS} <= set(sources)
    assert {'__init__.py', 'cache.py', 'sdre.py', 'kf.py', 'general.py'} <= {
        p.name for p in sources}
    assert all(f'soft_gripper_sdre.control.kernels.{p.stem}'.removesuffix('.__init__')
               in sys.modules for p in sources)
    copy = kernel_tree(tmp_path, 1.0)
    for extra in ('pair_callee.py', 'pair_caller.py'):
        (copy / extra).unlink()
    assert source_digest(copy) == source_digest()
    (copy / 'notes.txt').write_text('X = 1\n')
    assert source_digest(copy) == source_digest()
    (copy / 'new.py').write_text('')
    with_new = source_digest(copy)
    assert with_new != source_digest()
    kf = copy / 'kf.py'
    kf.write_bytes(kf.read_bytes().replace(b'Joseph form', b'Joseph-form'))
    assert source_digest(copy) not in (with_new, source_digest())


def test_the_kernels_cache_directory_holds_the_digest_of_their_sources():
    directories = cache_directories()
    assert sum(len(kernels) for kernels in directories.values()) == len(KERNELS)
    for directory in directories:
        assert read_digest(directory) == source_digest()


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_an_edit_of_a_callees_module_reaches_its_caller_in_another(tmp_path):
    """The caller is cached with the callee's constant; after an edit of the callee's module alone,
    two interpreters started together both compute with the new constant (numba alone would load
    the caller with the old one, its own file unchanged), and the next loads that from the cache."""
    root, cache = tmp_path / 'tree', tmp_path / 'cache'
    control = kernel_tree(root, offset=1.0)
    assert probe(root, cache) == (4.0, 0, 1)
    (control / 'pair_callee.py').write_text(CALLEE.format(offset=2.0))
    together = [start(root, cache) for _ in range(2)]
    assert [result(process)[0] for process in together] == [6.0, 6.0]
    assert probe(root, cache) == (6.0, 1, 0)
    (digest,) = digest_files(cache)
    assert read_digest(digest.parent) == source_digest(control)
    assert not list(cache.rglob('*.tmp'))


def test_a_refreshed_cache_keeps_no_data_file_a_new_index_entry_could_name(tmp_path):
    """numba writes a new index entry before its data file and numbers the file as the flushed
    entry was: the refresh deletes the stale data files with the index, so a process that finds
    the entry early reads nothing (and compiles) instead of the old machine code."""
    root, cache = tmp_path / 'tree', tmp_path / 'cache'
    control = kernel_tree(root, offset=1.0)
    assert probe(root, cache) == (4.0, 0, 1)
    assert list(cache.rglob('pair_caller.*.nbc')) and list(cache.rglob('pair_callee.*.nbc'))
    (control / 'pair_callee.py').write_text(CALLEE.format(offset=2.0))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(root))
    subprocess.run([sys.executable, '-c', 'import soft_gripper_sdre.control.kernels'], cwd=root,
                   env=env, check=True, timeout=240)                 # the refresh, no kernel run
    assert not list(cache.rglob('*.nbc'))
    assert probe(root, cache) == (6.0, 0, 1)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_an_unchanged_tree_loads_its_kernels_from_the_cache(tmp_path):
    """The second interpreter on the same sources loads the caller from the cache (no
    compilation) and leaves the digest as the first wrote it."""
    root, cache = tmp_path / 'tree', tmp_path / 'cache'
    kernel_tree(root, offset=1.0)
    assert probe(root, cache) == (4.0, 0, 1)
    (digest,) = digest_files(cache)
    written = digest.stat().st_mtime_ns, digest.read_text()
    assert probe(root, cache) == (4.0, 1, 0)
    assert (digest.stat().st_mtime_ns, digest.read_text()) == written
