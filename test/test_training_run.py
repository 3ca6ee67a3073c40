"""The training pipeline both ``tools.learning.train`` paths share (analysis/training_run.py): a
run's files appear together or not at all, and the scores are those of the checkpoint as loaded."""
from dataclasses import replace

import numpy as np
import pytest

from soft_gripper_sdre.analysis import training_run
from soft_gripper_sdre.analysis.metrics import poly_features, r2_score
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import train


def test_a_staged_run_replaces_the_old_files_and_removes_the_stale_ones(tmp_path):
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'model.pt').write_text('old')
    (out / 'params.yaml').write_text('of the old model')
    (out / 'notes.txt').write_text('the user\'s')
    with training_run.staged(out, stale=('params.yaml',)) as stage:
        (stage / 'model.pt').write_text('new')
        (stage / 'metrics.json').write_text('{}')
        assert (out / 'model.pt').read_text() == 'old'      # nothing moves before the end
    assert (out / 'model.pt').read_text() == 'new' and (out / 'metrics.json').exists()
    assert not (out / 'params.yaml').exists()
    assert (out / 'notes.txt').read_text() == 'the user\'s'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run']     # no staging left


def test_a_run_that_fails_leaves_the_output_as_it_was(tmp_path):
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'model.pt').write_text('old')
    (out / 'params.yaml').write_text('of the old model')
    with pytest.raises(RuntimeError, match='training broke'):
        with training_run.staged(out, stale=('params.yaml',)) as stage:
            (stage / 'model.pt').write_text('half written')
            raise RuntimeError('training broke')
    assert (out / 'model.pt').read_text() == 'old'
    assert (out / 'params.yaml').read_text() == 'of the old model'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run']


def test_the_checkpoint_is_scored_as_loaded_and_carries_the_callers_metrics(tmp_path):
    """A few epochs on a linear spring's data: the metrics in the checkpoint are the caller's,
    built from scores that match the loaded model's own predictions and the baseline's R²."""
    rng = np.random.default_rng(0)
    n = 4000
    x = rng.normal(scale=[2e-3, 2e-3, 0.05, 0.05], size=(n, 4))
    u = rng.normal(scale=0.01, size=(n, 2))
    acc = -400.0 * x[:, :2] - 4.0 * x[:, 2:] + u @ np.array([[300.0, -100.0], [250.0, 200.0]])
    settings = replace(PRESETS['default'], epochs=3)
    result = train(x[:3000], u[:3000], acc[:3000], x[3000:], u[3000:], acc[3000:], settings)
    seen = {}

    def describe(model, scores):
        seen['model'] = model
        return {**scores.common_metrics(settings, result), 'mine': 1}
    model, scores, metrics = training_run.checkpoint(
        tmp_path / 'model.pt', result, settings, rest_tip=np.zeros(3), dt=1e-3, data={},
        train=(x[:3000], u[:3000], acc[:3000]), val=(x[3000:], u[3000:]), acc_ref=acc[3000:],
        describe=describe)
    assert seen['model'] is model
    assert SDCModel(tmp_path / 'model.pt').metrics == metrics and metrics['mine'] == 1
    assert metrics['epochs_run'] == 3
    pred = model.xdot(x[3000:], u[3000:])[:, 2:]
    np.testing.assert_array_equal(scores.pred, pred)
    assert scores.r2 == r2_score(acc[3000:], pred).tolist()
    coef, *_ = np.linalg.lstsq(poly_features(x[:3000], u[:3000]), acc[:3000], rcond=None)
    baseline = r2_score(acc[3000:], poly_features(x[3000:], u[3000:]) @ coef)
    assert scores.r2_ls == pytest.approx(baseline)
    assert min(scores.r2_ls) > 0.99                       # the baseline holds a linear plant
    assert np.array_equal(np.asarray(metrics['G2_at_origin']), model.AG(np.zeros(4))[1][0, 2:, :])


def test_the_report_prints_g2_in_any_unit_and_the_roll_off_the_controller_applies():
    """A gain per pascal (1e-5 m/s² per Pa) reads as a number, not as 0.0; a roll-off above a
    tenth of the recordings' rate is printed with the corner the controller applies."""
    from soft_gripper_sdre.tools.learning.train_bags import roll_off_text
    scores = training_run.Scores(np.zeros((3, 2)), [0.9, 0.8], [0.5, 0.4],
                                 np.array([[-1.234e-5], [2.5e-6]]))
    assert scores.lines('u4')[1] == ('G2 at the origin [m/s² per unit of input]: '
                                     '[[-1.23e-05], [2.5e-06]]')
    assert roll_off_text(16.6326, 0.01) == '16.6326 Hz (applied at 10 Hz, a tenth of the rate)'
    assert roll_off_text(40.0, 0.001) == '40 Hz'
