"""What a foreign finger is: :class:`FingerParams`, and the presets two grippers are made of.

The parameters are the terms of the model in :mod:`soft_gripper_sdre.sim.plants.chain` (frame,
dynamics, Dahl friction, RK4 step); :class:`FingerParams` checks them, down to whether ``substep``
is fine enough for the friction's bristles.

**The presets** (:data:`PLANTS`; :data:`PAIRS` names a gripper's two fingers). Measured on
:class:`~.chain.FingerPlant`: the rest tip (x, y); the natural frequencies
and modal damping ratios of the frictionless finger linearised at rest (``modes``); the static tip
displacement per mN·m on each input, frictionless (``static_gain``), the direction of each input's
tip motion (from +X toward +Y) and the angle between the two
(:func:`~soft_gripper_sdre.sim.plants.chain.input_angle`):

=============  =============  ================  =====  ============  ==========  =====
preset         rest tip [mm]  modes [Hz]        ζ₁     mm per mN·m   directions  angle
=============  =============  ================  =====  ============  ==========  =====
tendon3_index  (78.3, 44.2)   5.4, 21.4, 71.2   0.15   1.49, 1.34    125°, 138°  12.7°
tendon3_thumb  (81.3, 39.1)   5.1, 22.0, 82.8   0.14   0.89, 0.83    122°, 135°  13.5°
stiff2_a       (71.6, 38.5)   28.1, 124.5       0.073  0.015, 0.014  121°, 133°  11.9°
stiff2_b       (71.7, 38.4)   20.0, 100.2       0.055  0.013, 0.012  121°, 133°  11.9°
=============  =============  ================  =====  ============  ==========  =====

* ``tendon3_*``: three links of 45/30/20 mm and 12/7/4 g (uniform), a fingertip of 4 g (index)
  or 12 g (thumb); linear springs of 0.12/0.08/0.05 N·m/rad (index) or 0.20/0.13/0.08 (thumb)
  curling the finger at rest; two flexor tendons over all three joints, one pulling mostly on
  the proximal joint, the other mostly on the distal ones; Dahl friction of 0.5/0.35/0.2 mN·m
  (a tendon in its sheath) with a 5 mrad presliding range. Torque limit 20 mN·m (the index's tip
  then moves ~25 mm); RK4 steps of 0.25 ms. Soft and slow, unlike the SoMo finger's 10 joints,
  ~110 mm and 3.1/8.9 Hz with one input per bending axis.
* ``stiff2_*``: two links of 50/35 mm and 30/18 g, a 10 g (a) or 40 g (b) tip; springs of
  6.0/3.5 (a) or 7.0/4.0 N·m/rad (b) with a hardening k₃ = 60 k (+60 % stiffness at 0.1 rad);
  a coupled 2 × 2 transmission (1.0/0.2 and 0.3/1.0); lightly damped; Dahl friction 3/2 mN·m
  with a 2 mrad presliding range. Torque limit 0.25 N·m (tip ~4 mm); RK4 steps of 0.2 ms.
* ``flexor2_*``: the ``tendon3_*`` fingers (the same rest tips and modes) driven by two tendons
  that only pull, 0 to 4 N: a flexor on the palm side (moment arms 8/3/1.5 mm) and an extensor on
  the back (2.5/4.5/7 mm). Their tip directions at rest lie 167° apart (index: 7.4 mm per N at
  125°, 6.7 mm per N at 318°).

Friction above ``friction_speed`` v_s (20 rad/s tendon, 10 rad/s stiff) grows like F_c|q̇|/v_s:
v(q̇) = v_s tanh(|q̇|/v_s) bounds the bristles' relaxation rate σv/F_c, which keeps RK4 stable
(checked against ``substep``) at the speeds a torque-limited bang-bang input reaches.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
from typing import Callable

from soft_gripper_sdre.sim.shape import MAX_INPUTS, FingerShape, InputBounds

GRAVITY = 9.81


@dataclass(frozen=True)
class FingerParams:
    """A planar serial-link finger; per-joint tuples have one entry per joint (SI units).

    The m inputs (1 to 4, the rows of ``transmission``) are in the actuator's unit: torques
    [N·m] for a tendon motor, pressures [Pa] for a chamber (B then in N·m/Pa). Input k is
    clipped to [``lower_limits[k]``, ``torque_limit``], or to ±``torque_limit`` without
    ``lower_limits``. With ``input_lag`` > 0 the delivered input follows the commanded one
    through a first-order lag of that time constant (a chamber's pressure, a motor's current).
    """

    name: str
    lengths: tuple[float, ...]           # m
    masses: tuple[float, ...]            # kg, uniform links
    tip_mass: float                      # kg, a point mass at the tip
    rest_angles: tuple[float, ...]       # rad, the springs' rest angles q_r
    stiffness: tuple[float, ...]         # N·m/rad, k
    hardening: tuple[float, ...]         # N·m/rad³, k₃
    damping: tuple[float, ...]           # N·m·s/rad, c
    coulomb: tuple[float, ...]           # N·m, F_c (0 = no friction at that joint)
    presliding: tuple[float, ...]        # N·m/rad, σ, the Dahl bristle stiffness
    friction_speed: float                # rad/s, v_s: friction turns viscous above it
    transmission: tuple[tuple[float, ...], ...]   # B, m × n: joint torque per unit input
    torque_limit: float                  # input unit (N·m, Pa), each input's upper bound
    substep: float                       # s, the RK4 step
    gravity: float = GRAVITY             # m/s², along +X
    lower_limits: tuple[float, ...] | None = None   # per input; None: −torque_limit
    input_lag: float = 0.0               # s, first-order lag of the delivered input (0: none)

    def __post_init__(self) -> None:
        n = len(self.lengths)
        per_joint = ('masses', 'rest_angles', 'stiffness', 'hardening', 'damping', 'coulomb',
                     'presliding')
        for name in per_joint:
            if len(getattr(self, name)) != n:
                raise ValueError(f'{self.name}: {name} has {len(getattr(self, name))} entries, '
                                 f'expected one per joint ({n})')
        m = len(self.transmission)
        if not 1 <= m <= MAX_INPUTS or any(len(row) != n for row in self.transmission):
            raise ValueError(f'{self.name}: transmission must be m × {n} with m = 1 to '
                             f'{MAX_INPUTS} inputs')
        if self.lower_limits is not None and (
                len(self.lower_limits) != m
                or not all(math.isfinite(v) and v < self.torque_limit for v in self.lower_limits)):
            raise ValueError(f'{self.name}: lower_limits must hold one finite bound per input '
                             f'({m}), each below torque_limit')
        if not (math.isfinite(self.input_lag) and self.input_lag >= 0):
            raise ValueError(f'{self.name}: input_lag must be finite and >= 0 s')
        if 0 < self.input_lag < 4 * self.substep:
            raise ValueError(f'{self.name}: input_lag {self.input_lag} s is too short for RK4 '
                             f'steps of {self.substep} s (keep it >= 4 substeps)')
        if min(self.lengths) <= 0 or min(self.masses) <= 0 or self.tip_mass < 0:
            raise ValueError(f'{self.name}: lengths and masses must be positive')
        if min(self.stiffness) <= 0 or min(self.damping) < 0 or min(self.hardening) < 0:
            raise ValueError(f'{self.name}: stiffness must be positive, damping and hardening >= 0')
        if any(f < 0 or s < 0 or (f > 0) != (s > 0) for f, s in zip(self.coulomb, self.presliding)):
            raise ValueError(f'{self.name}: coulomb and presliding must both be positive '
                             '(friction) or both zero (none) at each joint')
        if self.torque_limit <= 0 or self.substep <= 0 or self.friction_speed <= 0:
            raise ValueError(f'{self.name}: torque_limit, substep and friction_speed must be '
                             'positive')
        rate = self.friction_speed * max(s / f if f else 0.0
                                         for s, f in zip(self.presliding, self.coulomb))
        if rate * self.substep > 1.5:
            raise ValueError(f'{self.name}: the bristles relax at up to {rate:.0f}/s, too fast '
                             f'for RK4 steps of {self.substep} s (keep the product <= 1.5)')

    @property
    def n(self) -> int:
        return len(self.lengths)

    @property
    def m(self) -> int:
        """The number of inputs (rows of the transmission)."""
        return len(self.transmission)

    @property
    def shape(self) -> FingerShape:
        """A planar tip (d = 2) and m inputs."""
        return FingerShape(2, self.m)

    @property
    def bounds(self) -> InputBounds:
        """Each input's interval: [lower_limits, torque_limit], or ±torque_limit."""
        if self.lower_limits is None:
            return InputBounds.symmetric(self.torque_limit, self.m)
        return InputBounds(self.lower_limits, (self.torque_limit,) * self.m)


