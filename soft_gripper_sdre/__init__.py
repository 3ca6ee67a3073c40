"""Learned-model SDRE task-space tracking control of a soft gripper.

Subpackages, bottom to top (each imports only from those below it):

* :mod:`~soft_gripper_sdre.sim` — the PyBullet finger and hand, excitation signals, units, and
  the simulated finger's exact dynamics (ground truth).
* :mod:`~soft_gripper_sdre.learning` — derivative labels, datasets, the SDC networks and their
  training; the only place torch is imported.
* :mod:`~soft_gripper_sdre.control` — Riccati solvers, the SDRE supervisor, the control laws, the
  Kalman filter, references and horizons.
* :mod:`~soft_gripper_sdre.analysis` — the in-process closed loop, metrics, bags, plots, the oracle
  laws and other ground-truth yardsticks.
* :mod:`~soft_gripper_sdre.nodes` (ROS glue only) and :mod:`~soft_gripper_sdre.tools` (command
  lines) on top.

Everything below ``nodes`` and ``tools`` is free of ROS imports.
"""
from importlib import metadata as _metadata

try:
    __version__ = _metadata.version('soft_gripper_sdre')
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = '0.0.0+unknown'

FINGER_NAMES = tuple(f'finger_{i}' for i in range(4))
