"""The evaluation tool: a short run of the laws on the fast grasp, and the model scoring."""
import json

import numpy as np
import pytest

from soft_gripper_sdre.analysis.ground_truth import score_model
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import PAPER_DATA_MODEL, SDCModel
from soft_gripper_sdre.tools.judging import evaluate as ev
from soft_gripper_sdre.tools.judging.evaluation_runs import LAW_SPECS, RunSummary, run_law


@pytest.fixture(scope='module')
def model():
    return SDCModel()


@pytest.fixture(scope='module')
def fast_runs(model):
    """The four laws of the expectation (docs/results.md "Beyond the paper"), the feedforward laws
    beyond the paper (SDRE with and without integral action, oracle and PD with the reference
    acceleration) and computed torque, on the first 1.5 s of the fast grasp (closing, holding, half
    the opening), with the default noise and weights."""
    w = Weights(**DEFAULT_WEIGHTS)
    return {k: run_law(k, 'fast', model, w, duration=1.5)[0]
            for k in ('sdre', 'lqr', 'pd', 'oracle', 'sdre_ff', 'oracle_ff', 'pd_ff', 'sdre_ff_noi',
                      'computed_torque')}


@pytest.mark.slow
@pytest.mark.timeout(150)     # the first user of fast_runs: its set-up counts here
def test_every_law_tracks_the_fast_grasp_without_failed_checks(fast_runs):
    for key, s in fast_runs.items():
        assert s.saturated_pct < 1.0, (key, s)
        assert s.check_fail_pct < 0.1, (key, s)
        assert s.rmse_mm_grasp < 2.0, (key, s)       # 30 mm in 0.5 s: ≤ 7 % of the excursion
        assert np.isfinite(s.compute_us) and s.compute_us > 0


@pytest.mark.slow
def test_learned_sdre_is_within_1_5x_of_the_oracle(fast_runs):
    """The expectation, second half: holds as measured."""
    assert fast_runs['sdre'].rmse_mm_grasp <= 1.5 * fast_runs['oracle'].rmse_mm_grasp


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason='measured: the learned SDRE does not beat LQR frozen at the '
                   'origin and the tuned PD on free-space RMSE (docs/results.md '
                   '"Beyond the paper")')
def test_learned_sdre_beats_lqr_and_pd(fast_runs):
    """The expectation, first half: does NOT hold as measured (strict xfail: this test
    starts failing the day it holds, so docs/results.md must then be updated)."""
    s = fast_runs['sdre'].rmse_mm_grasp
    assert s < fast_runs['lqr'].rmse_mm_grasp and s < fast_runs['pd'].rmse_mm_grasp


@pytest.mark.slow
def test_sdre_with_feedforward_beats_lqr_and_pd_and_is_within_1_5x_of_the_oracle(fast_runs):
    """Beyond the paper: the expectation holds for SDRE feedback + model-inversion feedforward
    (docs/results.md "Beyond the paper"), against the PD with the same reference acceleration too,
    and within 1.5× of the oracle with the same feedforward (measured: below it)."""
    s = fast_runs['sdre_ff'].rmse_mm_grasp
    assert s < fast_runs['lqr'].rmse_mm_grasp and s < fast_runs['pd'].rmse_mm_grasp
    assert s < fast_runs['pd_ff'].rmse_mm_grasp
    assert s <= 1.5 * fast_runs['oracle_ff'].rmse_mm_grasp
    assert s < 0.5 * fast_runs['sdre'].rmse_mm_grasp           # the feedforward, not the weights


@pytest.mark.slow
def test_integral_action_removes_the_held_offset_without_giving_back_tracking(fast_runs):
    """The default law's integral action (docs/results.md "Integral action"): the error where the
    reference stands still and is reachable falls below the law's without it and below the 0.05 mm
    target with the margin measured there, and the free-space RMSE of the moving fingers is no
    worse than 1.1× the law's without it; the grasp holds."""
    on, off = fast_runs['sdre_ff'], fast_runs['sdre_ff_noi']
    assert on.held_mm < off.held_mm and on.held_mm <= 0.025
    assert (on.rmse_mm_grasp <= 1.1 * off.rmse_mm_grasp
            and on.rmse_mm_worst <= 1.1 * off.rmse_mm_worst)
    assert on.grasp_success and on.saturated_pct == 0.0


@pytest.mark.slow
def test_computed_torque_tracks_at_least_as_well_as_the_riccati_gains_on_the_same_inversion(
        fast_runs):
    """Computed torque with the learned model (tuned PD gains where sdre_ff has the SDRE's Riccati
    gains) against sdre_ff without integral action, as docs/results.md reports: on this part of the
    fast grasp the grasping fingers are tracked as well (within 10 %) and the worst finger better;
    the Riccati equation does not earn its cost here."""
    ct, riccati = fast_runs['computed_torque'], fast_runs['sdre_ff_noi']
    assert ct.rmse_mm_grasp <= 1.1 * riccati.rmse_mm_grasp
    assert ct.rmse_mm_worst < riccati.rmse_mm_worst
    assert ct.grasp_success and ct.check_fail_pct == 0.0


