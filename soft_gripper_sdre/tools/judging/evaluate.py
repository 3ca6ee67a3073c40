"""Beyond the paper: every control law on the same plant, trajectories and noise, plus the learned
model scored against the simulator's ground truth. Writes ``report.md``, ``evaluate.json`` and PNGs.

    python -m soft_gripper_sdre.tools.judging.evaluate --out runs/evaluate
        # (make evaluate)
    python -m soft_gripper_sdre.tools.judging.evaluate --out DIR --laws sdre lqr --trajectories fast
        --workers 1
    python -m soft_gripper_sdre.tools.judging.evaluate --out runs/evaluate --ray auto
        # the runs on a Ray cluster

It uses the in-process loop (:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`: the
node graph's loop with the topics replaced by calls, lockstep, seeded noise), because the oracle
needs the plant's joint state at every step. The runs are independent jobs on ``--workers``
processes (default: every core) or on the Ray cluster at ``--ray ADDRESS``
(:mod:`soft_gripper_sdre.tools.judging.jobs`), with the same numbers wherever they run (but the
compute time). The numbers:

* free-space RMSE and max of the 2-D tip error [mm] on the *true* tip (grasping fingers 0 and 2,
  and the worst of the four), where the finger does not touch the cube;
* torque effort: RMS of the applied torques over the run and all fingers [N·m];
* grasp success: both grasping fingers touch the cube during ≥ 90 % of the hold phase and the
  cube moves < 1 mm;
* held-reference error: mean 2-D tip error [mm] where the reference stands still and the finger
  does not touch the cube (rest phases, and the hold of the fingers that do not grasp), averaged
  over the fingers (:func:`~soft_gripper_sdre.analysis.metrics.held_reference_error`);
* check failures: share of the per-finger steps whose Riccati checks failed (SDRE laws);
* compute time per 4-finger step [µs] (the law only; machine- and load-dependent).
"""
from __future__ import annotations

import argparse
from dataclasses import asdict
import json
from pathlib import Path

import numpy as np

from soft_gripper_sdre.analysis.ground_truth import score_model
from soft_gripper_sdre.analysis.law_plots import plot_feedforward, plot_laws, plot_model_vs_truth
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import PAPER_DATA_MODEL, ModelFileError, SDCModel
from soft_gripper_sdre.tools.judging import jobs
from soft_gripper_sdre.tools.judging.evaluation_runs import (
    LAW_SPECS,
    NOISE,
    TRAJECTORIES,
    TUNABLE,
    U_MAX,
    RunSummary,
    run_laws,
    tune_gains,
    tune_integral,
)

#: the paper-data model retrained with the singular-value penalty (docs/results.md "Beyond the
#: paper")
PAPER_DATA_SV_MODEL = PAPER_DATA_MODEL.with_name('paper_data_sv.pt')


def workspace_check_failures(model: SDCModel, weights: Weights, n: int = 9,
                             speeds=(0.0, 0.1)) -> float:
    """Share [%] of a grid of states (tip X ±10 mm, Y −35…+45 mm around rest; speeds in each
    direction) where an SDRE step on the learned model fails a Riccati check."""
    return workspace_survey(model, weights, n, speeds)['check_fail_pct']


def workspace_survey(model: SDCModel, weights: Weights, n: int = 9, speeds=(0.0, 0.1)) -> dict:
    """On the grid of :func:`workspace_check_failures`: the check-failure share [%], and G2's
    smallest singular value [m/s² per N·m] and largest condition number."""
    from soft_gripper_sdre.control.sdre import SdreController
    xs = np.linspace(-0.010, 0.010, n)
    ys = np.linspace(-0.035, 0.045, n)
    states = []
    for s in speeds:
        for vx, vy in ({(0.0, 0.0)} if s == 0 else {(s, 0.0), (-s, 0.0), (0.0, s), (0.0, -s)}):
            for x in xs:
                for y in ys:
                    states.append([x, y, vx, vy])
    X = np.asarray(states)
    A, G = model.AG(X)
    ctrl = SdreController(weights.Q, weights.R, U_MAX, n=len(X), method='reference')
    out = ctrl.step(A, G, X, np.zeros_like(X))
    sv = np.linalg.svd(G[:, 2:, :], compute_uv=False)
    return dict(check_fail_pct=100.0 * float((~out.ok).mean()), min_sv=float(sv[:, 1].min()),
                max_cond=float((sv[:, 0] / sv[:, 1]).max()), states=int(len(X)))


