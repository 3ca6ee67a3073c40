"""One-chamber pneumatic bending fingers: a planar tip, one input, the chamber's pressure.

A soft pneumatic finger (an elastomer bellows or fibre-reinforced actuator) bends one way when
its chamber is pressurised and springs back when it is vented. It is modelled as the chain of
:mod:`soft_gripper_sdre.sim.plants.chain` (same frame: X down the hanging finger, Y toward the
palm; same gravity, springs, damping and Dahl friction, same energy and RK4 step) with

* one input u, the commanded chamber pressure [Pa] (gauge), clipped to [0, p_max]: a chamber
  can only push (``lower_limits`` = (0,), ``torque_limit`` = p_max);
* the transmission B ∈ R^{1×n} in N·m/Pa, all positive: the chamber bends every joint toward
  +Y (the chamber's cross-section times its lever arm about each joint's neutral axis);
* a first-order pressure lag, ȧ = (u − a) / τ_p, the delivered pressure a being a state (the
  valve and the tubing filling the chamber; ``input_lag`` τ_p of tens of milliseconds);
* spring return: the elastomer's stiffness k brings the vented finger back to its rest curl.

The finger is meant to be served at 100 Hz (the driver's ``rate``), as pneumatic grippers are.

=============  =============  ================  =====  =====  ===========  ==========
preset         rest tip [mm]  modes [Hz]        ζ₁     τ_p    p_max [kPa]  reach [mm]
=============  =============  ================  =====  =====  ===========  ==========
pneumatic1_a   (104.6, 7.8)   4.1, 22.4, 63.6   0.16   40 ms  60           24.1
pneumatic1_b   (104.7, 7.1)   3.4, 22.6, 67.3   0.12   60 ms  60           18.3
=============  =============  ================  =====  =====  ===========  ==========

(reach: how far the tip moves from rest at p_max, held, frictionless; the static gain at rest,
``FingerPlant.static_gain()``, (2, 1) in m/Pa, is 0.40 (a) and 0.30 (b) mm per kPa, toward +Y.)

* ``pneumatic1_a``: three segments of 45/35/25 mm and 10/7/5 g, a 5 g tip; elastomer springs of
  0.10/0.07/0.05 N·m/rad curling it slightly (0.05 rad per joint) at rest; the chamber gives
  0.24/0.19/0.15 mN·m per kPa; Dahl friction 0.3/0.2/0.1 mN·m (the skin's hysteresis) with a
  5 mrad presliding range; RK4 steps of 0.25 ms.
* ``pneumatic1_b``: the same segments with a 15 g tip (a pad), stiffer springs (×1.2) and a
  slower valve (60 ms).
"""
from __future__ import annotations

from soft_gripper_sdre.sim.plants.chain_params import FingerParams

#: the chamber's largest gauge pressure [Pa]
P_MAX = 60e3
#: the finger's segments [m] and masses [kg]: 105 mm, 22 g without the tip
_SEGMENTS = dict(lengths=(0.045, 0.035, 0.025), masses=(0.010, 0.007, 0.005))
#: the chamber's torque per pascal at each joint [N·m/Pa]
_CHAMBER = ((2.4e-7, 1.9e-7, 1.5e-7),)
#: Dahl friction [N·m] and bristle stiffness [N·m/rad] (5 mrad presliding range)
_FRICTION = dict(coulomb=(3e-4, 2e-4, 1e-4), presliding=(0.06, 0.04, 0.02), friction_speed=20.0)


def pneumatic1_a() -> FingerParams:
    """One chamber, 5 g tip, a 40 ms pressure lag (module doc)."""
    return FingerParams(
        'pneumatic1_a', **_SEGMENTS, tip_mass=0.005, rest_angles=(0.05, 0.05, 0.05),
        stiffness=(0.10, 0.07, 0.05), hardening=(0.0, 0.0, 0.0), damping=(1.5e-3, 1.0e-3, 0.6e-3),
        **_FRICTION, transmission=_CHAMBER, torque_limit=P_MAX, substep=2.5e-4,
        lower_limits=(0.0,), input_lag=0.04)


def pneumatic1_b() -> FingerParams:
    """One chamber, 15 g tip, stiffer, a 60 ms pressure lag (module doc)."""
    return FingerParams(
        'pneumatic1_b', **_SEGMENTS, tip_mass=0.015, rest_angles=(0.05, 0.05, 0.05),
        stiffness=(0.12, 0.084, 0.06), hardening=(0.0, 0.0, 0.0), damping=(1.8e-3, 1.2e-3, 0.7e-3),
        **_FRICTION, transmission=_CHAMBER, torque_limit=P_MAX, substep=2.5e-4,
        lower_limits=(0.0,), input_lag=0.06)


#: preset name → its parameters (a plant: ``sim.plants.chain.FingerPlant(PNEUMATIC[name]())``)
PNEUMATIC = {'pneumatic1_a': pneumatic1_a, 'pneumatic1_b': pneumatic1_b}
