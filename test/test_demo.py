"""The main command: the node graph as five processes, recorded to a bag and reported."""
import json
import subprocess
import sys

import pytest

from soft_gripper_sdre.analysis.bag import read_bag, topic_counts
from soft_gripper_sdre.tools.demo import run_demo, summary

pytestmark = pytest.mark.ros


@pytest.mark.slow
@pytest.mark.timeout(75)
def test_demo_runs_the_graph_as_processes_and_writes_a_readable_bag(tmp_path):
    result = run_demo(tmp_path, duration=1.0, timeout=60, progress=False)
    counts = topic_counts(tmp_path / 'bag')
    # lockstep: one message per period on every loop topic, t = 0 … 1 s inclusive (the answer to
    # the final tips may be cut off by the shutdown: the simulator no longer needs it)
    for topic in ('/clock', '/tip_positions'):
        assert counts[topic] == 1001, (topic, counts)
    assert counts['/state_estimate'] in (1000, 1001), counts
    # torque commands of the run (a controller that outlives the simulator by more than its
    # estimate_timeout adds zero-torque commands stamped with its own clock after it)
    in_run = [m for _, m in read_bag(tmp_path / 'bag', ['torque_commands'])['/torque_commands']
              if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec <= 10**9]
    assert len(in_run) in (1000, 1001), len(in_run)
    assert counts['/grasp_reference'] >= 50 and counts['/cube_contacts'] >= 100
    assert (tmp_path / 'bag' / 'metadata.yaml').is_file()
    assert list((tmp_path / 'bag').glob('*.mcap'))
    assert all(code == 0 for code in result['run']['exit_codes'].values()), result['run']
    run = result['run']        # the simulator's final diagnostics, read back from the bag
    assert 0 < run['real_time_factor'] and 0 < run['loop_latency_us_p50'] <= run['loop_latency_us_p99']
    for name in ('fig5_positions.png', 'fig6_velocities.png', 'fig7_torques.png'):
        assert (tmp_path / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    saved = json.loads((tmp_path / 'metrics.json').read_text())
    assert saved['controller']['commands'] >= 1000        # the controller's final diagnostics
    assert saved['controller']['fallback_fraction'] == 0.0
    assert set(saved['fingers']) == {'finger_0', 'finger_1', 'finger_2', 'finger_3'}
    assert 'finger_0: free-space RMSE' in summary(result, tmp_path)


@pytest.mark.parametrize('args, needle', [
    (['--duration', '-1'], '--duration'),
    (['--model', '/nonexistent.pt'], '--model'),
    (['--noise', '-0.1'], '--noise'),
])
def test_demo_bad_usage_exits_2(args, needle, tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.demo', '--out', str(tmp_path),
                           *args], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and needle in proc.stderr
