"""Reading and checking excitation datasets (the ``.npz`` files the collect tool writes)."""
from __future__ import annotations

from dataclasses import dataclass
import logging
from pathlib import Path
import zipfile

import numpy as np

log = logging.getLogger(__name__)

#: first bytes of a zip archive: an .npz dataset, and also a torch.save checkpoint
ZIP_MAGIC = b'PK\x03\x04'
REQUIRED = {'t': 1, 'u': 2, 'tip': 3, 'rest_tip': None, 'dt': None}
WIDTH = {'u': 2, 'tip': 3, 'tip_true': 3, 'vel_true': 3, 'acc_true': 3}


class DatasetError(ValueError):
    """A dataset file cannot be used; the message names the file and the problem."""


@dataclass
class Record:
    """One excitation record (SI)."""

    name: str
    t: np.ndarray
    u: np.ndarray
    tip: np.ndarray
    rest_tip: np.ndarray
    dt: float
    vel_true: np.ndarray | None = None
    acc_true: np.ndarray | None = None
    noise_std: float = 0.0


def load_record(path: Path) -> Record:
    """Load and validate one file; non-finite samples are dropped with a warning saying how many.

    Raises:
        DatasetError: missing, truncated or not an npz, missing arrays, wrong shapes, bad Δt.
    """
    path = Path(path)
    arrays = _read_arrays(path)
    n, dt, noise_std = _check_arrays(path, arrays)
    arrays = _longest_finite_run(path, arrays, n)
    return Record(name=path.stem, t=arrays['t'], u=arrays['u'], tip=arrays['tip'],
                  rest_tip=arrays['rest_tip'], dt=dt, vel_true=arrays.get('vel_true'),
                  acc_true=arrays.get('acc_true'), noise_std=noise_std)


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the archive at ``path``, read without unpickling anything."""
    if not path.is_file():
        raise DatasetError(f'{path}: no such dataset file')
    try:
        with path.open('rb') as f:
            head = f.read(len(ZIP_MAGIC))
    except OSError as exc:
        raise DatasetError(f'{path}: cannot be read ({exc})') from None
    if head != ZIP_MAGIC:
        raise DatasetError(f'{path}: not an .npz archive (a zip file); it starts with {head!r} '
                           '(corrupt, or another kind of file)')
    try:
        with np.load(path, allow_pickle=False) as d:
            return {k: d[k] for k in d.files}
    except (ValueError, zipfile.BadZipFile, OSError, EOFError) as exc:
        if isinstance(exc, ValueError) and 'allow_pickle' in str(exc):
            # an object array: unpickling it could run code
            raise DatasetError(f'{path}: holds pickled objects, refused unread (a dataset is plain '
                               'numeric arrays)') from None
        raise DatasetError(f'{path}: unreadable or truncated ({exc})') from None


def _check_arrays(path: Path, arrays: dict[str, np.ndarray]) -> tuple[int, float, float]:
    """The record's sample count, Δt [s] and noise σ [m], once its arrays are found complete, of
    matching shapes and on a uniform grid of Δt."""
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise DatasetError(f'{path}: missing arrays {missing}')
    n = arrays['t'].shape[0] if arrays['t'].ndim == 1 else -1
    if n < 10:
        raise DatasetError(f'{path}: t must be a 1-D array of at least 10 samples, '
                           f'got shape {arrays["t"].shape}')
    for key, width in WIDTH.items():
        if key in arrays and arrays[key].shape != (n, width):
            raise DatasetError(f'{path}: {key} must have shape ({n}, {width}), '
                               f'got {arrays[key].shape}')
    if arrays['rest_tip'].shape != (3,) or not np.all(np.isfinite(arrays['rest_tip'])):
        raise DatasetError(f'{path}: rest_tip must be 3 finite numbers, got {arrays["rest_tip"]!r}')
    try:
        dt = float(arrays['dt'].item())
        noise_std = float(arrays['noise_std'].item()) if 'noise_std' in arrays else 0.0
    except (ValueError, TypeError) as exc:
        raise DatasetError(f'{path}: dt and noise_std must be single numbers ({exc})') from None
    if not (np.isfinite(dt) and dt > 0):
        raise DatasetError(f'{path}: dt must be > 0, got {dt}')
    if not np.allclose(np.diff(arrays['t']), dt, rtol=1e-6, atol=1e-12):
        raise DatasetError(f'{path}: t is not sampled at dt = {dt} s')
    return n, dt, noise_std


def _longest_finite_run(path: Path, arrays: dict[str, np.ndarray],
                        n: int) -> dict[str, np.ndarray]:
    """``arrays`` with the time series cut to their longest run of finite samples (the derivative
    estimate needs a uniform grid), with a warning when that drops any."""
    keys = ['t', 'u', 'tip'] + [k for k in ('vel_true', 'acc_true') if k in arrays]
    finite = np.ones(n, dtype=bool)
    for k in keys:
        finite &= np.all(np.isfinite(arrays[k].reshape(n, -1)), axis=1)
    if finite.all():
        return arrays
    bad = int((~finite).sum())
    edges = np.flatnonzero(np.diff(np.concatenate([[0], finite.astype(int), [0]])))
    runs = edges.reshape(-1, 2)
    if len(runs) == 0:
        raise DatasetError(f'{path}: fewer than 10 consecutive finite samples '
                           '(every sample holds NaN/Inf)')
    start, stop = max(runs, key=lambda r: r[1] - r[0])
    if stop - start < 10:
        raise DatasetError(f'{path}: fewer than 10 consecutive finite samples')
    log.warning('%s: %d samples with NaN/Inf; keeping the longest finite run [%d, %d) '
                '(%d dropped)', path, bad, start, stop, n - (stop - start))
    return {k: (v[start:stop] if k in keys else v) for k, v in arrays.items()}


def load_records(directory: Path, names: list[str]) -> dict[str, Record]:
    """Load ``directory/<name>.npz`` for every name; all must share Δt and the rest pose."""
    records = {name: load_record(Path(directory) / f'{name}.npz') for name in names}
    first = next(iter(records.values()))
    for r in records.values():
        if not np.isclose(r.dt, first.dt, rtol=1e-9):
            raise DatasetError(f'{r.name}.npz: dt = {r.dt} s differs from {first.name}.npz '
                               f'({first.dt} s)')
        if not np.allclose(r.rest_tip, first.rest_tip, atol=1e-4):
            raise DatasetError(f'{r.name}.npz: rest_tip {r.rest_tip} differs from {first.name}.npz '
                               f'({first.rest_tip}); all records must come from the same finger '
                               'mount')
    return records
