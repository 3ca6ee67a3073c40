"""The sweep and input-matrix tools end to end (real simulator, shipped model)."""
import json
import subprocess
import sys

import pytest


def run_tool(module, *args):
    return subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.{module}', *args],
                          capture_output=True, text=True, timeout=600)


def test_sweep_writes_json_figure_and_table(tmp_path):
    proc = run_tool('judging.sweep', '--out', str(tmp_path), '--q-pos', '1e6', '--noise', '0',
                    '--lowpass', '0', '40', '--duration', '0.3')
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((tmp_path / 'sweep.json').read_text())
    assert [r['lowpass_hz'] for r in rows] == [0.0, 40.0]
    for r in rows:
        assert r['q_pos'] == 1e6 and r['noise_m'] == 0.0 and r['fallback_fraction'] == 0.0
        assert 1.0 < r['frictionless_radius'] < 1.1
    assert rows[1]['frictionless_radius'] < rows[0]['frictionless_radius']
    assert (tmp_path / 'sweep.png').read_bytes()[:4] == b'\x89PNG'
    assert '| 40 Hz | 1e+06 | 0.00 |' in proc.stdout


def test_sweep_bad_arguments_exit_2(tmp_path):
    proc = run_tool('judging.sweep', '--out', str(tmp_path), '--q-pos', '-1')
    assert proc.returncode == 2 and 'q_pos' in proc.stderr


@pytest.mark.slow
def test_input_matrix_tool_reports_both_shipped_models(tmp_path):
    proc = run_tool('judging.input_matrix', '--out', str(tmp_path))
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads((tmp_path / 'input_matrix.json').read_text())
    assert set(result) == {'default', 'paper_data'}
    assert max(result['default']['rest']['error_deg']) < 10.0
    assert min(result['paper_data']['rest']['error_deg']) > 20.0
    assert len(result['default']['workspace']['true_deg']) == 9


def test_input_matrix_tool_refuses_a_missing_model(tmp_path, run_main):
    from soft_gripper_sdre.tools.judging.input_matrix import main
    proc = run_main(main, '--models', tmp_path / 'none.pt')      # (python -m: the test above)
    assert proc.returncode == 2 and 'none.pt' in proc.stderr