# -- report ---------------------------------------------------------------------------------------
def law_figures(results: dict, summaries: list[RunSummary], trajectory: str,
                out: Path) -> list[str]:
    """The figures of one trajectory's runs (``results``: law key → LoopResult) in ``out``: every
    law (RMSE and grasp success from ``summaries``), and the feedforward law against the paper's
    law and the PD when it ran."""
    labels = {key: LAW_SPECS[key][0] for key in results}
    scores = {s.law: (s.rmse_mm_grasp, s.grasp_success) for s in summaries
              if s.trajectory == trajectory}
    names = [plot_laws(results, labels, scores, trajectory, out / f'{trajectory}_laws.png').name]
    ff = [k for k in ('sdre', 'pd', 'pd_ff', 'oracle_ff', 'sdre_ff') if k in results]
    if 'sdre_ff' in ff:
        names.append(plot_feedforward({k: results[k] for k in ff}, labels, trajectory,
                                      out / f'{trajectory}_feedforward.png',
                                      highlight='sdre_ff').name)
    return names


def _fmt(v, f='.3f'):
    return 'diverged' if not np.isfinite(v) else format(v, f)


def _law_row(s: RunSummary) -> str:
    return (f'| {LAW_SPECS[s.law][0]} | {_fmt(s.rmse_mm_grasp)} | '
            f'{_fmt(s.max_mm_grasp, ".2f")} | '
            f'{_fmt(s.rmse_mm_worst)} | {_fmt(s.max_mm_all, ".2f")} | '
            f'{"n/a" if np.isnan(s.held_mm) else _fmt(s.held_mm)} | '
            f'{s.effort_rms_nm:.4f} | '
            f'{s.saturated_pct:.1f} % | {"yes" if s.grasp_success else "no"} | '
            f'{s.cube_mm:.2f} | {s.check_fail_pct:.2f} % | {s.compute_us:.0f} |')


def _trajectory_section(traj: str, summaries: list[RunSummary], figures: list[str]) -> list[str]:
    """The grasp ``traj``: its timing, every law's row, and its figures."""
    p, dur = TRAJECTORIES[traj]
    lines = [f'## {traj}: close {p.close_distance * 1e3:g} mm in {p.t_close:g} s, '
             f'hold {p.t_hold:g} s, open in {p.t_open:g} s ({dur:g} s run)', '',
             '| law | RMSE grasp fingers [mm] | max grasp [mm] | worst-finger RMSE [mm] '
             '| max any [mm] | held-reference error [mm] | torque RMS [N·m] | saturated '
             '| grasp | cube moved [mm] | check failures '
             '| compute [µs/step] |',
             '| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | :---: | ---: | ---: '
             '| ---: |']
    lines += [_law_row(s) for s in summaries if s.trajectory == traj]
    lines += ['']
    for f in figures:
        if f.startswith(traj):
            lines += [f'![{traj}]({f})', '']
    return lines


def _model_section(s: dict) -> list[str]:
    """The learned model against the ground truth (:func:`score_model`'s statistics ``s``)."""
    lines = ['## The learned model against the ground truth', '',
             f'Held-out signal {s["signal"]} on the hand-mounted finger, '
             f'{s["samples"]} states. R² per axis (X, Y):', '',
             '| compared | R² X | R² Y |', '| --- | ---: | ---: |']
    for key, label in (('r2_learned_vs_sim', 'learned ẍ vs simulator'),
                       ('r2_exact_vs_sim', 'exact ẍ (friction off) vs simulator'),
                       ('r2_proj_vs_sim', 'projected ẍ vs simulator'),
                       ('r2_learned_vs_exact', 'learned ẍ vs exact'),
                       ('r2_learned_vs_proj', 'learned ẍ vs projected'),
                       ('drift_r2_vs_exact', 'learned drift A(x)x vs exact f'),
                       ('drift_r2_vs_proj', 'learned drift A(x)x vs projected f')):
        lines.append(f'| {label} | {s[key][0]:.3f} | {s[key][1]:.3f} |')
    lines += ['', f'The drifts agree better than the matrices: [A₂₁ A₂₂] learned vs the '
              f'oracle\'s (projected) factorisation differ by {s["a_rel_diff_median"]:.2f} '
              '(median relative Frobenius) — the SDC factorisation is not unique.', '',
              '| learned G2 vs | column angle error (median, ax0 / ax1) '
              '| magnitude ratio (median) | relative Frobenius error (median) |',
              '| --- | ---: | ---: | ---: |']
    for key, label in (('g2_vs_exact', 'exact J M⁻¹ B'),
                       ('g2_vs_proj', 'projected S M_r⁻¹ Φᵀ B')):
        g = s[key]
        lines.append(f'| {label} | {g["angle_median_deg"][0]:.1f}° / '
                     f'{g["angle_median_deg"][1]:.1f}° | '
                     f'{g["magnitude_ratio_median"][0]:.2f} / '
                     f'{g["magnitude_ratio_median"][1]:.2f} | '
                     f'{g["rel_frobenius_median"]:.2f} |')
    return lines + ['', '![model vs truth](model_vs_truth.png)', '']


