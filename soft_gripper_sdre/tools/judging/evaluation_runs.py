"""The evaluation's runs (:mod:`~soft_gripper_sdre.tools.judging.evaluate`): each control law by a
named spec, on the demo's grasp and a faster one, on the same plant and noise, scored into a
:class:`RunSummary`; the gain grids that tuned the shipped gains; and every law on every trajectory
as independent jobs.

A run is the in-process loop (:func:`soft_gripper_sdre.analysis.law_runs.run_law`: lockstep,
:data:`NOISE` of seeded tip noise, torques saturated at :data:`U_MAX`), errors on the true tip.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from soft_gripper_sdre.analysis import law_runs
from soft_gripper_sdre.analysis.oracle import register_oracle_laws
from soft_gripper_sdre.control.laws import DEFAULT_CT, DEFAULT_PD, LAW_REGISTRY
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.judging import jobs

register_oracle_laws()          # the comparison includes the laws on the plant's true dynamics

#: (label, law name, make_law options)
LAW_SPECS = {
    'sdre': ('learned SDRE', 'sdre', {}),
    'sdre_qx': ('learned SDRE, Q(x)', 'sdre', {'adaptive': True}),
    'sdre_4e6': ('learned SDRE, q_pos 4e6', 'sdre', {'q_pos': 4e6}),
    'lqr': ('LQR at the origin', 'lqr', {}),
    'pd': ('task-space PD', 'pd', {}),
    'oracle': ('oracle SDRE (projected truth)', 'oracle', {}),
    'oracle_exact': ('oracle SDRE (exact eq. 13)', 'oracle_exact', {}),
    'sdre_ff': ('learned SDRE + feedforward', 'sdre_ff', {}),
    'sdre_ff_noi': ('learned SDRE + feedforward, no integral', 'sdre_ff', {'integral_gain': 0.0}),
    'sdre_ff_ref': ('learned SDRE + feedforward at x_d', 'sdre_ff', {'ff_at': 'ref'}),
    'pd_ff': ('task-space PD + p̈_d', 'pd', {'feedforward': True}),
    'oracle_ff': ('oracle SDRE + feedforward', 'oracle_ff', {}),
    'koopman_mpc': ('Koopman MPC', 'koopman_mpc', {}),
    'koopman_lqr': ('Koopman LQR', 'koopman_lqr', {}),
    'computed_torque': ('computed torque (learned model)', 'computed_torque', {}),
}
#: the laws whose PD gains tune_gains grids (LAW_SPECS keys): the gains they ship with, the grid's
#: k_p and k_d
TUNABLE = {'pd': (DEFAULT_PD, (3e3, 1e4, 1.5e4, 2e4), (40.0, 150.0)),
           'computed_torque': (DEFAULT_CT, (5e3, 1.5e4, 3e4, 6e4), (40.0, 80.0, 150.0))}
#: the grasp of the demo, and a faster one (30 mm in 0.5 s: peak 94 mm/s) that stresses the model
TRAJECTORIES = {
    'grasp': (GraspProfile(others='open'), 6.0),
    'fast': (GraspProfile(t_start=0.2, t_close=0.5, t_hold=0.5, t_open=0.5, others='open'), 2.0),
}
#: each torque's saturation [N·m] (the controller node's default torque_limit)
U_MAX = 0.0625
#: standard deviation of the tip sensor's noise [m]
NOISE = 5e-5


@dataclass
class RunSummary:
    """One law on one trajectory: the figures of
    :func:`~soft_gripper_sdre.analysis.law_runs.score` the report tabulates (errors in mm on the
    true tip)."""

    law: str
    trajectory: str
    rmse_mm_grasp: float          # mean over the grasping fingers
    max_mm_grasp: float
    rmse_mm_worst: float          # worst finger
    max_mm_all: float
    effort_rms_nm: float
    saturated_pct: float
    grasp_success: bool
    cube_mm: float
    check_fail_pct: float
    compute_us: float
    held_mm: float = float('nan')  # held-reference error, mean over the fingers


def run_law(key: str, trajectory: str, model: SDCModel, weights: Weights,
            duration: float | None = None, progress: bool = False, pd_gains: dict | None = None,
            koopman_path: Path | None = None, **law_options):
    """One closed-loop run: (RunSummary, LoopResult). ``pd_gains`` go to a law that takes them,
    ``koopman_path`` (None = the shipped model) to the Koopman laws, ``law_options`` (e.g.
    ``integral_gain``) to make_law over the spec's."""
    _, name, opts = LAW_SPECS[key]
    opts = dict(opts, **law_options)
    profile, dur = TRAJECTORIES[trajectory]
    dur = duration or dur
    if pd_gains and 'pd_gains' in LAW_REGISTRY[name].options:
        opts = dict(opts, pd_gains=pd_gains)
    if koopman_path is not None and name.startswith('koopman'):
        opts['koopman_path'] = koopman_path
    if 'q_pos' in opts:
        weights = Weights(opts.pop('q_pos'), weights.q_vel, weights.r)
    res = law_runs.run_law(name, model, weights, U_MAX, profile, dur,
                           SimConfig(scene='hand', noise_std=NOISE), progress=progress, **opts)
    return RunSummary(law=key, trajectory=trajectory,
                      **law_runs.score(res, profile).pick(RunSummary)), res


