"""The train tool on data collected from the real simulator: its refusals of bad arguments in
this process (``run_main``), a tiny training run as a real subprocess."""
import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.learning.collect import collect_signal, write_record
from soft_gripper_sdre.tools.learning.train import main

SIGNALS = DATA_VARIANTS['identifying'] + (VALIDATION,)
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def run_train(*args, cwd=None):
    return subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.learning.train', *args],
                          capture_output=True, text=True, timeout=50, cwd=cwd)


@pytest.fixture(scope='module')
def data_dir(tmp_path_factory):
    """0.5 s of every signal the default variant needs, written as the collect tool writes them."""
    out = tmp_path_factory.mktemp('excitation')
    for i, name in enumerate(SIGNALS):
        write_record(out / f'{name}.npz',
                     collect_signal(name, SimConfig(scene='finger', seed=i), duration=0.5))
    return out


def finite(value):
    """True when every number inside a nested dict/list is finite."""
    if isinstance(value, dict):
        return all(finite(v) for v in value.values())
    if isinstance(value, list):
        return all(finite(v) for v in value)
    return not isinstance(value, float) or math.isfinite(value)


def test_missing_data_dir_is_a_usage_error(tmp_path, run_main):
    """A data directory that does not exist: exit 2, the message names the file, nothing written."""
    missing = tmp_path / 'no_such_dir'
    proc = run_main(main, '--data', str(missing), '--out', str(tmp_path / 'out'))
    assert proc.returncode == 2, proc.stderr
    assert 'error:' in proc.stderr and str(missing / 'u1.npz') in proc.stderr
    assert 'no such dataset file' in proc.stderr and 'Traceback' not in proc.stderr
    assert not (tmp_path / 'out').exists()


def test_missing_signal_file_is_a_usage_error(tmp_path, data_dir, run_main):
    """A data directory lacking one signal of the variant: exit 2 naming that file."""
    partial = tmp_path / 'partial'
    shutil.copytree(data_dir, partial)
    (partial / 'x2.npz').unlink()
    proc = run_main(main, '--data', str(partial), '--out', str(tmp_path / 'out'))
    assert proc.returncode == 2, proc.stderr
    assert 'x2.npz: no such dataset file' in proc.stderr and 'Traceback' not in proc.stderr


def test_unknown_preset_is_a_usage_error(tmp_path, data_dir, run_main):
    """--preset outside the known ones: exit 2 listing the choices."""
    proc = run_main(main, '--data', str(data_dir), '--out', str(tmp_path / 'out'),
                    '--preset', 'turbo')
    assert proc.returncode == 2
    assert ("invalid choice: 'turbo'" in proc.stderr and 'default' in proc.stderr
            and 'paper' in proc.stderr)
    assert not (tmp_path / 'out').exists()


def test_zero_epochs_is_a_usage_error(tmp_path, data_dir, run_main):
    proc = run_main(main, '--data', str(data_dir), '--out', str(tmp_path / 'out'), '--epochs', '0')
    assert proc.returncode == 2
    assert '--epochs must be >= 1' in proc.stderr


@pytest.mark.parametrize('args, why', [
    (('--sv-penalty', '-1'), 'sv_penalty must be finite and >= 0'),
    (('--sv-penalty', 'nan'), 'sv_penalty must be finite and >= 0'),
    (('--sv-penalty', '1', '--sv-floor', '0'), 'sv_floor must be finite and > 0')])
def test_bad_singular_value_penalty_is_a_usage_error(tmp_path, data_dir, args, why, run_main):
    proc = run_main(main, '--data', str(data_dir), '--out', str(tmp_path / 'out'), *args)
    assert proc.returncode == 2 and why in proc.stderr and 'Traceback' not in proc.stderr
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('args, why', [(('--patience', '0'), 'patience must be an int >= 1'),
                                       (('--jitter', 'nan'), '--jitter must be in [0, 1e-3)'),
                                       (('--jitter', '0.01'), '--jitter must be in [0, 1e-3)')])