def test_run_law_leaves_the_law_specs_as_they_were(model):
    """A spec's options (q_pos here) are taken from a copy: the same law runs the same way twice."""
    import copy
    before = copy.deepcopy(LAW_SPECS)
    run_law('sdre_4e6', 'fast', model, Weights(**DEFAULT_WEIGHTS), duration=0.005,
               integral_gain=None)
    assert LAW_SPECS == before


def test_model_scoring_against_the_ground_truth(model):
    stats = score_model(model, seconds=1.0, every=20)['stats']
    assert stats['samples'] == 49
    # the learned model predicts the simulator's acceleration on the held-out signal
    assert stats['r2_learned_vs_sim'][1] > 0.9
    # and its G2 points where the projected true input map points
    assert max(stats['g2_vs_proj']['angle_median_deg']) < 10.0


def test_workspace_grid_checks(model):
    w = Weights(**DEFAULT_WEIGHTS)
    assert ev.workspace_check_failures(model, w, n=5) == 0.0
    assert ev.workspace_check_failures(SDCModel(PAPER_DATA_MODEL), w, n=5) == 0.0


def test_report_is_written(tmp_path):
    s = RunSummary('lqr', 'fast', 1.0, 2.0, 1.1, 2.1, 0.01, 0.0, True, 0.1, 0.0, 50.0)
    ws = {'default': dict(check_fail_pct=0.0, min_sv=200.0, max_cond=4.0)}
    path = ev.write_report(tmp_path, [s], ['fast_laws.png'], None, ws, {'x': 'y'})
    text = path.read_text()
    assert '| LQR at the origin | 1.000 | 2.00 |' in text and 'fast_laws.png' in text
    assert json.dumps(ev.expectation_verdict([s])) == '{}'       # needs all four laws


def _summary(law: str, rmse: float, success: bool = True) -> RunSummary:
    return RunSummary(law, 'fast', rmse, 2 * rmse, rmse, 2 * rmse, 0.01, 0.0, success, 0.1,
                         0.0, 50.0)


def test_law_figures_add_the_feedforward_comparison_when_the_feedforward_law_ran(tmp_path):
    from types import SimpleNamespace
    t = np.arange(50) * 1e-3
    ref = np.zeros((50, 4, 2)) + np.linspace(0, 1e-2, 50)[:, None, None]

    def run(lag):
        return SimpleNamespace(t=t, pos=ref - lag, ref_pos=ref, u=np.full((50, 4, 2), lag))
    summaries = [_summary('sdre', 1.0), _summary('lqr', 2.0)]
    names = ev.law_figures({'sdre': run(1e-3), 'lqr': run(2e-3)}, summaries, 'fast', tmp_path)
    assert names == ['fast_laws.png']
    summaries = [_summary('sdre', 1.0), _summary('pd', float('nan'), False),
                 _summary('sdre_ff', 0.1)]
    names = ev.law_figures({'sdre': run(1e-3), 'pd': run(2e-3), 'sdre_ff': run(1e-4)}, summaries,
                           'fast', tmp_path)
    assert names == ['fast_laws.png', 'fast_feedforward.png']
    assert all((tmp_path / n).read_bytes()[:4] == b'\x89PNG' for n in names)


def test_the_traced_laws_are_the_highlighted_the_papers_and_the_best_rival():
    from soft_gripper_sdre.analysis.law_plots import detail_laws
    scores = {'sdre': (0.4, True), 'sdre_ff': (0.08, True), 'pd': (0.2, True), 'lqr': (0.3, True),
              'oracle_ff': (0.01, True), 'koopman': (float('nan'), False),
              'sdre_ff_ref': (0.09, True)}
    # no yardstick that knows the plant, no diverged run, no variant of the highlighted law
    assert detail_laws(scores, 'sdre_ff') == ['sdre_ff', 'sdre', 'pd']


@pytest.mark.slow
@pytest.mark.timeout(100)
def test_command_line_writes_the_report(tmp_path, run_main):
    import subprocess
    import sys
    out = tmp_path / 'ev'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.judging.evaluate',
                           '--out', str(out),
                           '--laws', 'lqr', 'pd', '--trajectories', 'fast', '--duration', '0.4',
                           '--no-model-score'], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    text = (out / 'report.md').read_text()
    assert '| LQR at the origin |' in text and '| task-space PD |' in text
    assert (out / 'fast_laws.png').stat().st_size > 10_000
    runs = json.loads((out / 'evaluate.json').read_text())['runs']
    assert ({r['law'] for r in runs} == {'lqr', 'pd'}
            and all(r['check_fail_pct'] == 0.0 for r in runs))
    assert all(np.isfinite(r['compute_us']) and r['compute_us'] > 0
               for r in runs)  # the loop timed the law
    # the refusals, in this process (the run above went through python -m)
    bad = run_main(ev.main, '--laws', 'mpc')
    assert bad.returncode == 2 and 'mpc' in bad.stderr
    for args, why in ((['--duration', '0'], '--duration must be > 0'),
                      (['--model', str(tmp_path / 'missing.pt')], '--model:')):
        bad = run_main(ev.main, '--out', tmp_path / 'bad', *args)
        assert bad.returncode == 2 and why in bad.stderr, bad.stderr
        assert not (tmp_path / 'bad').exists()
