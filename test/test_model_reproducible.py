"""Reproducible training: the stopping rule, the fixed thread count, and (slow) `make model`
reproducing the shipped model from nothing.

Training is deterministic on the machine kind CI runs on (one thread, deterministic algorithms,
seeded shuffles), so the slow test compares exactly: the same data fingerprint, the same epochs, the
same u4 R² and the same weights as soft_gripper_sdre/models/default.pt and its default.json.
"""
from dataclasses import replace
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from soft_gripper_sdre.learning.model import DEFAULT_MODEL, read_checkpoint
from soft_gripper_sdre.learning.training import PRESETS, TrainSettings, train
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.collect import collect_signal


@pytest.fixture(scope='module')
def data():
    """0.5 s of x1 (training) and u4 (validation) from the simulated finger: true states and
    accelerations."""
    def arrays(name):
        r = collect_signal(name, SimConfig(scene='finger'), duration=0.5)
        return np.hstack([r['tip_true'][:, :2] - r['rest_tip'][:2], r['vel_true'][:, :2]]), r['u'], r['acc_true'][:, :2]
    return arrays('x1') + arrays('u4')


def test_the_default_preset_runs_its_whole_budget(data):
    """No early stop (patience None): every epoch runs, and the best validation epoch's weights are kept."""
    assert PRESETS['default'].patience is None and PRESETS['paper'].patience is None
    result = train(*data, replace(PRESETS['default'], epochs=12))
    assert len(result.val_loss) == 12
    assert result.val_loss[result.best_epoch] == min(result.val_loss)


def test_patience_stops_after_that_many_epochs_without_a_new_best(data):
    """At learning rate 0 the validation loss never improves on epoch 0's: the run ends
    ``patience`` epochs later."""
    result = train(*data, replace(PRESETS['default'], epochs=60, lr=0.0, patience=3))
    assert len(result.val_loss) == 4 and result.best_epoch == 0


@pytest.mark.parametrize('patience', [0, -2, 2.5])
def test_patience_must_be_a_positive_int_or_none(patience):
    with pytest.raises(ValueError, match='patience'):
        TrainSettings(patience=patience)


def test_training_fixes_its_thread_count_and_restores_the_callers(data):
    """The same bits whatever thread count and determinism mode the caller runs torch with, and
    both are as the caller left them afterwards."""
    settings = replace(PRESETS['default'], epochs=3)
    old_threads = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results.append(train(*data, settings))
            assert torch.get_num_threads() == threads and not torch.are_deterministic_algorithms_enabled()
    finally:
        torch.set_num_threads(old_threads)
    a, b = results
    assert a.val_loss == b.val_loss
    for key, value in a.net.state_dict().items():
        assert torch.equal(value, b.net.state_dict()[key]), key


def run_tool(tool, *args, timeout):
    proc = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.{tool}', *args],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_collect_then_train_reproduces_the_shipped_checkpoint(tmp_path):
    data, out = tmp_path / 'excitation', tmp_path / 'train'
    run_tool('collect', '--out', str(data), timeout=300)
    run_tool('train', '--data', str(data), '--out', str(out), timeout=800)

    shipped = json.loads(DEFAULT_MODEL.with_suffix('.json').read_text())
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['u4_r2_true'] == shipped['u4_r2_true']
    assert (metrics['epochs_run'], metrics['best_epoch']) == (shipped['epochs_run'], shipped['best_epoch'])
    assert metrics['derivative_errors'] == shipped['derivative_errors']
    assert metrics['G2_at_origin'] == shipped['G2_at_origin']

    ours, theirs = read_checkpoint(out / 'model.pt'), read_checkpoint(DEFAULT_MODEL)
    assert ours['data']['fingerprint'] == theirs['data']['fingerprint']     # the same training arrays
    assert ours['settings'] == theirs['settings']
    assert ours['state_dict'].keys() == theirs['state_dict'].keys()
    for key, weights in ours['state_dict'].items():
        assert torch.equal(weights, theirs['state_dict'][key]), key
    assert ours['history'] == theirs['history']