def test_bad_patience_or_jitter_is_a_usage_error(tmp_path, data_dir, args, why, run_main):
    proc = run_main(main, '--data', str(data_dir), '--out', str(tmp_path / 'out'), *args)
    assert proc.returncode == 2 and why in proc.stderr and 'Traceback' not in proc.stderr
    assert not (tmp_path / 'out').exists()


def test_tiny_training_run_writes_model_metrics_and_figures(tmp_path, data_dir):
    """3 epochs on collected data write a loadable model.pt, finite metrics.json and both
    figures."""
    out = tmp_path / 'run'
    proc = run_train('--data', str(data_dir), '--out', str(out), '--epochs', '3', '--seed', '1')
    assert proc.returncode == 0, proc.stderr
    assert 'u4 R² vs true acceleration' in proc.stdout

    metrics = json.loads((out / 'metrics.json').read_text())
    assert set(metrics) >= {
        'preset', 'variant', 'epochs_run', 'best_epoch', 'train_seconds', 'u4_r2_true',
        'u4_r2_ls_baseline', 'u4_true_variance_below_10hz', 'derivative_errors', 'G2_at_origin',
        'G2_column_angles_deg', 'final_train_loss', 'best_val_loss'}
    assert finite(metrics), metrics
    assert metrics['preset'] == 'default' and metrics['variant'] == 'identifying'
    assert metrics['epochs_run'] == 3 and 0 <= metrics['best_epoch'] < 3
    assert set(metrics['u4_r2_true']) == set(metrics['u4_r2_ls_baseline']) == {'X', 'Y'}
    assert set(metrics['derivative_errors']) == set(SIGNALS)
    for err in metrics['derivative_errors'].values():
        assert (set(err) == {'vel_rmse', 'acc_rmse', 'acc_r2'}
                and all(len(v) == 2 for v in err.values()))
    assert np.shape(metrics['G2_at_origin']) == (2, 2)
    assert metrics['best_val_loss'] > 0 and metrics['final_train_loss'] > 0
    timings = metrics['timings']        # the report's own time is printed only
    assert list(timings) == ['read', 'labels', 'training', 'label_stage', 'simulation_stage',
                             'checkpoint', 'total']
    assert all(v >= 0 for v in timings.values())
    assert timings['simulation_stage'] < 0.1       # off in this preset: the best weights loaded
    assert timings['label_stage'] <= timings['training'] + 1e-3
    assert timings['read'] + timings['labels'] + timings['training'] + timings['checkpoint'] \
        <= timings['total'] + 4e-3

    model = SDCModel(out / 'model.pt')
    # the checkpoint is written before its own writing is timed: metrics.json's less the timings
    assert model.metrics == {k: v for k, v in metrics.items() if k != 'timings'}
    assert model.settings['epochs'] == 3 and model.settings['seed'] == 1
    assert model.data['train_signals'] == list(DATA_VARIANTS['identifying'])
    assert len(model.history['val_loss']) == 3
    np.testing.assert_allclose(model.G(np.zeros(4))[0, 2:], metrics['G2_at_origin'], rtol=1e-12)

    for name in ('fig2_loss.png', 'fig3_accel_u4.png'):
        raw = (out / name).read_bytes()
        assert raw.startswith(PNG_MAGIC) and len(raw) > 10_000, name


def test_install_copies_the_written_checkpoint_and_its_metrics(data_dir, tmp_path, monkeypatch):
    """``--install`` puts the run's model.pt and metrics.json where the package's shipped model
    lives (here a temporary stand-in for it), byte for byte."""
    from soft_gripper_sdre.tools.learning import train
    shipped = tmp_path / 'models' / 'default.pt'
    monkeypatch.setattr(train, 'DEFAULT_MODEL', shipped)
    out = tmp_path / 'run'
    assert main(['--data', str(data_dir), '--out', str(out), '--epochs', '1', '--install']) == 0
    assert shipped.read_bytes() == (out / 'model.pt').read_bytes()
    assert shipped.with_suffix('.json').read_text() == (out / 'metrics.json').read_text()
    assert json.loads(shipped.with_suffix('.json').read_text())['epochs_run'] == 1