# -- the presets -----------------------------------------------------------------------------

#: the tendon finger's links [m] and masses [kg]: ~95 mm, 23 g without the tip
_TENDON_LINKS = dict(lengths=(0.045, 0.030, 0.020), masses=(0.012, 0.007, 0.004))
#: the stiff finger's links [m] and masses [kg]: 85 mm, 48 g without the tip
_STIFF_LINKS = dict(lengths=(0.050, 0.035), masses=(0.030, 0.018))


def tendon3_index() -> FingerParams:
    """Three-link tendon finger, soft and light (4 g tip): a flexor tendon that pulls mostly on
    the proximal joint (moment arms 1.6/0.6/0.3 of the pulley radius) and one that pulls mostly
    on the distal joints (0.5/0.9/1.4); Dahl friction 0.5/0.35/0.2 mN·m."""
    return FingerParams(
        'tendon3_index', **_TENDON_LINKS, tip_mass=0.004, rest_angles=(0.25, 0.45, 0.45),
        stiffness=(0.12, 0.08, 0.05), hardening=(0.0, 0.0, 0.0), damping=(1.2e-3, 0.8e-3, 0.4e-3),
        coulomb=(5e-4, 3.5e-4, 2e-4), presliding=(0.1, 0.07, 0.04), friction_speed=20.0,
        transmission=((1.6, 0.6, 0.3), (0.5, 0.9, 1.4)), torque_limit=0.02, substep=2.5e-4)