def _workspace_section(workspace: dict) -> list[str]:
    """The Riccati checks on the workspace grid (model label → :func:`workspace_survey`)."""
    lines = ['## Riccati checks on a workspace grid', '',
             'Tip X ±10 mm, Y −35…+45 mm around rest (9 × 9), at rest and at 0.1 m/s in four '
             'directions; one SDRE step (scipy solver, every check of Remarks 2–3) per '
             'state.', '',
             '| model | check failures | smallest σ_min(G2) [m/s² per N·m] '
             '| largest cond(G2) |',
             '| --- | ---: | ---: | ---: |']
    for k, v in workspace.items():
        lines.append(f'| {k} | {v["check_fail_pct"]:.2f} % | {v["min_sv"]:.3g} | '
                     f'{v["max_cond"]:.3g} |')
    return lines + ['']


def write_report(out: Path, summaries: list[RunSummary], figures: list[str],
                 model_stats: dict | None, workspace: dict | None, expectation: dict) -> Path:
    """``out/report.md``: per trajectory every law's figures, the expectation's verdict, and, when
    given, the model against the ground truth and the workspace checks."""
    lines = ['# Beyond the paper: evaluation report', '',
             'Generated by `python -m soft_gripper_sdre.tools.judging.evaluate` (in-process loop, '
             f'lockstep, {NOISE * 1e3:g} mm tip noise, seed 0; errors on the true tip).', '']
    for traj in dict.fromkeys(s.trajectory for s in summaries):
        lines += _trajectory_section(traj, summaries, figures)
    lines += ['## The expectation', '']
    for k, v in expectation.items():
        lines.append(f'- {k}: **{v}**')
    lines.append('')
    if model_stats:
        lines += _model_section(model_stats)
    if workspace:
        lines += _workspace_section(workspace)
    path = out / 'report.md'
    path.write_text('\n'.join(lines) + '\n')
    return path


def expectation_verdict(summaries: list[RunSummary]) -> dict:
    """The expectation of docs/results.md "Beyond the paper", per trajectory: learned SDRE beats
    LQR and PD on free-space RMSE (grasping fingers) and is within 1.5× of the oracle — for the
    paper's law (``sdre`` against ``oracle``) and, when run, the feedforward law (``sdre_ff``
    against ``oracle_ff`` if run, else ``oracle``)."""
    out = {}
    for traj in dict.fromkeys(s.trajectory for s in summaries):
        by = {s.law: s.rmse_mm_grasp for s in summaries if s.trajectory == traj}
        if not {'sdre', 'lqr', 'pd', 'oracle'} <= set(by):
            continue
        pairs = [('sdre', 'SDRE', 'oracle')]
        if 'sdre_ff' in by:
            pairs.append(('sdre_ff', 'SDRE + feedforward',
                          'oracle_ff' if 'oracle_ff' in by else 'oracle'))
        for law, label, oracle in pairs:
            beats = by[law] < by['lqr'] and by[law] < by['pd']
            ratio = by[law] / by[oracle] if by[oracle] > 0 else float('nan')
            out[f'{traj}: {label} {by[law]:.3f} mm vs LQR {by["lqr"]:.3f}, PD {by["pd"]:.3f}, '
                f'{oracle} {by[oracle]:.3f} ({law}/{oracle} {ratio:.2f})'] = (
                ('beats LQR and PD' if beats else 'does NOT beat both LQR and PD') + ', ' +
                ('within 1.5× of the oracle' if ratio <= 1.5 else 'NOT within 1.5× of the oracle'))
    return out


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=Path('runs/evaluate'))
    ap.add_argument('--laws', nargs='+', default=list(LAW_SPECS), choices=list(LAW_SPECS))
    ap.add_argument('--trajectories', nargs='+', default=list(TRAJECTORIES),
                    choices=list(TRAJECTORIES))
    ap.add_argument('--duration', type=float, default=None,
                    help='override every run\'s duration [s]')
    ap.add_argument('--no-model-score', action='store_true',
                    help='skip the ground-truth model scoring')
    ap.add_argument('--tune', choices=[*TUNABLE, 'integral'], default=None,
                    help='print the tuning grid of this law\'s PD gains (or of the default law\'s '
                         'integral gain) on both trajectories and exit')
    ap.add_argument('--tune-pd', dest='tune', action='store_const', const='pd',
                    help='the same as --tune pd')
    ap.add_argument('--model', type=Path, default=None,
                    help='checkpoint (default: the shipped model)')
    ap.add_argument('--koopman', type=Path, default=None,
                    help='Koopman model of the koopman_* laws (default: the shipped one; '
                         'tools.learning.koopman writes one)')
    jobs.add_arguments(ap)
    return ap


