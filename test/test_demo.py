"""The main command: the node graph as five processes, recorded to a bag and reported."""
import json
import subprocess
import sys

import pytest

from soft_gripper_sdre.analysis.bag import topic_counts
from soft_gripper_sdre.tools.graph.demo import DemoGraph, main, run_demo, summary

pytestmark = pytest.mark.ros


@pytest.mark.slow
@pytest.mark.timeout(75)
def test_demo_runs_the_graph_as_processes_and_writes_a_readable_bag(tmp_path):
    result = run_demo(tmp_path, duration=1.0, timeout=60, progress=False)
    counts = topic_counts(tmp_path / 'bag')
    # lockstep: one message per period on every loop topic, t = 0 … 1 s inclusive (the answer to
    # the final tips may be cut off by the shutdown: the simulator no longer needs it); /clock at
    # 100 Hz of sim time; the controller answers estimates only
    assert counts['/tip_positions'] == 1001 and counts['/clock'] == 101, counts
    assert counts['/state_estimate'] in (1000, 1001), counts
    assert counts['/torque_commands'] in (1000, 1001), counts
    # the whole plan, once
    assert counts['/grasp_reference'] == 1 and counts['/cube_contacts'] >= 100
    assert (tmp_path / 'bag' / 'metadata.yaml').is_file()
    assert list((tmp_path / 'bag').glob('*.mcap'))
    assert all(code == 0 for code in result['run']['exit_codes'].values()), result['run']
    run = result['run']        # the simulator's final diagnostics, read back from the bag
    assert (0 < run['real_time_factor']
            and 0 < run['loop_latency_us_p50'] <= run['loop_latency_us_p99'])
    for name in ('fig5_positions.png', 'fig6_velocities.png', 'fig7_torques.png'):
        assert (tmp_path / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    saved = json.loads((tmp_path / 'metrics.json').read_text())
    assert saved['controller']['commands'] >= 1000        # the controller's final diagnostics
    assert saved['controller']['fallback_fraction'] == 0.0
    assert set(saved['fingers']) == {'finger_0', 'finger_1', 'finger_2', 'finger_3'}
    assert 'finger_0: free-space RMSE' in summary(result, tmp_path)


def _corrupt_model(tmp_path):
    path = tmp_path / 'corrupt.pt'
    path.write_bytes(bytes(range(256)) * 8)
    return path


@pytest.mark.parametrize('args, needle', [
    (['--duration', '-1'], '--duration must be > 0'),
    (['--model', '/nonexistent.pt'], '--model: model file /nonexistent.pt does not exist'),
    (['--model', 'CORRUPT'], 'is not a checkpoint: a torch.save file is a zip archive'),
    (['--noise', '-0.1'], '--noise is σ in mm'),
    (['--noise', '50'], '--noise is σ in mm, from 0 to 10 mm, got 50.0'),
    (['--seed', '-3'], '--seed must be in'),
    (['--law', 'nonsense'], "invalid choice: 'nonsense'"),
    (['--fingers', 'left=1,right=3'], 'none of the fingers is at hand finger 0 or 2'),
    (['--fingers', 'left'], "--fingers: 'left' is not NAME=HAND_FINGER"),
    (['--fingers', 'left=0,right=0'], 'hand fingers must be distinct'),
    (['--fingers', 'a/b=0'], "'a/b' is not a valid finger name"),
    (['--period', '20'], '--period is the control period in ms, from 1 to 10, got 20.0'),
    (['--period', 'nan'], '--period is the control period in ms'),
    (['--integral-gain', '-1'], '--integral-gain must be in [0, '),
])
def test_demo_bad_usage_exits_2_before_starting_anything(args, needle, tmp_path, run_main):
    args = [str(_corrupt_model(tmp_path)) if a == 'CORRUPT' else a for a in args]
    out = tmp_path / 'out'
    proc = run_main(main, '--out', out, *args)
    assert proc.returncode == 2 and needle in proc.stderr, proc.stderr
    assert not out.exists(), 'a refused command line must not start the graph'


def test_demo_command_line_refuses_bad_usage_with_exit_2_and_no_traceback(tmp_path):
    """The refusals above, through ``python -m`` once."""
    out = tmp_path / 'out'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.graph.demo',
                           '--out', str(out), '--duration', '-1'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and '--duration must be > 0' in proc.stderr, proc.stderr
    assert 'Traceback' not in proc.stderr
    assert not out.exists()


def test_a_node_that_dies_is_named_with_its_own_log_and_no_bag_is_left(tmp_path):
    """run_demo on a corrupt model (past the CLI's check): the controller exits at start-up."""
    with pytest.raises(RuntimeError) as exc:
        run_demo(tmp_path, 1.0, DemoGraph(model=_corrupt_model(tmp_path)), timeout=120,
                 progress=False)
    message = str(exc.value)
    assert message.startswith('the controller node exited with status')
    assert 'last lines of controller.log' in message and 'is not a checkpoint' in message
    assert not (tmp_path / 'bag').exists()


@pytest.mark.parametrize('controller, expected, absent', [
    ({'law': 'sdre_ff', 'max_residual': 3e-9, 'fallback_fraction': 0.0,
      'check_failure_fraction': 0.01, 'compute_us_mean': 40.0},
     '  Riccati: checks failed on 1.00% of solves, fallbacks 0.00%, max residual '
     '3.0e-09; compute 40 µs mean per 1-finger step', 'no per-step'),
    ({'law': 'pd', 'fallback_fraction': 0.0, 'check_failure_fraction': 0.0, 'compute_us_mean': 9.0},
     '  pd (no per-step Riccati solve): compute 9 µs mean per 1-finger step', 'residual'),
])
def test_summary_reports_the_riccati_checks_only_for_laws_that_solve_one(controller, expected,
                                                                         absent, tmp_path):
    finger = {'rmse_mm': 0.1, 'rmse_pct': 1.0, 'excursion_mm': 10.0, 'max_mm': 0.2,
              'contact_fraction': 0.0}
    result = {'run': {'sim_duration_s': 1.0, 'wall_s': 2.0, 'real_time_factor': 0.5},
              'fingers': {'finger_0': finger}, 'controller': controller}
    text = summary(result, tmp_path)
    assert expected in text.splitlines() and absent not in text and 'nan' not in text
