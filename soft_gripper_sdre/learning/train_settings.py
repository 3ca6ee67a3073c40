"""Training's settings: :class:`TrainSettings`, checked when made, and the named presets the
tools offer (:data:`PRESETS`). What the two stages and the penalties do with them:
:mod:`soft_gripper_sdre.learning.training`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_gripper_sdre.learning.model import HIDDEN


@dataclass(frozen=True)
class TrainSettings:
    """A training preset. ``paper``: Adam 1e-5, 70 epochs, unscaled, as published.

    ``patience``: stop after this many epochs without a new best validation loss; None runs the
    whole budget. The default preset runs it: its cosine schedule anneals the learning rate to zero
    over the budget, while a stop decided by the noisy mid-schedule validation curve can fall
    tens of epochs earlier or later when the data change at rounding level, and so give another
    model. Either way the weights of the best validation epoch are kept.
    """

    preset: str = 'default'
    epochs: int = 300
    lr: float = 1e-3
    batch_size: int = 256
    cosine: bool = True
    scale: bool = True
    weight_decay: float = 0.0
    patience: int | None = None
    seed: int = 0
    hidden: int = HIDDEN
    #: controllability-aware learning (docs/results.md "Beyond the paper"): weight of the penalty
    #: mean(relu(σ_floor − σ_min(G2(x)))²) on G2's smallest singular value at states drawn uniformly
    #: from a box of ±sv_box (scaled units: data standard deviations) each batch; 0 = off
    sv_penalty: float = 0.0
    sv_floor: float = 0.3
    sv_box: float = 3.0
    #: simulation-error stage (:mod:`~soft_gripper_sdre.learning.training`): epochs (0 = off),
    #: window length [s], learning rate, and how many windows cover each sample (their starts
    #: are H / overlap samples apart, so the cost per epoch does not grow with the rate)
    rollout_epochs: int = 0
    rollout_seconds: float = 0.1
    rollout_lr: float = 3e-4
    rollout_overlap: int = 5
    #: the epochs are scored by free runs of this length [s] on the validation records, as long
    #: as the verdict's (analysis/model_fitness.py): 0.1 s runs of a slow signal cannot tell a
    #: quasi-static model from the finger
    rollout_val_seconds: float = 1.0
    #: with the simulation stage on, the label epochs are scored by those free runs at the first,
    #: every ``score_every``-th and the last epoch (an epoch not scored is not kept): the free runs
    #: step the networks sequentially and cost more than an epoch of labels
    score_every: int = 1
    #: windows per batch of the simulation stage (None: ``batch_size``)
    rollout_batch_size: int | None = None
    #: stable learned rest (:mod:`~soft_gripper_sdre.learning.training`): A(0)'s eigenvalues
    #: kept left of −rest_margin [1/s] (0 = off) by a penalty of this weight
    rest_margin: float = 0.0
    rest_weight: float = 10.0

    def __post_init__(self) -> None:
        if self.patience is not None and not (isinstance(self.patience, int)
                                              and self.patience >= 1):
            raise ValueError(f'patience must be an int >= 1 or None (run every epoch), '
                             f'got {self.patience!r}')
        if not (np.isfinite(self.sv_penalty) and self.sv_penalty >= 0.0):
            raise ValueError(f'sv_penalty must be finite and >= 0 (0 = off), '
                             f'got {self.sv_penalty!r}')
        for name in ('sv_floor', 'sv_box', 'rollout_seconds', 'rollout_lr', 'rest_weight',
                     'rollout_val_seconds'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v!r}')
        for name in ('rollout_epochs', 'rollout_overlap', 'score_every', 'batch_size',
                     'rollout_batch_size'):
            v = getattr(self, name)
            if name == 'rollout_batch_size' and v is None:
                continue
            low = 0 if name == 'rollout_epochs' else 1
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
                raise ValueError(f'{name} must be an int >= {low}'
                                 + (' or None' if name == 'rollout_batch_size' else '')
                                 + f', got {v!r}')
        if not (np.isfinite(self.rest_margin) and self.rest_margin >= 0.0):
            raise ValueError(f'rest_margin must be finite and >= 0 (0 = off), '
                             f'got {self.rest_margin!r}')


PRESETS = {
    'default': TrainSettings(),
    'paper': TrainSettings(preset='paper', epochs=70, lr=1e-5, batch_size=64, cosine=False,
                           scale=False),
    # a gripper of your own (docs/own_gripper.md): labels, then the simulation error, rest kept
    # stable; sized for a lab's iteration (docs/own_gripper.md, "What training costs"): 100 label
    # epochs in batches of 512, scored every fifth, then 30 simulation epochs over windows that
    # cover each sample once, 128 a batch
    'gripper': TrainSettings(preset='gripper', epochs=100, lr=1.5e-3, batch_size=512,
                             score_every=5, rollout_epochs=30, rollout_overlap=1,
                             rollout_batch_size=128, rest_margin=1.0),
}
