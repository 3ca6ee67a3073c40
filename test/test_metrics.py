"""Tracking metrics against hand-computed values."""
import numpy as np
import pytest

from soft_gripper_sdre.analysis.metrics import held_reference_error, r2_score, tracking_metrics


def test_tracking_metrics_known_values():
    ref = np.zeros((4, 2, 2))
    pos = ref.copy()
    pos[:, 0, 0] = [0.003, 0.004, 0.0, 0.0]        # finger 0 errors 3, 4, 0, 0 mm
    mask = np.ones((4, 2), dtype=bool)
    mask[3, 0] = False                               # last sample not scored
    m = tracking_metrics(pos, ref, mask, excursion=np.array([0.05, 0.0]))
    assert m[0].samples == 3
    assert m[0].rmse_mm == pytest.approx(np.sqrt((9 + 16) / 3))
    assert m[0].max_mm == pytest.approx(4.0)
    assert m[0].rmse_pct == pytest.approx(100 * np.sqrt(25 / 3) / 50)
    assert m[1].rmse_mm == 0.0 and np.isnan(m[1].rmse_pct)


def test_tracking_metrics_shape_errors():
    with pytest.raises(ValueError, match='mask'):
        tracking_metrics(np.zeros((3, 2, 2)), np.zeros((3, 2, 2)), np.ones((3, 3), bool), 1.0)
    with pytest.raises(ValueError, match='pos and ref'):
        tracking_metrics(np.zeros((3, 2, 3)), np.zeros((3, 2, 3)), np.ones((3, 2), bool), 1.0)


def test_r2():
    y = np.array([[1.0, 2.0], [2.0, 4.0], [3.0, 9.0]])
    np.testing.assert_allclose(r2_score(y, y), 1.0)
    np.testing.assert_allclose(r2_score(y, np.broadcast_to(y.mean(0), y.shape)), 0.0)


def test_held_reference_error_scores_a_still_reachable_reference_only():
    T = 6
    ref = np.zeros((T, 3, 2))
    ref_vel = np.zeros((T, 3, 2))
    ref_vel[:2, 0, 1] = 0.1                     # finger 0's reference moves for two samples
    pos = ref + [3e-5, 4e-5]                    # 0.05 mm everywhere
    pos[:2, 0] += 1e-3                          # the moving samples are not scored
    contact = np.zeros((T, 3), dtype=bool)
    contact[:, 2] = True                        # finger 2 presses on the cube throughout
    held = held_reference_error(pos, ref, ref_vel, contact)
    np.testing.assert_allclose(held[:2], [0.05, 0.05], rtol=1e-12)
    assert np.isnan(held[2])
    with pytest.raises(ValueError, match='contact'):
        held_reference_error(pos, ref, ref_vel, contact[:, :2])
    with pytest.raises(ValueError, match='ref_vel'):
        held_reference_error(pos, ref, ref_vel[:, :2], contact)
