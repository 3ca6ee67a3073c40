"""Learned-model SDRE task-space tracking control of a soft gripper.

Core modules (no ROS imports): :mod:`units`, :mod:`sim`, :mod:`signals`, :mod:`kf`,
:mod:`derivatives`, :mod:`model` (the only torch user), :mod:`sdre`, :mod:`trajectory`,
:mod:`metrics`, :mod:`plots`. ROS glue lives in :mod:`soft_gripper_sdre.nodes`, command-line
tools in :mod:`soft_gripper_sdre.tools`.
"""
from importlib import metadata as _metadata

try:
    __version__ = _metadata.version('soft_gripper_sdre')
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = '0.0.0+unknown'

FINGER_NAMES = tuple(f'finger_{i}' for i in range(4))
