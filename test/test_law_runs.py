"""Scoring a closed-loop run (analysis/law_runs.py) on hand-made runs: which fingers the
worst-finger scores take in, the grasp criterion, and what the evaluation and the robustness grid
take from it."""
import math

import numpy as np
import pytest

from soft_gripper_sdre.analysis.closed_loop import LoopResult
from soft_gripper_sdre.analysis.law_runs import grasp_success, score
from soft_gripper_sdre.analysis.metrics import TrackingMetrics
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.tools.judging.evaluation_runs import RunSummary
from soft_gripper_sdre.tools.judging.robustness_grid import CaseResult

PROFILE = GraspProfile(t_start=0.1, t_close=0.2, t_hold=0.3, t_open=0.2)   # hold: 0.3 ≤ t < 0.6
T, N = 100, 4


def run(metrics, contact_share=1.0, cube_moves=0.0) -> LoopResult:
    t = np.arange(T) * 0.01
    zeros = np.zeros((T, N, 2))
    contact = np.zeros((T, N), dtype=bool)
    hold = np.flatnonzero((t >= 0.3) & (t < 0.6))
    contact[hold[:int(round(contact_share * len(hold)))][:, None], [0, 2]] = True
    cube = np.zeros((T, 7))
    cube[:, 0] = np.linspace(0.0, cube_moves, T)
    return LoopResult(t=t, pos=zeros, vel=zeros, meas=zeros, est=np.zeros((T, N, 4)), ref_pos=zeros,
                      ref_vel=zeros, u=np.full((T, N, 2), 0.01), ok=np.ones((T, N), dtype=bool),
                      fallback=np.zeros((T, N), dtype=bool),
                      saturated=np.zeros((T, N, 2), dtype=bool),
                      residual=np.zeros((T, N)), contact=contact, cube=cube,
                      free_space=np.ones((T, N), dtype=bool), excursion=np.full(N, 0.03),
                      metrics=metrics, law_seconds=np.full(T, 2e-5))


def finger(rmse, peak=None, excursion=30.0, samples=50) -> TrackingMetrics:
    return TrackingMetrics(rmse, 2 * rmse if peak is None else peak, excursion,
                           100 * rmse / excursion if excursion else math.nan, samples)


def test_scores_of_a_clean_run():
    s = score(run([finger(0.1), finger(0.3), finger(0.2), finger(0.05)]), PROFILE)
    assert s.rmse_mm_grasp == pytest.approx(0.15) and s.max_mm_grasp == pytest.approx(0.4)
    assert s.rmse_mm_worst == pytest.approx(0.3) and s.rmse_pct_worst == pytest.approx(1.0)
    assert s.max_mm_all == pytest.approx(0.6) and s.effort_rms_nm == pytest.approx(0.01)
    assert (s.grasp_success and s.cube_mm == 0.0 and s.saturated_pct == 0.0
            and s.check_fail_pct == 0.0)
    assert s.compute_us == pytest.approx(20.0)


def test_worst_finger_scores_leave_out_fingers_without_a_score_but_not_a_diverged_one():
    no_free_space = TrackingMetrics(math.nan, math.nan, 30.0, math.nan, 0)
    still = finger(0.9, excursion=0.0)                 # its reference does not move: no percentage
    s = score(run([finger(0.1), no_free_space, finger(0.2), still]), PROFILE)
    assert (s.rmse_mm_worst == pytest.approx(0.9)
            and s.rmse_pct_worst == pytest.approx(100 * 0.2 / 30))
    diverged = score(run([finger(0.1), finger(math.nan, samples=50), finger(0.2), finger(0.1)]),
                     PROFILE)
    assert math.isnan(diverged.rmse_mm_worst) and math.isnan(diverged.max_mm_all)


@pytest.mark.parametrize('share, moves, ok', [(1.0, 0.0, True), (0.95, 0.0, True),
                                             (0.85, 0.0, False), (1.0, 0.0009, True),
                                             (1.0, 0.0011, False)])
def test_the_grasp_holds_when_both_fingers_touch_90_percent_of_the_hold_and_the_cube_stays(
        share, moves, ok):
    success, cube_mm = grasp_success(run([finger(0.1)] * N, share, moves), PROFILE)
    assert success is ok and cube_mm == pytest.approx(1e3 * moves)


def test_a_run_without_a_cube_pose_is_no_grasp():
    r = run([finger(0.1)] * N)
    r.cube[:] = np.nan
    success, cube_mm = grasp_success(r, PROFILE)
    assert not success and math.isnan(cube_mm)


def test_the_evaluation_and_the_grid_take_every_score_they_report_from_the_same_score():
    s = score(run([finger(0.1), finger(0.3), finger(0.2), finger(0.05)]), PROFILE)
    own = {RunSummary: {'law', 'trajectory'},
           CaseResult: {'law', 'variation', 'trajectory', 'close_mm', 'anchored', 'error'}}
    for cls, labels in own.items():
        assert set(s.pick(cls)) == set(cls.__dataclass_fields__) - labels
    summary = RunSummary(law='pd', trajectory='fast', **s.pick(RunSummary))
    assert summary.rmse_mm_worst == s.rmse_mm_worst and summary.held_mm == s.held_mm
