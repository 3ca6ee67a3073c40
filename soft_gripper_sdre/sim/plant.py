"""Departures of the simulated plant from the nominal finger, for robustness studies.

The learned model is trained on the nominal finger of :mod:`soft_gripper_sdre.sim.finger`. A
:class:`PlantVariation` in :attr:`SimConfig.plant <soft_gripper_sdre.sim.hand.SimConfig>` builds
the simulator on a plant the model has not seen, by scaling the finger's physical numbers when the
world is built:

* ``stiffness_scale`` multiplies every joint spring (both axes): τ_j = u − s·k_j q_j;
* ``friction_scale`` multiplies the force limit of the velocity-0 motors that act as the joints'
  Coulomb-like friction;
* ``tip_mass_scale`` multiplies the tip link's mass and its inertia (a denser tip of the same
  shape, so its centre of mass stays put);
* ``cube_mass_scale`` multiplies the cube's mass (hand scene).

Every scale is 1 by default, and a scale of 1 leaves the plant's arithmetic bit-identical (x·1.0 is
x in IEEE arithmetic). The sensor's departures (noise, delay) are not the plant's: the noise is
:attr:`SimConfig.noise_std`, the delay a FIFO in the closed loop
(:func:`soft_gripper_sdre.analysis.closed_loop.run_closed_loop`'s ``sensor_delay``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
import math

#: the largest accepted scale: beyond it the physics step (0.5 ms) is no longer known to be stable
MAX_SCALE = 10.0


@dataclass(frozen=True)
class PlantVariation:
    """Scales applied to the nominal finger's physical numbers when the simulator builds its world.

    Attributes:
        stiffness_scale: factor on every joint spring stiffness.
        friction_scale: factor on every joint's friction torque (0 = frictionless joints).
        tip_mass_scale: factor on the tip link's mass and inertia.
        cube_mass_scale: factor on the cube's mass (hand scene with the cube).
    """

    stiffness_scale: float = 1.0
    friction_scale: float = 1.0
    tip_mass_scale: float = 1.0
    cube_mass_scale: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            smallest = 0.0 if f.name == 'friction_scale' else 1e-3
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and smallest <= value <= MAX_SCALE):
                raise ValueError(f'{f.name} must be a finite number in '
                                 f'[{smallest:g}, {MAX_SCALE:g}], got {value!r}')

    @property
    def is_nominal(self) -> bool:
        """True when every scale is 1 (the plant the model was trained on)."""
        return all(getattr(self, f.name) == 1.0 for f in fields(self))

    def describe(self) -> str:
        """The scales that differ from 1, e.g. ``'stiffness ×1.2'`` (``'nominal'`` if none)."""
        parts = [f'{f.name.removesuffix("_scale").replace("_", " ")} ×{getattr(self, f.name):g}'
                 for f in fields(self) if getattr(self, f.name) != 1.0]
        return ', '.join(parts) or 'nominal'
