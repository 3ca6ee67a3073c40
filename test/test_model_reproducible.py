"""Reproducible training: the stopping rule, the fixed thread count, and (slow) `make model`
reproducing the shipped model from nothing.

Training is deterministic on one machine (one thread, deterministic algorithms, seeded shuffles).
Across machines the bits part in the math libraries' CPU-specific kernels: OpenBLAS picks its
matrix kernels by CPU (the KF/RTS labels differ at 1e-12 between its Haswell and SkylakeX
kernels), MKL and ATen theirs for training. ``tools.graph.procs.PINNED_KERNELS`` fixes each of them
to one code path that every x86-64 machine with AVX2 and FMA runs; with them the slow test demands
the shipped checkpoint bit for bit (the same data fingerprint, epochs, u4 R² and weights as
soft_gripper_sdre/models/default.pt and its default.json). On every machine, pinned or not, it
demands the model within :data:`BAND` of the shipped one: the spread measured by perturbing the
training data at rounding level (docs/model.md, "The same model on another machine").
"""
from dataclasses import asdict, replace
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from soft_gripper_sdre.learning.model import DEFAULT_MODEL, read_checkpoint
from soft_gripper_sdre.learning.train_settings import PRESETS, TrainSettings
from soft_gripper_sdre.learning.training import train
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.graph.procs import PINNED_KERNELS, cpu_runs_pinned_kernels, ros_env
from soft_gripper_sdre.tools.learning.collect import collect_signal


@pytest.fixture(scope='module')
def data():
    """0.5 s of x1 (training) and u4 (validation) from the simulated finger: true states and
    accelerations."""
    def arrays(name):
        r = collect_signal(name, SimConfig(scene='finger'), duration=0.5)
        return (np.hstack([r['tip_true'][:, :2] - r['rest_tip'][:2], r['vel_true'][:, :2]]), r['u'],
                r['acc_true'][:, :2])
    return arrays('x1') + arrays('u4')


def test_the_default_preset_runs_its_whole_budget(data):
    """No early stop (patience None): every epoch runs, and the best validation epoch's weights are
    kept."""
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
            assert (torch.get_num_threads() == threads
                    and not torch.are_deterministic_algorithms_enabled())
    finally:
        torch.set_num_threads(old_threads)
    a, b = results
    assert a.val_loss == b.val_loss
    for key, value in a.net.state_dict().items():
        assert torch.equal(value, b.net.state_dict()[key]), key


