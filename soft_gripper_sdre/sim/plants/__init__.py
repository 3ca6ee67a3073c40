"""Plants nobody here wrote: the fingers the own-gripper recipe is tried on, in plain numpy and
floats (no PyBullet, no ROS), each behind :mod:`soft_gripper_sdre.nodes.plant_driver`.

* :mod:`~soft_gripper_sdre.sim.plants.chain`: planar serial-link fingers with joint springs,
  Dahl friction and tendon or motor actuation (``tendon3``, ``stiff2``; their presets in
  :mod:`~soft_gripper_sdre.sim.plants.chain_params`, their equations of motion and the RK4 step
  in :mod:`~soft_gripper_sdre.sim.plants.dynamics`);
* :mod:`~soft_gripper_sdre.sim.plants.pneumatic`: one-chamber pneumatic bending fingers (one
  input, pressure ≥ 0, a pressure lag; ``pneumatic1``);
* :mod:`~soft_gripper_sdre.sim.plants.trunk`: three-tendon constant-curvature segments with a
  3-D tip (``trunk3``);
* :mod:`~soft_gripper_sdre.sim.plants.presets`: every gripper by name, with its fingers' shape,
  input bounds and rate.
"""
