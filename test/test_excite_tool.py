"""tools.graph.excite: the excitation level's arguments refused before anything starts (exit 2, the
argument named, nothing written), and ``--level auto`` over the node graph (slow): the excitation
node probes the simulated finger, then plays the signal near the target, off the clip, with the
amplitude in the recorded /diagnostics."""
import os
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.analysis.bag import read_bag
from soft_gripper_sdre.analysis.bag_dataset import read_recording, settle_noise
from soft_gripper_sdre.tools.graph import excite

BAD = [
    (['--amplitude', '0'], '--amplitude must be in [1e-6, 100], got 0.0'),
    (['--amplitude', 'nan'], '--amplitude must be in'),
    (['--level', 'manual'], "argument --level: invalid choice: 'manual'"),
    (['--max-excursion', '-1'], '--max-excursion is in mm, from 0 (off) to 1000, got -1.0'),
    (['--level-target', '0'], '--level-target must be in [0.05, 1]'),
    (['--level-target', '1.5'], '--level-target must be in [0.05, 1]'),
    (['--level', 'auto'], '--level auto needs --max-excursion > 0'),
    (['--level', 'auto', '--max-excursion', '20', '--settle', '0'],
     '--level auto needs --settle > 0'),
    (['--level', 'auto', '--max-excursion', '20', '--amplitude', '0.5'],
     '--amplitude is chosen by --level auto'),
    # wider than the simulator's clip: the excitation node would refuse it only once running
    (['--torque-limit', '0.2'], '--torque-limit must be in (0, 0.1] N·m (the simulator clips'),
    (['--torque-limit', '0'], '--torque-limit must be in (0, 0.1] N·m'),
]


@pytest.mark.parametrize('args, message', BAD)
def test_bad_level_arguments_exit_2_naming_them_and_write_nothing(args, message, tmp_path, capsys):
    out = tmp_path / 'bags'
    with pytest.raises(SystemExit) as info:
        excite.main(['--out', str(out), '--signals', 'u1', *args])
    assert info.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_bad_level_parameter_exits_the_node_2_without_a_traceback(tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    for param, name in (('level:=auto', 'max_excursion'), ('amplitude:=0.0', 'amplitude'),
                        ('min_command_subscribers:=-2', 'min_command_subscribers')):
        proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.nodes.excitation',
                               '--ros-args', '-p', param], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert f"parameter '{name}'" in proc.stderr and 'Traceback' not in proc.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(400)
def test_level_auto_on_the_simulated_finger(tmp_path):
    bags = tmp_path / 'bags'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.graph.excite',
                           '--out', str(bags),
                           '--signals', 'u1', '--duration', '2', '--level', 'auto',
                           '--max-excursion', '20', '--domain-id', os.environ['ROS_DOMAIN_ID'],
                           '--timeout', '300'], capture_output=True, text=True, timeout=380)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    bag = bags / 'u1'
    rec = read_recording(bag)
    rest, sigma, n = settle_noise(rec, 0)          # the settle phase before the first probe
    # 0.5 s at 1 kHz: 500 tips; a recorder starved past the writers' history (LOOP_QOS, 50 ms)
    # can miss some (394 in a run beside two training jobs); the noise level still comes out
    assert n >= 250 and sigma == pytest.approx(5e-5, rel=0.2)
    # the excitation node's last /diagnostics in the bag: the amplitude it chose and its clip share
    values = {}
    for _, msg in read_bag(bag, ['/diagnostics'])['/diagnostics']:
        for status in msg.status:
            if status.name.endswith('excitation'):
                values.update({kv.key: kv.value for kv in status.values})
    amplitude = float(values['amplitude'])
    assert values['level'] == 'auto: chosen' and float(values['clip_share']) == 0.0
    assert 0.01 < amplitude < 1.6 and values['probes'].count('mm') >= 2
    # the signal: the last 2.5 s of commands (settle and u1); u1 at the chosen amplitude
    t = (rec.cmd_ns - rec.cmd_ns[-1]) / 1e9
    signal = (t > -2.0) & (t < -0.01)
    peak = np.abs(rec.torques[signal, 0]).max()
    assert peak == pytest.approx(amplitude * 0.0625, rel=1e-3)
    played = rec.tip_ns >= rec.cmd_ns[np.flatnonzero(signal)[0]]
    excursion = np.linalg.norm(rec.tips[played, 0] - rest, axis=-1).max()
    assert 10e-3 / 1.5 <= excursion <= 10e-3 * 1.5, (values, excursion)