def _print_tuning(tune: str, trajectories, model: SDCModel, weights: Weights,
                  duration: float | None) -> None:
    """``--tune``: the grid of a law's PD gains, or of the default law's integral gain."""
    if tune == 'integral':
        for traj in trajectories:
            for gain, rmse, held in tune_integral(model, weights, trajectory=traj,
                                                  duration=duration):
                print(f'{traj} integral_gain={gain:g}: grasp-finger RMSE {rmse:.4f} mm, '
                      f'held-reference error {held:.4f} mm')
        return
    for traj in trajectories:
        for kp, kd, rmse in tune_gains(model, weights, tune, trajectory=traj, duration=duration):
            print(f'{traj} {tune} kp={kp:g} kd={kd:g}: grasp-finger RMSE {rmse:.4f} mm')
    print(f'shipped: {TUNABLE[tune][0]}')


def _score_models(model: SDCModel, model_path: Path | None, weights: Weights,
                  out: Path) -> tuple[dict, dict]:
    """The model against the ground truth (its statistics; ``model_vs_truth.png`` in ``out``) and
    the workspace checks of the shipped models and of ``model_path`` if given."""
    scored = score_model(model)
    plot_model_vs_truth(scored['samples'], out / 'model_vs_truth.png')
    workspace = {'default (shipped)': workspace_survey(SDCModel(), weights),
                 'paper_data (shipped)': workspace_survey(SDCModel(PAPER_DATA_MODEL), weights)}
    if PAPER_DATA_SV_MODEL.is_file():
        workspace['paper_data_sv (shipped, σ-penalty)'] = workspace_survey(
            SDCModel(PAPER_DATA_SV_MODEL), weights)
    if model_path is not None:
        workspace[str(model_path)] = workspace_survey(model, weights)
    return scored['stats'], workspace


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    runner = jobs.runner_from_args(ap, args)
    if args.koopman is not None and not args.koopman.is_file():
        ap.error(f'--koopman: no such file {args.koopman}')
    if args.duration is not None and not args.duration > 0:
        ap.error(f'--duration must be > 0 s, got {args.duration}')
    try:
        model = SDCModel(args.model)
    except ModelFileError as exc:
        ap.error(f'--model: {exc}')
    weights = Weights(**DEFAULT_WEIGHTS)
    if args.tune:
        _print_tuning(args.tune, args.trajectories, model, weights, args.duration)
        return 0
    try:
        with jobs.session(runner):
            args.out.mkdir(parents=True, exist_ok=True)
            summaries, results = run_laws(args.laws, args.trajectories, args.model, args.koopman,
                                          args.duration, runner)
    except jobs.JobsError as exc:
        ap.error(f'--ray: {exc}')
    for s in summaries:
        print(f'{s.trajectory:6s} {s.law:15s} RMSE {s.rmse_mm_grasp:.3f} mm, '
              f'max {s.max_mm_all:.2f} mm, held {s.held_mm:.3f} mm, '
              f'checks failed {s.check_fail_pct:.2f} %, {s.compute_us:.0f} µs/step')
    figures = [name for traj, res in results.items()
               for name in law_figures(res, summaries, traj, args.out)]
    model_stats = workspace = None
    if not args.no_model_score:
        model_stats, workspace = _score_models(model, args.model, weights, args.out)
    verdict = expectation_verdict(summaries)
    (args.out / 'evaluate.json').write_text(json.dumps(
        dict(runs=[asdict(s) for s in summaries], expectation=verdict, model=model_stats,
             workspace_check_failures_pct=workspace), indent=2))
    path = write_report(args.out, summaries, figures, model_stats, workspace, verdict)
    print(path.read_text())
    return 0

if __name__ == '__main__':
    raise SystemExit(main())
