"""Every foreign gripper by name: the planar two-input fingers (``tendon3``, ``stiff2``:
:mod:`~.chain_params`), the one-chamber pneumatic fingers (``pneumatic1``:
:mod:`soft_gripper_sdre.sim.plants.pneumatic`) and the three-tendon continuum segments with a
3-D tip (``trunk3``: :mod:`soft_gripper_sdre.sim.plants.trunk`); two fingers per gripper.

Each gripper knows its finger's shape (:class:`~soft_gripper_sdre.sim.shape.FingerShape`) and
its inputs' bounds (:class:`~soft_gripper_sdre.sim.shape.InputBounds`, the tighter of its two
fingers'), and the rate a driver serves it at.

=============  ======  ==========================  =====================  ==========
gripper        (d, m)  input, bounds               fingers                rate [Hz]
=============  ======  ==========================  =====================  ==========
tendon3        (2, 2)  torques, ±0.02 N·m          index, thumb           200
stiff2         (2, 2)  torques, ±0.25 N·m          a, b                   500
pneumatic1     (2, 1)  pressure, 0 to 60 kPa       a, b                   100
trunk3         (3, 3)  tensions, 0 to 4 N          a, b                   250
=============  ======  ==========================  =====================  ==========
"""
from __future__ import annotations

from typing import Callable, Union

import numpy as np

from soft_gripper_sdre.sim.plants.chain import FingerPlant
from soft_gripper_sdre.sim.plants.chain_params import PAIRS, PLANTS, FingerParams
from soft_gripper_sdre.sim.plants.pneumatic import PNEUMATIC
from soft_gripper_sdre.sim.plants.trunk import TRUNKS, TrunkParams, TrunkPlant
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

Plant = Union[FingerPlant, TrunkPlant]

#: finger preset name → its parameters
PRESETS: dict[str, Callable[[], Union[FingerParams, TrunkParams]]] = {
    **PLANTS, **PNEUMATIC, **TRUNKS}
#: gripper kind → the presets of its two fingers
GRIPPERS: dict[str, tuple[str, str]] = {
    **PAIRS, 'pneumatic1': ('pneumatic1_a', 'pneumatic1_b'), 'trunk3': ('trunk3_a', 'trunk3_b')}
#: gripper kind → the rate [Hz] a driver serves it at
RATES = {'tendon3': 200.0, 'stiff2': 500.0, 'pneumatic1': 100.0, 'trunk3': 250.0,
         'flexor2': 200.0}


def _kind(kind: str) -> tuple[str, str]:
    if kind not in GRIPPERS:
        raise ValueError(f'unknown plant kind {kind!r}: expected one of {", ".join(GRIPPERS)}')
    return GRIPPERS[kind]


def make_plant(name: str) -> Plant:
    """The finger preset ``name`` at rest.

    Raises:
        ValueError: an unknown preset.
    """
    if name not in PRESETS:
        raise ValueError(f'unknown finger preset {name!r}: expected one of {", ".join(PRESETS)}')
    params = PRESETS[name]()
    return TrunkPlant(params) if isinstance(params, TrunkParams) else FingerPlant(params)


def plant_pair(kind: str) -> tuple[Plant, Plant]:
    """The two fingers of the gripper ``kind``, at rest.

    Raises:
        ValueError: an unknown kind.
    """
    return tuple(make_plant(name) for name in _kind(kind))


def gripper_shape(kind: str) -> FingerShape:
    """The shape of the gripper's fingers (both have the same)."""
    return PRESETS[_kind(kind)[0]]().shape


def gripper_bounds(kind: str) -> InputBounds:
    """The bounds every finger of the gripper accepts: per input the tighter of the two."""
    a, b = (PRESETS[name]().bounds for name in _kind(kind))
    return InputBounds(np.maximum(a.lower, b.lower), np.minimum(a.upper, b.upper))
