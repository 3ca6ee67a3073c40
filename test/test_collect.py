"""The collect tool, run as a real subprocess on the real simulator."""
import subprocess
import sys

import numpy as np

from soft_gripper_sdre.sim.signals import get_signal


def run_collect(*args, cwd=None):
    return subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.learning.collect', *args],
                          capture_output=True, text=True, timeout=50, cwd=cwd)


def test_collect_writes_aligned_dataset(tmp_path):
    proc = run_collect('--signals', 'u1', 'x1', '--out', str(tmp_path), '--duration', '0.3',
                       '--noise-std', '1e-5')
    assert proc.returncode == 0, proc.stderr
    for name in ('u1', 'x1'):
        with np.load(tmp_path / f'{name}.npz', allow_pickle=False) as d:
            n = d['t'].size
            assert n == 300 and float(d['dt']) == 1e-3 and str(d['signal']) == name
            assert int(d['format_version']) == 1
            np.testing.assert_allclose(d['u'], get_signal(name)(d['t']))
            for key, width in (('tip', 3), ('tip_true', 3), ('vel_true', 3), ('acc_true', 3),
                               ('q', 10)):
                assert d[key].shape == (n, width)
            # acc_true[k] is the response to u[k]: the velocity change over [t_k, t_k+Δt)
            np.testing.assert_allclose(d['acc_true'][:-1], np.diff(d['vel_true'], axis=0) / 1e-3,
                                       rtol=1e-9, atol=1e-9)
            # the record starts at the settled rest pose
            np.testing.assert_allclose(d['tip_true'][0], d['rest_tip'], atol=1e-12)
            noise = d['tip'] - d['tip_true']
            assert 0 < noise.std() < 3e-5


def test_unknown_signal_is_a_usage_error(tmp_path):
    proc = run_collect('--signals', 'u1', 'u9', '--out', str(tmp_path))
    assert proc.returncode == 2
    assert 'unknown signal' in proc.stderr and 'u9' in proc.stderr and 'u4' in proc.stderr
    assert not list(tmp_path.iterdir())


def test_unwritable_output_is_a_usage_error(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    proc = run_collect('--signals', 'u1', '--out', str(blocker / 'sub'), '--duration', '0.01')
    assert proc.returncode == 2
    assert 'output directory' in proc.stderr
