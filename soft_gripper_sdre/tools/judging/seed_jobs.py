"""One model of the seed sweep (:mod:`~soft_gripper_sdre.tools.judging.seeds`) as one job: train it
on its seed and draw of the data, or take the shipped one, and score its accuracy and tracking.

A job is self-contained (the labelled data and the settings travel in its
:class:`SweepContext`), so it gives the same numbers in this process, on a worker or as a Ray task
(:func:`~soft_gripper_sdre.tools.judging.jobs.run_jobs`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
import tempfile
import time

#: the shipped model's row
SHIPPED = 'shipped'


@dataclass(frozen=True)
class ModelJob:
    """Train seed ``seed`` on draw ``draw`` of the data and score it; ``seed`` None scores the
    shipped model."""

    seed: int | None
    draw: int = 0

    @property
    def name(self) -> str:
        if self.seed is None:
            return SHIPPED
        return f'seed{self.seed}' + (f'_draw{self.draw}' if self.draw else '')


@dataclass(frozen=True)
class SweepContext:
    """What every job shares: the labelled data, the training settings, the jitter, the tracking
    runs."""

    data: object                   # tools.learning.train.LabelledData
    settings: object               # learning.train_settings.TrainSettings
    jitter: float
    laws: tuple[str, ...]
    trajectories: tuple[str, ...]
    duration: float | None


@dataclass
class ModelOutcome:
    """One model: its checkpoint (None for the shipped one), its training metrics, the sha256 of its
    weights, and its tracking runs (``evaluation_runs.RunSummary`` as dicts)."""

    name: str
    seed: int | None
    draw: int
    checkpoint: bytes | None
    metrics: dict
    weights_sha256: str
    tracking: list[dict]
    job_seconds: float


def tracking_runs(model, laws, trajectories, duration) -> list[dict]:
    """Every law on every trajectory, in-process, as ``make evaluate`` runs them (RunSummary
    dicts)."""
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.tools.judging.evaluation_runs import run_law
    weights = Weights(**DEFAULT_WEIGHTS)
    out = []
    for trajectory in trajectories:
        for law in laws:
            summary, _ = run_law(law, trajectory, model, weights, duration=duration)
            out.append(asdict(summary))
    return out


def run_model_job(context: SweepContext, job: ModelJob) -> ModelOutcome:
    """Train and score one model (a job of
    :func:`~soft_gripper_sdre.tools.judging.jobs.run_jobs`)."""
    from soft_gripper_sdre.analysis.training_run import fit
    from soft_gripper_sdre.learning.model import (
        DEFAULT_MODEL,
        SDCModel,
        set_torch_threads,
        weights_sha256,
    )
    set_torch_threads(1)
    start = time.perf_counter()
    if job.seed is None:
        model = SDCModel()
        tracking = tracking_runs(model, context.laws, context.trajectories, context.duration)
        return ModelOutcome(job.name, None, 0, None, dict(model.metrics),
                            weights_sha256(DEFAULT_MODEL), tracking, time.perf_counter() - start)
    settings = replace(context.settings, seed=job.seed)
    jitter = context.jitter if job.draw else 0.0
    with tempfile.TemporaryDirectory(prefix='sgs-seeds-') as tmp:
        path, metrics, _, _ = fit(context.data, settings, Path(tmp) / 'model.pt', jitter, job.draw)
        model = SDCModel(path)
        tracking = tracking_runs(model, context.laws, context.trajectories, context.duration)
        return ModelOutcome(job.name, job.seed, job.draw, path.read_bytes(), metrics,
                            weights_sha256(path), tracking, time.perf_counter() - start)
