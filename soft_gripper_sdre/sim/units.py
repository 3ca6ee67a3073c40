"""SoMo's scaled world and SI.

SoMo simulates at world scale 20: one simulator length unit is 0.05 m. Lengths, velocities,
accelerations and gravity scale by 1/20 to SI; torques and stiffnesses (N·m, N·m/rad) by 1/400
(force × length, with mass unscaled); masses and time are unchanged. Only :mod:`sim` works in
simulator units; every other module and every interface speaks SI.
"""
from __future__ import annotations

#: simulator length units per metre (1 unit = 0.05 m)
LENGTH_SCALE = 20.0
#: simulator torque units per N·m
TORQUE_SCALE = LENGTH_SCALE**2


def torque_to_si(value):
    """Simulator torque units → N·m."""
    return value / TORQUE_SCALE