def test_training_runs_under_atens_deterministic_flag_without_importing_the_graph_compiler():
    """Inside training ATen's deterministic algorithms are on (errors, not warnings); torch's graph
    compiler, whose configuration ``torch.use_deterministic_algorithms`` would import and which a
    ``torch.optim`` optimizer imports as it is made, is not loaded by a training, with the
    simulation stage or without, in a fresh process: the test session may have imported it."""
    code = (
        'import sys, numpy as np, torch\n'
        'from dataclasses import replace\n'
        'from soft_gripper_sdre.learning.rollout import Run\n'
        'from soft_gripper_sdre.learning.train_settings import PRESETS\n'
        'from soft_gripper_sdre.learning.training import train\n'
        'seen = []\n'
        'def on_epoch(*_):\n'
        '    seen.append((torch.are_deterministic_algorithms_enabled(),\n'
        '                 torch.is_deterministic_algorithms_warn_only_enabled()))\n'
        'rng = np.random.default_rng(0)\n'
        'x, u, a = (rng.normal(size=(300, k)) for k in (4, 2, 2))\n'
        'train(x, u, a, x, u, a, replace(PRESETS["default"], epochs=2), on_epoch)\n'
        'runs = [Run(1e-3 * x, 1e-3 * u, 1e-3)]\n'
        'train(x, u, a, x, u, a, replace(PRESETS["gripper"], epochs=1, rollout_epochs=1,\n'
        '      rollout_val_seconds=0.1), on_epoch, runs=runs, val_runs=runs)\n'
        'print(seen, torch.are_deterministic_algorithms_enabled(),\n'
        '      "torch._inductor.config" in sys.modules, "torch._dynamo" in sys.modules)\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, **PINNED_KERNELS})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == f'{[(True, False)] * 4} False False False'


#: how far the trained model may move when the training arrays' bits do (another CPU's kernels):
#: the u4 R² X and Y (absolute), the two dominant entries of G2 at the origin (relative), the
#: angles of G2's columns [deg] and the derivative errors (relative). Measured (MEASURED): the
#: shipped data trained with this machine's own OpenBLAS kernels and with --jitter 1e-9 (four
#: seeds) moved R² X by at most 0.0135, Y by 0.0031, the dominant entries by 2.2 %, the angles by
#: 1.0°, the derivative errors by 6e-9; the band is 2 to 3 times that (the derivative errors'
#: far more). G2's two small entries, the cross coupling at about 1 % of the dominant ones, are
#: not held: they ranged from -11.5 to +1.9 and from 20.7 to 25.6 (docs/model.md).
BAND = {'r2_X': 0.03, 'r2_Y': 0.01, 'G2_dominant': 0.05, 'angle_deg': 2.5, 'derivative': 1e-6}

#: metrics of models trained on the shipped data with other bits (see BAND): this machine's own
#: OpenBLAS kernels (SkylakeX, an AMD EPYC with AVX-512), then --jitter 1e-9 with seeds 1 to 4
MEASURED = (
    {'u4_r2_true': {'X': 0.8508390426046684, 'Y': 0.9869506743537236},
     'G2_at_origin': [[23.475, 644.988], [-608.142, 1.926]],
     'G2_column_angles_deg': [-87.79, 0.17]},
    {'u4_r2_true': {'X': 0.8355894838048261, 'Y': 0.9864810164317401},
     'G2_at_origin': [[24.8, 648.754], [-606.736, -11.006]],
     'G2_column_angles_deg': [-87.66, -0.97]},
    {'u4_r2_true': {'X': 0.8381743807830602, 'Y': 0.9831892775189803},
     'G2_at_origin': [[20.698, 635.695], [-594.046, -5.171]],
     'G2_column_angles_deg': [-88.0, -0.47]},
    {'u4_r2_true': {'X': 0.8334907947978176, 'Y': 0.9855799895236229},
     'G2_at_origin': [[25.596, 643.601], [-599.441, -11.485]],
     'G2_column_angles_deg': [-87.55, -1.02]},
    {'u4_r2_true': {'X': 0.8338788505684773, 'Y': 0.9859978056983386},
     'G2_at_origin': [[25.033, 647.288], [-600.154, -8.16]],
     'G2_column_angles_deg': [-87.61, -0.72]},
)


def band_problems(metrics: dict, shipped: dict, band: dict = BAND) -> list[str]:
    """Where ``metrics`` leave the band around ``shipped`` (empty: within it)."""
    problems = []
    for axis in 'XY':
        got, want = metrics['u4_r2_true'][axis], shipped['u4_r2_true'][axis]
        if abs(got - want) > band[f'r2_{axis}']:
            problems.append(f'u4 R² {axis} {got:.4f}, shipped {want:.4f}')
    G, G0 = np.asarray(metrics['G2_at_origin']), np.asarray(shipped['G2_at_origin'])
    for i, j in ((0, 1), (1, 0)):
        if abs(G[i, j] - G0[i, j]) > band['G2_dominant'] * abs(G0[i, j]):
            problems.append(f'G2[{i}][{j}] {G[i, j]:.1f}, shipped {G0[i, j]:.1f}')
    for k, (got, want) in enumerate(zip(metrics['G2_column_angles_deg'],
                                         shipped['G2_column_angles_deg'])):
        if abs(got - want) > band['angle_deg']:
            problems.append(f'G2 column {k} at {got:.2f}°, shipped {want:.2f}°')
    for signal, errors in metrics.get('derivative_errors', {}).items():
        for key, values in errors.items():
            want = shipped['derivative_errors'][signal][key]
            if not np.allclose(values, want, rtol=band['derivative'], atol=0.0):
                problems.append(f'derivative error {signal} {key} {values}, shipped {want}')
    return problems


def test_the_band_holds_every_measured_run_and_refuses_another_model():
    shipped = json.loads(DEFAULT_MODEL.with_suffix('.json').read_text())
    assert band_problems(shipped, shipped) == []
    for run in MEASURED:
        assert band_problems(run, shipped) == [], run
    swapped = {**MEASURED[0], 'G2_at_origin': [[645.0, 23.5], [1.9, -608.1]],
               'G2_column_angles_deg': [2.0, 89.0]}
    assert len(band_problems(swapped, shipped)) == 4
    worse = {**MEASURED[0], 'u4_r2_true': {'X': 0.78, 'Y': 0.9869}}
    assert band_problems(worse, shipped) == ['u4 R² X 0.7800, shipped 0.8374']


@pytest.mark.skipif(not cpu_runs_pinned_kernels(), reason='needs x86-64 with AVX2 and FMA')
def test_the_pinned_kernels_are_the_ones_numpy_and_torch_run():
    """The variables are honoured: OpenBLAS reports its Haswell core, ATen its AVX2 kernels."""
    probe = ('import ctypes, glob, os, numpy, torch\n'
             "libs = os.path.join(os.path.dirname(numpy.__file__), '..', 'numpy.libs')\n"
             "lib = ctypes.CDLL(glob.glob(os.path.join(libs, 'libscipy_openblas*'))[0])\n"
             'lib.scipy_openblas_get_corename64_.restype = ctypes.c_char_p\n'
             'print(lib.scipy_openblas_get_corename64_().decode(), '
             'torch.backends.cpu.get_cpu_capability())\n')
    out = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                         env={**os.environ, **PINNED_KERNELS}, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ['Haswell', 'AVX2']


def test_the_graph_processes_get_the_pinned_kernels_unless_the_caller_set_its_own(monkeypatch):
    """The demo's, the runners' and the tests' node processes (tools.graph.procs.ros_env) run the
    pinned kernels where the CPU has them; a variable set by the caller is kept."""
    monkeypatch.setenv('MKL_CBWR', 'COMPATIBLE')
    monkeypatch.delenv('OPENBLAS_CORETYPE', raising=False)
    env = ros_env(42)
    assert env['MKL_CBWR'] == 'COMPATIBLE'
    if cpu_runs_pinned_kernels():
        assert env['OPENBLAS_CORETYPE'] == 'Haswell'
        assert env['ATEN_CPU_CAPABILITY'] == PINNED_KERNELS['ATEN_CPU_CAPABILITY']
    else:
        assert 'OPENBLAS_CORETYPE' not in env


def run_tool(tool, *args, timeout, env=None):
    proc = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.{tool}', *args],
                          capture_output=True, text=True, timeout=timeout, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_collect_then_train_reproduces_the_shipped_checkpoint(tmp_path):
    """Within the band on every machine; bit for bit where the pinned kernels run."""
    pinned = cpu_runs_pinned_kernels()
    env = {**os.environ, **(PINNED_KERNELS if pinned else {})}
    data, out = tmp_path / 'excitation', tmp_path / 'train'
    run_tool('learning.collect', '--out', str(data), timeout=300, env=env)
    run_tool('learning.train', '--data', str(data), '--out', str(out), timeout=800, env=env)

    shipped = json.loads(DEFAULT_MODEL.with_suffix('.json').read_text())
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['epochs_run'] == shipped['epochs_run']
    assert band_problems(metrics, shipped) == []
    if not pinned:
        return

    assert metrics['u4_r2_true'] == shipped['u4_r2_true']
    assert (metrics['epochs_run'], metrics['best_epoch']) == (shipped['epochs_run'],
                                                              shipped['best_epoch'])
    assert metrics['derivative_errors'] == shipped['derivative_errors']
    assert metrics['G2_at_origin'] == shipped['G2_at_origin']

    ours, theirs = read_checkpoint(out / 'model.pt'), read_checkpoint(DEFAULT_MODEL)
    assert ours['data']['fingerprint'] == theirs['data']['fingerprint']     # the same arrays
    # settings and history the shipped checkpoint does not record are the ones that leave the
    # default preset's training alone: the simulation stage and the rest penalty off
    assert {k: ours['settings'][k] for k in theirs['settings']} == theirs['settings']
    defaults = asdict(TrainSettings())
    unrecorded = ours['settings'].keys() - theirs['settings'].keys()
    assert all(ours['settings'][k] == defaults[k] for k in unrecorded)
    assert ours['settings']['rollout_epochs'] == 0 and ours['settings']['rest_margin'] == 0.0
    assert ours['state_dict'].keys() == theirs['state_dict'].keys()
    for key, weights in ours['state_dict'].items():
        assert torch.equal(weights, theirs['state_dict'][key]), key
    assert {k: ours['history'][k] for k in theirs['history']} == theirs['history']
    assert all(ours['history'][k] == [] for k in ours['history'].keys() - theirs['history'].keys())
