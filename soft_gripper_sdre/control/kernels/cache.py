"""The kernels' decorator and the rule that keeps numba's on-disk cache of them valid.

numba keys a cached kernel on its own source file alone: a kernel that calls a kernel of another
file keeps, in its cached machine code, the callee as it was compiled, after the callee's file
changed (numba issue #1833). So the cache is held to the kernel modules as a whole: every kernel is
defined with :func:`kernel`, which registers its dispatcher, and :func:`invalidate_stale_cache`
(run at the import of :mod:`~soft_gripper_sdre.control.kernels`, before any kernel runs) imports
every kernel module (every module of this package), compares the digest of their sources
(:func:`source_digest`, this file's included, so a change of the decorator's options counts too)
with the one kept in the kernels' cache directory, and where they differ empties every kernel's
cache index before it writes the new digest. docs/design/compiled_kernel.md, "Compilation and the
cache".
"""
from __future__ import annotations

import glob
import hashlib
import importlib
import os
from pathlib import Path
import tempfile

from numba import njit

#: the directory of the kernel modules: this package's
HERE = Path(__file__).resolve().parent
#: the kernel modules, by name, in that directory: every module of the package, its
#: ``__init__.py`` (the record dtypes, :func:`~soft_gripper_sdre.control.kernels.warm_up`) included
SOURCES = '*.py'
#: the file, in the kernels' cache directory, that holds the digest the cache was filled for
DIGEST_FILE = 'kernel_sources.sha256'

#: every kernel's dispatcher, in the order they were defined
KERNELS: list = []

_njit = njit(cache=True, error_model='numpy', nogil=True)


def kernel(py_func):
    """Compile ``py_func`` as a kernel: cached on disk, IEEE division (x / 0 = ±inf or NaN, never
    an exception), no GIL; its dispatcher is registered in :data:`KERNELS`."""
    dispatcher = _njit(py_func)
    KERNELS.append(dispatcher)
    return dispatcher


def kernel_sources(directory: Path = HERE) -> list[Path]:
    """The kernel modules in ``directory`` (every ``*.py``), sorted by name."""
    return sorted(Path(directory).glob(SOURCES))


def source_digest(directory: Path = HERE) -> str:
    """sha256 (hex) of the kernel modules' names and bytes: any edit, new file or removed file
    changes it; the same files elsewhere give the same digest."""
    digest = hashlib.sha256()
    for path in kernel_sources(directory):
        data = path.read_bytes()
        for part in (path.name.encode(), len(data).to_bytes(8, 'little'), data):
            digest.update(part)
    return digest.hexdigest()


def import_kernel_modules() -> None:
    """Import every kernel module of this package (:func:`kernel_sources`; the package itself is
    the one importing them), which registers its kernels."""
    package = __name__.rpartition('.')[0]
    for path in kernel_sources():
        if path.stem != '__init__':
            importlib.import_module(f'{package}.{path.stem}')


def cache_directories() -> dict[str, list]:
    """The directories numba caches the registered kernels in, each with its kernels, as numba
    reports them (``stats.cache_path``): beside their sources (``__pycache__``), or numba's
    per-user directory, or ``NUMBA_CACHE_DIR``. Kernels without an on-disk cache (numba's JIT
    disabled) are left out."""
    directories: dict[str, list] = {}
    for dispatcher in KERNELS:
        stats = getattr(dispatcher, 'stats', None)
        if stats is not None and stats.cache_path:
            directories.setdefault(stats.cache_path, []).append(dispatcher)
    return directories


def read_digest(directory: str) -> str | None:
    """The digest kept in the cache ``directory``; None if there is none or it cannot be read."""
    try:
        return (Path(directory) / DIGEST_FILE).read_text(encoding='ascii').strip()
    except (OSError, UnicodeDecodeError):
        return None


def _write_atomically(path: Path, text: str) -> None:
    """``text`` into ``path`` through a file of its own renamed over it, so that a reader sees the
    old or the new text, never a part."""
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f'{path.name}.', suffix='.tmp')
    try:
        with os.fdopen(fd, 'w', encoding='ascii') as f:
            f.write(text + '\n')
        os.replace(temporary, path)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise


def _forget(dispatcher, directory: Path) -> None:
    """Empty ``dispatcher``'s cache index (numba's ``Cache.flush``) and delete its data files in
    ``directory``. numba names a kernel's data files by their number in its index and writes the
    index before the data: after a flush alone, a process that finds the first new entry while
    its data file is still being written would read the stale file of the same name. A missing
    data file numba treats as no entry (it compiles)."""
    dispatcher._cache.flush()
    base = dispatcher._cache._cache_file._index_name.removesuffix('.nbi')
    for data in directory.glob(glob.escape(base) + '.*.nbc'):
        data.unlink(missing_ok=True)


def invalidate_stale_cache() -> list[str]:
    """Import every kernel module, empty the cache index of every kernel whose cache directory does
    not hold the kernel modules' :func:`source_digest`, then write that digest there; returns the
    cache directories so refreshed. Call it before any kernel runs (a kernel loaded from the cache
    before keeps what it loaded).

    A directory that is not writable is left alone (numba cannot cache there either). Emptying an
    index is numba's own ``Cache.flush``, which replaces the index file atomically with one that
    lists nothing, so the kernel compiles on its next call and caches itself again; its data files
    are deleted with it (:func:`_forget`), so no new index entry can name a stale one; the digest is
    written atomically, and only once every index there is emptied. Processes doing this at once
    at most empty an index another one has just filled (it compiles again), never leave one stale.
    """
    import_kernel_modules()
    digest = source_digest()
    refreshed = []
    for path, group in cache_directories().items():
        if not os.access(path, os.W_OK) or read_digest(path) == digest:
            continue
        try:
            for dispatcher in group:
                _forget(dispatcher, Path(path))
            _write_atomically(Path(path) / DIGEST_FILE, digest)
        except OSError:         # gone or unwritable meanwhile: the next process tries again
            continue
        refreshed.append(path)
    return refreshed
