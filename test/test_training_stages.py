"""The simulation stage and the stable-rest penalty of training (learning/training.py), on a
linear spring–damper finger measured with noise, whose motions are small against it."""
from dataclasses import replace

import numpy as np
import pytest
from spring_finger import NOISE, RATE, SpringDamper
import torch

from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.learning.rollout import Run
from soft_gripper_sdre.learning.train_settings import PRESETS, TrainSettings
from soft_gripper_sdre.learning.training import save_checkpoint, train
from soft_gripper_sdre.sim.signals import SIGNALS

pytestmark = [pytest.mark.slow, pytest.mark.timeout(400)]

DT = 1.0 / RATE
SECONDS = 6.0
JERK = 100.0                      # KF + RTS white-jerk intensity [(m/s³)²/Hz]
SETTINGS = replace(PRESETS['gripper'], epochs=25, rollout_epochs=12)


def record(signal: str, seed: int) -> Run:
    """One record of ``signal`` at 2 % of its level: states and labels by the KF + RTS."""
    finger = SpringDamper(gain=1.0, seed=seed)
    t = np.arange(int(SECONDS * RATE)) * DT
    u = 0.02 * SIGNALS[signal](t)
    tips = []
    for k in range(len(t)):
        tips.append(finger.tips()[0, :2])
        finger.step(u[k])
    tips = np.array(tips) - tips[0]
    pos, vel, acc = derivatives.estimate_kinematics(t, tips, JERK, NOISE)
    return Run(np.hstack([pos, vel]), u, DT), acc


@pytest.fixture(scope='module')
def data():
    train_set = [record(name, seed) for seed, name in enumerate(('x1', 'b1', 'b2'))]
    val_set = [record('u4', 7)]
    stack = lambda rs, i: np.vstack([r[0][i] if i < 2 else r[1] for r in rs])  # noqa: E731
    arrays = [stack(train_set, i) for i in (0, 1, 2)] + [stack(val_set, i) for i in (0, 1, 2)]
    return arrays, [r for r, _ in train_set], [r for r, _ in val_set]


@pytest.fixture(scope='module')
def trained(data):
    arrays, runs, val_runs = data
    return train(*arrays, SETTINGS, runs=runs, val_runs=val_runs)


def _rest_eigenvalues(result, tmp_path):
    model = SDCModel(save_checkpoint(tmp_path / 'm.pt', result, rest_tip=np.zeros(3), dt=DT,
                                     settings=SETTINGS, data={}))
    return np.linalg.eigvals(model.AG(np.zeros(4))[0][0])


def test_the_simulation_stage_lowers_the_validation_simulation_error(trained):
    labels_only = trained.val_sim_error[SETTINGS.epochs - 1]
    assert len(trained.rollout_loss) == SETTINGS.rollout_epochs
    assert len(trained.val_sim_error) == SETTINGS.epochs + SETTINGS.rollout_epochs
    assert trained.best_epoch >= SETTINGS.epochs  # the kept weights are a rollout epoch's
    assert min(trained.val_sim_error) < 0.8 * labels_only


def test_the_kept_rest_is_stable_beyond_the_margin(trained, tmp_path):
    eig = _rest_eigenvalues(trained, tmp_path)
    assert eig.real.max() < -0.5 * SETTINGS.rest_margin


def test_the_rest_penalty_moves_an_unstable_rest_left(data, tmp_path):
    """Labels alone on these small motions leave some rest eigenvalue right of the margin; the
    penalty alone (no simulation stage) moves every one left of it."""
    arrays, _, _ = data
    plain = train(*arrays, replace(SETTINGS, rollout_epochs=0, rest_margin=0.0))
    held = train(*arrays, replace(SETTINGS, rollout_epochs=0, rest_margin=5.0))
    before, after = _rest_eigenvalues(plain, tmp_path), _rest_eigenvalues(held, tmp_path)
    assert before.real.max() > -5.0
    assert after.real.max() < before.real.max() and after.real.max() < -2.5


def test_two_runs_give_the_same_weights(data, trained):
    arrays, runs, val_runs = data
    again = train(*arrays, SETTINGS, runs=runs, val_runs=val_runs)
    for k, v in trained.net.state_dict().items():
        assert torch.equal(v, again.net.state_dict()[k]), k


@pytest.mark.parametrize('field, value', [('rollout_epochs', -1), ('rollout_epochs', 1.5),
                                          ('rollout_overlap', 0), ('rollout_seconds', 0.0),
                                          ('rollout_lr', float('nan')), ('rest_margin', -1.0),
                                          ('rest_weight', 0.0)])
def test_bad_stage_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        TrainSettings(**{field: value})


def test_the_simulation_stage_refuses_to_run_without_records(data):
    arrays, runs, _ = data
    with pytest.raises(ValueError, match='val_runs'):
        train(*arrays, SETTINGS, runs=runs, val_runs=None)
    short = [Run(r.x[:5], r.u[:5], r.dt) for r in runs]
    with pytest.raises(ValueError, match='runs'):
        train(*arrays, SETTINGS, runs=short, val_runs=short)
