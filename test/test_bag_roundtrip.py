"""The round trip on the graph (slow): the excitation node, the simulator node and the recorder as
processes over DDS → bags → ``train --bag``, checked against the ``.npz`` path on the same signals.

Short signals and a few epochs keep it within the slow budget; the full round trip (10 s signals,
the whole training budget, the grasp with the bag-trained model) is measured in docs/model.md,
"Training from bags".
"""
from dataclasses import replace
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.analysis.bag_dataset import label_finger, read_recording, settle_estimates
from soft_gripper_sdre.analysis.metrics import r2_score
from soft_gripper_sdre.learning.dataset import Record
from soft_gripper_sdre.learning.labels import states
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import save_checkpoint, train
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.learning.collect import collect_signal
from soft_gripper_sdre.tools.learning.train import NOT_FIT

pytestmark = pytest.mark.ros

SECONDS = 2.0
JERK = 1e3            # fixed on both paths (the tuner would pick the same on the same data)
EPOCHS = 5


def run_tool(tool, *args, timeout):
    proc = subprocess.run([sys.executable, '-m', f'soft_gripper_sdre.tools.{tool}',
                           *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=dict(os.environ))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def npz_record(name: str) -> tuple[Record, dict]:
    r = collect_signal(name, SimConfig(scene='finger'), duration=SECONDS)
    return Record(name, r['t'], r['u'], r['tip'], r['rest_tip'], float(r['dt']), r['vel_true'],
                  r['acc_true'], 0.0), r


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_bags_from_the_graph_train_the_model_the_npz_path_trains(tmp_path):
    bags = tmp_path / 'bags'
    run_tool('graph.excite', '--out', bags, '--signals', 'x1', 'u4', '--duration', SECONDS,
             '--settle', 0, '--noise', 0, '--domain-id', os.environ['ROS_DOMAIN_ID'],
             '--timeout', 120,
             timeout=260)

    # the same data: the graph's lockstep run is the in-process collection, sample for sample
    npz = {name: npz_record(name) for name in ('x1', 'u4')}
    labelled = {}
    for name, (record, raw) in npz.items():
        rec = read_recording(bags / name)
        n = record.t.size
        np.testing.assert_allclose(rec.tips[:n, 0], raw['tip'], rtol=0, atol=1e-12)
        np.testing.assert_allclose(rec.torques[:n, 0], record.u, rtol=0, atol=1e-15)
        rest, sigma, _ = settle_estimates(rec, 0)
        np.testing.assert_allclose(rest, record.rest_tip, rtol=0, atol=1e-12)
        [samples] = label_finger(rec, 0, JERK, 0.0, rest)
        ref = states(record, JERK)
        assert len(samples.t) == n and not samples.info['resampled']
        np.testing.assert_allclose(samples.t, record.t, rtol=0, atol=1e-12)
        np.testing.assert_allclose(samples.u, ref['u'], rtol=0, atol=1e-15)
        inner = slice(0, n - 100)          # the bag's smoother also sees the tips after the signal
        np.testing.assert_allclose(samples.x[inner], ref['x'][inner], rtol=0, atol=1e-9)
        scale = np.abs(ref['acc']).max()
        np.testing.assert_allclose(samples.acc[inner], ref['acc'][inner], rtol=0, atol=1e-6 * scale)
        labelled[name] = ref

    # train from the bags with the CLI, and on the npz records with the same settings
    out = tmp_path / 'model'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.learning.train',
                           *map(str, ('--bag', bags / 'x1', '--val-bag', bags / 'u4', '--out', out,
                                      '--epochs', EPOCHS, '--meas-std', 0, '--jerk-psd', JERK,
                                      '--preset', 'default'))],
                          capture_output=True, text=True, timeout=200, env=dict(os.environ))
    # one signal's bag: written and judged; 3 = judged not fit to control (no params.yaml)
    assert proc.returncode == (0 if (out / 'params.yaml').is_file() else NOT_FIT), proc.stderr
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['source'] == 'rosbag2' and metrics['train_samples'] == npz['x1'][0].t.size
    x, v = labelled['x1'], labelled['u4']
    settings = replace(PRESETS['default'], epochs=EPOCHS)
    result = train(x['x'], x['u'], x['acc'], v['x'], v['u'], v['acc'], settings)
    npz_model = SDCModel(save_checkpoint(tmp_path / 'npz.pt', result,
                                         rest_tip=npz['x1'][0].rest_tip, dt=0.001,
                                         settings=settings, data={}))
    npz_r2 = r2_score(npz['u4'][0].acc_true[:, :2], npz_model.xdot(v['x'], v['u'])[:, 2:])
    bag_model = SDCModel(out / 'model.pt')
    bag_r2 = r2_score(npz['u4'][0].acc_true[:, :2], bag_model.xdot(v['x'], v['u'])[:, 2:])
    np.testing.assert_allclose(bag_r2, npz_r2, atol=0.02)
    assert metrics['val_r2_labels']['Y'] == pytest.approx(float(bag_r2[1]), abs=0.05)

