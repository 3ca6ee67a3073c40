"""The robustness grid's runs: every law on plants and sensors the learned model was not trained on.

A case is one law on one trajectory with one :class:`Variation` of the plant or the sensor. Each
case runs the in-process closed loop
(:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`: the node graph's loop with the
topics replaced by calls, the KF, lockstep, seeded noise) like
:mod:`soft_gripper_sdre.tools.judging.evaluate`, with the model trained on the nominal finger, and
is scored on the true tip in free space and on the grasp
(:mod:`soft_gripper_sdre.analysis.law_runs`).

The cases are independent, so :func:`run_grid` runs them as jobs
(:mod:`soft_gripper_sdre.tools.judging.jobs`): on a pool of spawned worker processes or on a Ray
cluster, each worker with its own simulator, law and copy of the model. A case's result depends on
the case only (every simulator starts from the same seed, every law is built fresh), so the grid
gives the same numbers, bit for bit, whatever the number of workers and wherever they run.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from soft_gripper_sdre.analysis import law_runs

# the oracle laws know the nominal plant's dynamics, so the grid leaves them out unless asked
from soft_gripper_sdre.analysis.oracle import ORACLE_LAWS, register_oracle_laws
from soft_gripper_sdre.control.laws import LAW_REGISTRY
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, SDCModel
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.sim.plant import PlantVariation
from soft_gripper_sdre.tools.judging.evaluation_runs import NOISE, TRAJECTORIES, U_MAX
from soft_gripper_sdre.tools.judging.jobs import FileBlob, Runner, run_jobs

register_oracle_laws()          # asked for by name (--laws), never by default


@dataclass(frozen=True)
class Variation:
    """A plant or sensor the model was not trained on: the plant's scales, the tip noise [m] and the
    sensor delay [s] (the nominal values are those of
    :mod:`soft_gripper_sdre.tools.judging.evaluation_runs`)."""

    label: str
    plant: PlantVariation = field(default_factory=PlantVariation)
    noise_std: float = NOISE
    sensor_delay: float = 0.0


#: the grid's variations by name, the nominal plant (the reference row) first
VARIATIONS = {
    'nominal': Variation('nominal plant'),
    'stiffness_+20': Variation('joint stiffness +20 %', PlantVariation(stiffness_scale=1.2)),
    'stiffness_-20': Variation('joint stiffness −20 %', PlantVariation(stiffness_scale=0.8)),
    'friction_x0.5': Variation('joint friction ×0.5', PlantVariation(friction_scale=0.5)),
    'friction_x2': Variation('joint friction ×2', PlantVariation(friction_scale=2.0)),
    'tip_mass_+50': Variation('tip mass +50 %', PlantVariation(tip_mass_scale=1.5)),
    'cube_mass_x5': Variation('cube mass ×5', PlantVariation(cube_mass_scale=5.0)),
    'delay_2ms': Variation('sensor delay 2 ms', sensor_delay=0.002),
    'noise_0.1mm': Variation('sensor noise 0.1 mm', noise_std=1e-4),
    'noise_0.2mm': Variation('sensor noise 0.2 mm', noise_std=2e-4),
}


def grid_laws() -> list[str]:
    """The laws the grid runs by default: every registered law but the oracles, in registry
    order."""
    return [name for name in LAW_REGISTRY if name not in ORACLE_LAWS]


def known_laws() -> list[str]:
    """Every law the grid can run: the registry's, oracles included."""
    return list(LAW_REGISTRY)


@dataclass(frozen=True)
class Case:
    """One run of the grid: a law (registry name) on a trajectory (:data:`TRAJECTORIES`) with a
    variation (:data:`VARIATIONS`); ``duration`` [s] overrides the trajectory's run length and
    ``close_distance`` [m] the grasping fingers' travel. ``anchored``: the grasping fingers close
    to the nominal finger's closed pose (the model's rest Y plus the travel) wherever this plant's
    finger rests, instead of travelling that far from its own rest."""

    law: str
    variation: str
    trajectory: str = 'grasp'
    duration: float | None = None
    close_distance: float | None = None
    anchored: bool = False

    def profile(self, nominal_rest_y: float | None = None):
        """The trajectory's :class:`~soft_gripper_sdre.control.trajectory.GraspProfile` with this
        case's travel; an anchored case needs the nominal finger's rest Y [m]."""
        profile = TRAJECTORIES[self.trajectory][0]
        if self.close_distance is not None:
            profile = replace(profile, close_distance=self.close_distance)
        if self.anchored:
            if nominal_rest_y is None:
                raise ValueError('an anchored case needs the nominal rest Y')
            profile = replace(profile, close_to=nominal_rest_y + profile.close_distance)
        return profile