def tune_gains(model: SDCModel, weights: Weights, law: str = 'pd', kps=None, kds=None,
               trajectory: str = 'grasp',
               duration: float | None = None) -> list[tuple[float, float, float]]:
    """Grid over the PD gains (k_p, k_d) of ``law`` (a :data:`TUNABLE` key; None: its grid) on a
    trajectory: [(kp, kd, mean grasp-finger RMSE mm)]; a run that diverged or saturated > 5 % of the
    steps = inf."""
    if law not in TUNABLE:
        raise ValueError(f'law must be one of {tuple(TUNABLE)}, got {law!r}')
    _, grid_kps, grid_kds = TUNABLE[law]
    kps, kds = kps or grid_kps, kds or grid_kds
    rows = []
    for kp in kps:
        for kd in kds:
            s, _ = run_law(law, trajectory, model, weights, duration=duration,
                           pd_gains=dict(kp=kp, kd=kd))
            bad = s.saturated_pct > 5.0 or not np.isfinite(s.rmse_mm_grasp)
            rows.append((kp, kd, float('inf') if bad else s.rmse_mm_grasp))
    return rows


def tune_integral(model: SDCModel, weights: Weights, gains=(0.0, 3e4, 1e5, 3e5),
                  trajectory: str = 'grasp',
                  duration: float | None = None) -> list[tuple[float, float, float]]:
    """The default law's integral gain k_i over a grid: [(k_i, mean grasp-finger RMSE mm,
    held-reference error mm)]."""
    rows = []
    for gain in gains:
        s, _ = run_law('sdre_ff', trajectory, model, weights, duration=duration, integral_gain=gain)
        rows.append((gain, s.rmse_mm_grasp, s.held_mm))
    return rows


# -- every law, as independent jobs ---------------------------------------------------------------
@dataclass(frozen=True)
class LawRunsContext:
    """What the law runs share: the model's and the Koopman model's files (they travel with the
    jobs, :class:`~soft_gripper_sdre.tools.judging.jobs.FileBlob`) and the duration override."""

    model: jobs.FileBlob
    koopman: jobs.FileBlob
    duration: float | None


#: the SDC models this process has loaded, by the sha256 of their file
_models: dict[str, SDCModel] = {}


def run_law_job(context: LawRunsContext, job: tuple[str, str]):
    """One law on one trajectory, (RunSummary, LoopResult), as a job of
    :func:`~soft_gripper_sdre.tools.judging.jobs.run_jobs` (``job``: (trajectory, LAW_SPECS
    key))."""
    from soft_gripper_sdre.control.kernels import warm_up
    warm_up()                      # a new worker loads the kernels here, not inside the timed law
    trajectory, key = job
    if context.model.digest not in _models:
        _models[context.model.digest] = SDCModel(context.model.path())
    return run_law(key, trajectory, _models[context.model.digest], Weights(**DEFAULT_WEIGHTS),
                   duration=context.duration, koopman_path=context.koopman.path())


def run_laws(laws, trajectories, model_path: Path | None = None, koopman_path: Path | None = None,
             duration: float | None = None, runner: jobs.Runner = jobs.Runner(),
             progress: bool = True):
    """Every law of ``laws`` (LAW_SPECS keys) on every trajectory, with the default weights:
    ([RunSummary], {trajectory: {law: LoopResult}}), in the order trajectory by trajectory. The
    runs are independent jobs (:mod:`~soft_gripper_sdre.tools.judging.jobs`, on ``runner``); each
    result depends on its run only, so the numbers do not depend on the runner (but ``compute_us``,
    the law's wall time, does on the load)."""
    from soft_gripper_sdre.control.kernels import warm_up
    from soft_gripper_sdre.learning.koopman import DEFAULT_KOOPMAN
    from soft_gripper_sdre.learning.model import DEFAULT_MODEL
    warm_up()  # the kernels into numba's cache once, before the workers load them
    context = LawRunsContext(jobs.FileBlob.read(model_path or DEFAULT_MODEL),
                             jobs.FileBlob.read(koopman_path or DEFAULT_KOOPMAN), duration)
    todo = [(t, k) for t in trajectories for k in laws]
    out = jobs.run_jobs(run_law_job, todo, context, runner, desc='evaluate', progress=progress)
    summaries, results = [], {}
    for (traj, key), (summary, result) in zip(todo, out):
        summaries.append(summary)
        results.setdefault(traj, {})[key] = result
    return summaries, results
