"""One control law on the in-process loop, run and scored the same way wherever laws are compared
(the evaluation, :mod:`soft_gripper_sdre.tools.judging.evaluate`, and the robustness grid,
:mod:`soft_gripper_sdre.tools.judging.robustness_grid`).

The scores are taken on the *true* tip in free space
(:class:`~soft_gripper_sdre.analysis.closed_loop.LoopResult`) and on the grasp. The worst-finger
scores are over the fingers that have one (a finger that never leaves the cube has no free-space
sample, one whose reference does not move no excursion); a finger whose loop diverged to NaN makes
them NaN, so a diverged run never looks better than it is.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from soft_gripper_sdre.analysis.closed_loop import LoopResult, run_closed_loop
from soft_gripper_sdre.analysis.metrics import held_reference_error
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.sim.hand import SimConfig

#: share of the hold phase both grasping fingers must touch the cube, and how far it may move [m]
GRASP_CONTACT_SHARE = 0.9
GRASP_CUBE_MOVE = 1e-3


def run_law(name: str, model, weights: Weights, u_max: float, profile: GraspProfile,
            duration: float, sim_config: SimConfig, sensor_delay: float = 0.0,
            progress: bool = False, **options) -> LoopResult:
    """Build the law ``name`` (:func:`~soft_gripper_sdre.control.laws.make_law` with ``options``),
    run the grasp ``profile`` for ``duration`` seconds of sim time on ``sim_config``'s plant and
    release what the law holds (the oracles hold a PyBullet client), whatever happens."""
    law = make_law(name, model, weights, u_max, dt=sim_config.control_period, **options)
    try:
        return run_closed_loop(law, duration=duration, sim_config=sim_config, profile=profile,
                               progress=progress, sensor_delay=sensor_delay)
    finally:
        close = getattr(law, 'close', None)
        if close is not None:
            close()


def grasp_success(result: LoopResult, profile: GraspProfile) -> tuple[bool, float]:
    """(success, largest cube displacement [mm]): both grasping fingers touch the cube during at
    least 90 % of the hold phase and the cube moves less than 1 mm."""
    t = result.t
    hold = ((t >= profile.t_start + profile.t_close)
            & (t < profile.t_start + profile.t_close + profile.t_hold))
    touching = result.contact[hold][:, list(profile.grasp_fingers)].mean(axis=0)
    cube = result.cube[:, :3]
    if not np.all(np.isfinite(cube)):
        return False, float('nan')
    moved = float(np.max(np.linalg.norm(cube - cube[0], axis=1)))
    return bool(np.all(touching >= GRASP_CONTACT_SHARE) and moved < GRASP_CUBE_MOVE), 1e3 * moved


@dataclass(frozen=True)
class LoopScore:
    """The scores of one run (true tip, free space)."""

    rmse_mm_grasp: float          # free-space RMSE, mean over the grasping fingers [mm]
    max_mm_grasp: float           # largest free-space error of a grasping finger [mm]
    rmse_mm_worst: float          # free-space RMSE of the worst finger [mm]
    rmse_pct_worst: float         # free-space RMSE of the worst finger, % of its peak excursion
    max_mm_all: float             # largest free-space error of any finger [mm]
    effort_rms_nm: float          # RMS of the applied torques over the run and the fingers [N·m]
    saturated_pct: float          # share of the per-finger steps with a saturated torque [%]
    grasp_success: bool
    cube_mm: float                # largest displacement of the cube [mm]
    check_fail_pct: float         # share of the per-finger steps whose Riccati checks failed [%]
    compute_us: float             # the law's mean wall time per step [µs]
    held_mm: float                # held-reference error, mean over the fingers [mm]

    def pick(self, cls) -> dict:
        """The scores that the dataclass ``cls`` has fields for, by name."""
        wanted = {f.name for f in fields(cls)}
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name in wanted}


def score(result: LoopResult, profile: GraspProfile) -> LoopScore:
    """Score a run of the grasp ``profile``."""
    m = result.metrics
    grasping = list(profile.grasp_fingers)
    ok, cube_mm = grasp_success(result, profile)
    with np.errstate(all='ignore'):
        held = held_reference_error(result.pos, result.ref_pos, result.ref_vel, result.contact)
        return LoopScore(
            rmse_mm_grasp=float(np.mean([m[i].rmse_mm for i in grasping])),
            max_mm_grasp=float(np.max([m[i].max_mm for i in grasping])),
            rmse_mm_worst=_worst([x.rmse_mm for x in m if x.samples]),
            rmse_pct_worst=_worst([x.rmse_pct for x in m if x.samples and x.excursion_mm > 0]),
            max_mm_all=_worst([x.max_mm for x in m if x.samples]),
            effort_rms_nm=float(np.sqrt(np.mean(result.u ** 2))),
            saturated_pct=100.0 * float(result.saturated.any(axis=2).mean()),
            grasp_success=ok, cube_mm=cube_mm,
            check_fail_pct=100.0 * float((~result.ok).mean()),
            compute_us=1e6 * float(np.mean(result.law_seconds)),
            held_mm=float(np.nanmean(held)))


def _worst(values: list[float]) -> float:
    """The largest value; NaN if there is none or one is NaN."""
    return float(np.max(values)) if values else float('nan')