def tendon3_thumb() -> FingerParams:
    """The index's links with a 12 g tip, stiffer springs (×1.6–1.7), another rest curl and
    tendon routing (1.5/0.7/0.3 and 0.4/1.0/1.5)."""
    return FingerParams(
        'tendon3_thumb', **_TENDON_LINKS, tip_mass=0.012, rest_angles=(0.2, 0.4, 0.5),
        stiffness=(0.20, 0.13, 0.08), hardening=(0.0, 0.0, 0.0), damping=(2e-3, 1.3e-3, 0.7e-3),
        coulomb=(5e-4, 3.5e-4, 2e-4), presliding=(0.1, 0.07, 0.04), friction_speed=20.0,
        transmission=((1.5, 0.7, 0.3), (0.4, 1.0, 1.5)), torque_limit=0.02, substep=2.5e-4)


def stiff2_a() -> FingerParams:
    """Two-link stiff finger (10 g tip), hardening springs k₃ = 60 k, a coupled 2 × 2
    transmission (1.0/0.2 and 0.3/1.0), lightly damped; Dahl friction 3/2 mN·m."""
    return FingerParams(
        'stiff2_a', **_STIFF_LINKS, tip_mass=0.010, rest_angles=(0.25, 0.6),
        stiffness=(6.0, 3.5), hardening=(360.0, 210.0), damping=(5e-3, 3e-3),
        coulomb=(3e-3, 2e-3), presliding=(1.5, 1.0), friction_speed=10.0,
        transmission=((1.0, 0.2), (0.3, 1.0)), torque_limit=0.25, substep=2e-4)


def stiff2_b() -> FingerParams:
    """The stiff finger with a 40 g tip (a heavier fingertip or a tool) and stiffer joints."""
    return FingerParams(
        'stiff2_b', **_STIFF_LINKS, tip_mass=0.040, rest_angles=(0.25, 0.6),
        stiffness=(7.0, 4.0), hardening=(420.0, 240.0), damping=(6e-3, 4e-3),
        coulomb=(3e-3, 2e-3), presliding=(1.5, 1.0), friction_speed=10.0,
        transmission=((1.0, 0.2), (0.3, 1.0)), torque_limit=0.25, substep=2e-4)


#: the flexor's and the extensor's moment arms [m] about the three joints: pulleys of 5 mm
#: radius, the flexor on the palm side mostly about the proximal joint, the extensor on the back
#: mostly about the distal ones
_FLEXOR_EXTENSOR = ((0.008, 0.003, 0.0015), (-0.0025, -0.0045, -0.007))
#: a tendon's largest tension [N]
TENDON_MAX = 4.0


def _flexor_extensor(finger: FingerParams, name: str) -> FingerParams:
    """``finger``'s links, springs and friction driven by the flexor and the extensor, each
    pulling 0 to :data:`TENDON_MAX`."""
    return dataclasses.replace(finger, name=name, transmission=_FLEXOR_EXTENSOR,
                               torque_limit=TENDON_MAX, lower_limits=(0.0, 0.0))


def flexor2_index() -> FingerParams:
    """The tendon index's links, springs and friction, driven by two antagonistic tendons that
    only pull (0 to 4 N each): a flexor toward the palm (+Y) and an extensor away from it."""
    return _flexor_extensor(tendon3_index(), 'flexor2_index')


def flexor2_thumb() -> FingerParams:
    """The tendon thumb's links, springs and friction, with the index's two tendons."""
    return _flexor_extensor(tendon3_thumb(), 'flexor2_thumb')


#: preset name → its parameters (a plant: ``sim.plants.chain.FingerPlant(PLANTS[name]())``)
PLANTS: dict[str, Callable[[], FingerParams]] = {
    'tendon3_index': tendon3_index, 'tendon3_thumb': tendon3_thumb,
    'stiff2_a': stiff2_a, 'stiff2_b': stiff2_b,
    'flexor2_index': flexor2_index, 'flexor2_thumb': flexor2_thumb,
}
#: gripper kind → the presets of its two fingers (the fingers: ``chain.plant_pair(kind)``)
PAIRS = {'tendon3': ('tendon3_index', 'tendon3_thumb'), 'stiff2': ('stiff2_a', 'stiff2_b'),
         'flexor2': ('flexor2_index', 'flexor2_thumb')}
