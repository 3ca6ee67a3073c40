"""Loading and checking excitation datasets written by the collect tool."""
import logging

import numpy as np
import pytest

from soft_gripper_sdre.learning.dataset import DatasetError, load_record, load_records
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.learning.collect import collect_signal, write_record

N = 300


@pytest.fixture(scope='module')
def record():
    """0.3 s of u1 collected on the simulated finger with 10 µm measurement noise."""
    return collect_signal('u1', SimConfig(scene='finger', noise_std=1e-5, seed=1),
                          duration=N * 1e-3)


def write(path, record, **changes):
    """Write ``record`` with some arrays replaced (None removes one) and return the path."""
    arrays = {k: v for k, v in {**record, **changes}.items() if v is not None}
    return write_record(path, arrays)


def test_collected_file_round_trips(tmp_path, record):
    """Every array load_record returns equals what the collect tool wrote."""
    rec = load_record(write(tmp_path / 'u1.npz', record))
    assert rec.name == 'u1' and rec.dt == 1e-3 and rec.noise_std == 1e-5
    for key in ('t', 'u', 'tip', 'rest_tip', 'vel_true', 'acc_true'):
        np.testing.assert_array_equal(getattr(rec, key), record[key], err_msg=key)
    assert rec.t.shape == (N,) and rec.u.shape == (N, 2) and rec.tip.shape == (N, 3)


def test_load_records_keys_by_signal_name(tmp_path, record):
    """load_records reads <dir>/<name>.npz for each name, in order."""
    for name in ('u1', 'x1'):
        write(tmp_path / f'{name}.npz', record)
    records = load_records(tmp_path, ['x1', 'u1'])
    assert list(records) == ['x1', 'u1'] and records['x1'].name == 'x1'


def test_missing_file(tmp_path):
    """A missing file is a DatasetError naming it."""
    path = tmp_path / 'u1.npz'
    with pytest.raises(DatasetError, match='no such dataset file') as exc:
        load_record(path)
    assert str(path) in str(exc.value)


def test_missing_file_in_a_directory(tmp_path, record):
    """load_records names the one file that is missing."""
    write(tmp_path / 'u1.npz', record)
    with pytest.raises(DatasetError, match='u2.npz: no such dataset file'):
        load_records(tmp_path, ['u1', 'u2'])


