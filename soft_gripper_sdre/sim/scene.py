"""The simulator's scenes as PyBullet bodies: one finger, or the hand of four with palm and cube.

:func:`build_scene` loads a scene of :data:`~soft_gripper_sdre.sim.finger.SCENES` into a PyBullet
client whose world is empty and sets the bodies' contact properties and the fingers' joint
friction (module :mod:`soft_gripper_sdre.sim.finger` holds the numbers). The simulator
(:class:`~soft_gripper_sdre.sim.hand.GripperSim`) sets the physics engine up before and steps the
bodies after. Everything here is in SoMo's scaled world (sim units).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.finger import (
    CUBE,
    FINGER_BASE_POSITIONS,
    FINGER_FRICTION,
    FINGER_RESTITUTION,
    FRICTION_TORQUE,
    N_JOINTS,
    PALM,
    finger_base_rpy,
    load_fingers,
    rpy_matrix,
)
from soft_gripper_sdre.sim.plant import PlantVariation


@dataclass(frozen=True)
class Scene:
    """The PyBullet bodies of a built scene and where each finger's base sits (sim units)."""

    fingers: list[int]              # one multibody per finger, in finger order
    base_pos: np.ndarray            # (n, 3) each finger's base position in the world
    base_rot: np.ndarray            # (n, 3, 3) each finger's base rotation, base → world
    palm: int | None                # the palm, fixed to the world ('hand' scene)
    cube: int | None                # the cube on the palm ('hand' scene with a cube)


def build_scene(client: int, scene: str, mount_roll_deg: float, with_cube: bool,
                plant: PlantVariation) -> Scene:
    """Load ``scene`` into ``client``: ``'finger'``, one finger at the origin rolled
    ``mount_roll_deg`` about its base's x axis; ``'hand'``, the four fingers of the hand layout,
    the palm and, ``with_cube``, the cube. ``plant`` scales the tip mass, the joint friction and
    the cube's mass (the joint springs act in the simulator's physics step)."""
    if scene == 'finger':
        rpys = [(math.radians(mount_roll_deg), 0.0, 0.0)]
        positions = [(0.0, 0.0, 0.0)]
    else:
        rpys = [finger_base_rpy(i) for i in range(4)]
        positions = list(FINGER_BASE_POSITIONS)
    # One multibody per finger: four 10-DoF chains solve far faster than one 40-DoF body
    # (the joint-friction motors are constraints whose cost grows with the body's DoF).
    fingers = load_fingers(client, [(pos, pb.getQuaternionFromEuler(rpy))
                                    for pos, rpy in zip(positions, rpys)],
                           tip_mass_scale=plant.tip_mass_scale)
    palm = _load_palm(client) if scene == 'hand' else None
    cube = (_load_cube(client, CUBE['mass'] * plant.cube_mass_scale)
            if scene == 'hand' and with_cube else None)
    _set_finger_contacts_and_friction(client, fingers, FRICTION_TORQUE * plant.friction_scale)
    return Scene(fingers, np.array(positions, dtype=float),
                 np.stack([rpy_matrix(rpy) for rpy in rpys]), palm, cube)


def _load_palm(client: int) -> int:
    shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=PALM['radius'],
                                    height=PALM['length'], physicsClientId=client)
    # the palm is fixed to the world (mass 0 = static); its nominal mass is irrelevant then
    palm = pb.createMultiBody(0.0, shape, -1, PALM['center'], physicsClientId=client)
    pb.changeDynamics(palm, -1, lateralFriction=PALM['friction'], physicsClientId=client)
    return palm


def _load_cube(client: int, mass: float) -> int:
    half = CUBE['size'] / 2
    shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[half] * 3, physicsClientId=client)
    visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[half] * 3,
                                  rgbaColor=[0, 0.8, 0, 1], physicsClientId=client)
    cube = pb.createMultiBody(mass, shape, visual, CUBE['center'], physicsClientId=client)
    pb.changeDynamics(cube, -1, lateralFriction=CUBE['friction'], physicsClientId=client)
    return cube


def _set_finger_contacts_and_friction(client: int, fingers: list[int],
                                      friction_torque: float) -> None:
    """Every finger link's contact friction and restitution, and each joint's friction: a
    velocity-0 motor whose force limit is ``friction_torque``, active under torque control too."""
    joints = list(range(N_JOINTS))
    zeros, friction = [0.0] * N_JOINTS, [friction_torque] * N_JOINTS
    for body in fingers:
        for link in range(-1, N_JOINTS):
            pb.changeDynamics(body, link, lateralFriction=FINGER_FRICTION,
                              restitution=FINGER_RESTITUTION, physicsClientId=client)
        pb.setJointMotorControlArray(body, joints, pb.VELOCITY_CONTROL, targetVelocities=zeros,
                                     forces=friction, physicsClientId=client)