@dataclass(frozen=True)
class CaseResult:
    """The scores of one case (NaN where the loop diverged; ``error``: why the run failed, else
    '')."""

    law: str
    variation: str
    trajectory: str
    rmse_mm_grasp: float          # free-space RMSE, mean over the grasping fingers [mm]
    rmse_pct_worst: float         # free-space RMSE of the worst finger, % of its peak excursion
    max_mm_all: float             # largest free-space error of any finger [mm]
    grasp_success: bool
    cube_mm: float                # largest displacement of the cube [mm]
    saturated_pct: float          # share of the per-finger steps with a saturated torque
    check_fail_pct: float         # share of the per-finger steps whose Riccati checks failed
    # the grasping fingers' travel from rest [mm] (anchored: the nominal one's)
    close_mm: float = float('nan')
    anchored: bool = False          # the closed pose anchored to the hand (Case.anchored)
    error: str = ''


def run_case(case: Case, model: SDCModel) -> CaseResult:
    """Run one case in this process and score it."""
    variation = VARIATIONS[case.variation]
    profile, duration = case.profile(float(model.rest_tip[1])), TRAJECTORIES[case.trajectory][1]
    config = SimConfig(scene='hand', noise_std=variation.noise_std, plant=variation.plant)
    res = law_runs.run_law(case.law, model, Weights(**DEFAULT_WEIGHTS), U_MAX, profile,
                           case.duration or duration, config, sensor_delay=variation.sensor_delay)
    return CaseResult(law=case.law, variation=case.variation, trajectory=case.trajectory,
                      close_mm=profile.close_distance * 1e3, anchored=case.anchored,
                      **law_runs.score(res, profile).pick(CaseResult))


# -- the jobs -------------------------------------------------------------------------------------
#: the models this process has loaded, by the sha256 of their file
_models: dict[str, SDCModel] = {}


def _model_of(blob: FileBlob) -> SDCModel:
    if blob.digest not in _models:
        _models[blob.digest] = SDCModel(blob.path())
    return _models[blob.digest]


def run_case_job(model: FileBlob, case: Case) -> CaseResult:
    """One case as a job of :func:`~soft_gripper_sdre.tools.judging.jobs.run_jobs` (the model's file
    travels with it); a run that fails is a result with its ``error``, so the rest of the grid is
    kept."""
    try:
        return run_case(case, _model_of(model))
    except Exception as exc:  # noqa: BLE001 — one failing law must not lose the rest of the grid
        nan = float('nan')
        travel = (case.close_distance if case.close_distance is not None
                  else TRAJECTORIES[case.trajectory][0].close_distance)
        return CaseResult(case.law, case.variation, case.trajectory, nan, nan, nan, False, nan, nan,
                          nan, 1e3 * travel, case.anchored, error=f'{type(exc).__name__}: {exc}')


def run_grid(cases: list[Case], workers: int | Runner, model_path=None,
             progress: bool = True) -> list[CaseResult]:
    """Run every case; the results in the order of ``cases``.

    ``workers``: the number of spawned worker processes of this machine (1: this process), or a
    :class:`~soft_gripper_sdre.tools.judging.jobs.Runner` (a pool, or a Ray cluster). The model's
    file (``model_path``; None: the shipped one) goes with the cases, and each worker loads it once
    and builds a simulator and a law per case. The compiled kernels are loaded into numba's on-disk
    cache here first, so that the workers of this machine load them instead of each compiling them.
    ``progress``: a bar on stderr.

    Raises:
        ValueError: ``workers`` < 1, or a case names an unknown law, variation or trajectory.
        soft_gripper_sdre.tools.judging.jobs.JobsError: a Ray runner without ray or without its
            cluster.
    """
    runner = (workers if isinstance(workers, Runner)
              else Runner(workers) if isinstance(workers, int) else None)
    if runner is None:
        raise ValueError(f'workers must be an int >= 1 or a Runner, got {workers!r}')
    for case in cases:
        for value, known, what in ((case.law, known_laws(), 'law'),
                                   (case.variation, VARIATIONS, 'variation'),
                                   (case.trajectory, TRAJECTORIES, 'trajectory')):
            if value not in known:
                raise ValueError(f'unknown {what} {value!r}; known: {list(known)}')
    from soft_gripper_sdre.control.kernels import warm_up
    warm_up()
    return run_jobs(run_case_job, cases, FileBlob.read(model_path or DEFAULT_MODEL), runner,
                    desc='robustness', progress=progress)