def test_truncated_file(tmp_path, record):
    """Half a file is a DatasetError naming the file and saying it is truncated."""
    full = write(tmp_path / 'full.npz', record).read_bytes()
    path = tmp_path / 'u1.npz'
    path.write_bytes(full[:len(full) // 2])
    with pytest.raises(DatasetError, match='truncated') as exc:
        load_record(path)
    assert str(path) in str(exc.value)


@pytest.mark.parametrize('key, value, match', [
    ('u', np.zeros((N, 3)), r'u must have shape \(300, 2\)'),
    ('u', np.zeros((N - 1, 2)), r'u must have shape \(300, 2\)'),
    ('tip', np.zeros((N, 2)), r'tip must have shape \(300, 3\)'),
    ('acc_true', np.zeros((N, 2)), r'acc_true must have shape \(300, 3\)'),
    ('t', np.zeros((N, 1)), 't must be a 1-D array'),
    ('rest_tip', np.zeros(2), 'rest_tip must be 3 finite numbers'),
    ('tip', None, r"missing arrays \['tip'\]"),
])
def test_wrong_array_shape(tmp_path, record, key, value, match):
    """An array of the wrong shape (or a missing one) is a DatasetError naming file and array."""
    path = write(tmp_path / 'u1.npz', record, **{key: value})
    with pytest.raises(DatasetError, match=match) as exc:
        load_record(path)
    assert str(path) in str(exc.value)


def test_wrong_dt_shape(tmp_path, record):
    """A dt that is not a scalar is a DatasetError naming the file."""
    path = write(tmp_path / 'u1.npz', record, dt=np.array([1e-3, 1e-3]))
    with pytest.raises(DatasetError, match='dt'):
        load_record(path)


def test_time_not_sampled_at_dt(tmp_path, record):
    """t spaced differently from the stored dt is refused."""
    path = write(tmp_path / 'u1.npz', record, dt=np.float64(2e-3))
    with pytest.raises(DatasetError, match='not sampled at dt'):
        load_record(path)


def test_mismatched_dt_between_files(tmp_path, record):
    """load_records refuses records with different Δt and names both files."""
    write(tmp_path / 'u1.npz', record)
    write(tmp_path / 'u2.npz', record, t=np.arange(N) * 2e-3, dt=np.float64(2e-3))
    with pytest.raises(DatasetError, match=r'u2\.npz: dt = 0\.002 s differs from u1\.npz'):
        load_records(tmp_path, ['u1', 'u2'])


def test_mismatched_rest_pose_between_files(tmp_path, record):
    """load_records refuses records from a different finger mount (rest tip 1 mm away)."""
    write(tmp_path / 'u1.npz', record)
    write(tmp_path / 'u2.npz', record, rest_tip=record['rest_tip'] + [1e-3, 0.0, 0.0])
    with pytest.raises(DatasetError, match=r'u2\.npz: rest_tip .* differs from u1\.npz'):
        load_records(tmp_path, ['u1', 'u2'])


def test_nan_samples_are_dropped_with_a_warning(tmp_path, record, caplog):
    """NaN samples leave the longest finite run; the warning names the file and both counts."""
    tip = record['tip'].copy()
    tip[[20, 250], 1] = np.nan               # finite runs [0, 20), [21, 250), [251, 300)
    acc = record['acc_true'].copy()
    acc[21, 0] = np.inf                      # longest finite run is now [22, 250)
    path = write(tmp_path / 'u1.npz', record, tip=tip, acc_true=acc)
    with caplog.at_level(logging.WARNING, logger='soft_gripper_sdre.learning.dataset'):
        rec = load_record(path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, warnings
    assert str(path) in warnings[0]
    assert '3 samples with NaN/Inf' in warnings[0] and '[22, 250)' in warnings[0]
    assert '(72 dropped)' in warnings[0]
    assert rec.t.size == rec.u.shape[0] == rec.tip.shape[0] == rec.acc_true.shape[0] == 228
    np.testing.assert_array_equal(rec.t, record['t'][22:250])
    np.testing.assert_array_equal(rec.tip, record['tip'][22:250])
    np.testing.assert_array_equal(rec.vel_true, record['vel_true'][22:250])
    assert all(np.isfinite(getattr(rec, k)).all()
               for k in ('t', 'u', 'tip', 'vel_true', 'acc_true'))


def test_clean_file_logs_no_warning(tmp_path, record, caplog):
    """A finite record loads silently."""
    with caplog.at_level(logging.WARNING, logger='soft_gripper_sdre.learning.dataset'):
        load_record(write(tmp_path / 'u1.npz', record))
    assert not caplog.records


@pytest.mark.parametrize('bad_rows', [
    pytest.param(np.arange(N), id='all-nan'),
    pytest.param(np.arange(0, N, 2), id='every-other-nan'),
])
def test_record_without_a_usable_finite_run_is_refused(tmp_path, record, bad_rows):
    """All-NaN samples, or NaN every other sample, leave no 10 consecutive finite samples:
    refused."""
    tip = record['tip'].copy()
    tip[bad_rows] = np.nan
    path = write(tmp_path / 'u1.npz', record, tip=tip)
    with pytest.raises(DatasetError, match='fewer than 10 consecutive finite samples') as exc:
        load_record(path)
    assert str(path) in str(exc.value)


class _OpensAFile:
    """Unpickling this object calls open(marker, 'w'): a stand-in for arbitrary code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, 'w'))


@pytest.mark.parametrize('content', [bytes(range(256)) * 4, b'x'], ids=['random bytes', 'one byte'])
def test_a_file_that_is_not_an_npz_is_named_as_such(tmp_path, content):
    path = tmp_path / 'u1.npz'
    path.write_bytes(content)
    with pytest.raises(DatasetError) as exc:
        load_record(path)
    assert str(exc.value).startswith(f'{path}: not an .npz archive (a zip file)')
    assert 'pickled' not in str(exc.value)


def test_pickled_payload_is_refused_without_running_it(tmp_path, record):
    """An npz carrying an object array is refused with a clear message; the payload never runs."""
    marker = tmp_path / 'code_ran'
    path = tmp_path / 'u1.npz'
    payload = np.empty(1, dtype=object)
    payload[0] = _OpensAFile(marker)
    np.savez(path, **{k: v for k, v in record.items()}, extra=payload)
    with pytest.raises(DatasetError, match='pickled objects') as exc:
        load_record(path)
    assert str(path) in str(exc.value)
    assert not marker.exists(), 'the pickled payload was executed'
    with np.load(path, allow_pickle=True) as d:       # the payload is live: a trusting load runs it
        d['extra'][0].close()
    assert marker.exists()
