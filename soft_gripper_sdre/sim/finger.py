"""The soft finger in plain PyBullet: its numbers, its URDF, the hand layout (no ROS).

The finger is SoMo's in-hand-manipulation finger: ten rigid segments on revolute joints with
alternating axes (even joints bend about the link x axis, "ax0", the grasp axis; odd joints about
the link y axis, "ax1", the side axis), a linear spring on every joint and a velocity motor with
target 0 whose force limit acts as Coulomb-like joint friction. Every joint of an axis receives
the full actuator torque of that axis:

    τ_j = u[axis(j)] − k_axis(j) · q_j,        B = [[1,0],[0,1],[1,0],…] ∈ R^{10×2}.

Inside this module everything is in SoMo's scaled world (1 length unit = 0.05 m, torques ×400,
gravity 196.2 units/s²); the public API is SI (:mod:`soft_gripper_sdre.sim.units`): torques in
N·m in, tip positions in metres out, each in its finger's own base frame.
"""
from __future__ import annotations

import math
from pathlib import Path
import tempfile

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.units import LENGTH_SCALE

SCENES = ('finger', 'hand')
N_JOINTS = 10
#: gravity in the scaled world [units/s²] (9.81 m/s² × 20)
GRAVITY = 9.81 * LENGTH_SCALE
WORLD_GRAVITY = (0.0, 0.0, -GRAVITY)
#: joint spring stiffness per axis [sim torque units / rad]
STIFFNESS = (87.4286, 414.857)
#: force limit of the velocity-0 motor that acts as joint friction [sim torque units]
FRICTION_TORQUE = 0.4
#: axis of each joint: 0 = ax0 (grasp, link x), 1 = ax1 (side, link y)
JOINT_AXIS = np.arange(N_JOINTS) % 2
#: B ∈ R^{10×2}: every joint of an axis receives the full actuator torque
B_MATRIX = np.stack([JOINT_AXIS == 0, JOINT_AXIS == 1], axis=1).astype(float)
JOINT_STIFFNESS = np.where(JOINT_AXIS == 0, STIFFNESS[0], STIFFNESS[1])
TIP_LINK = N_JOINTS - 1
#: the tip link's mass [kg] and principal moments of inertia [kg·unit²] (sim units)
TIP_MASS = 0.01794
TIP_INERTIA = 1.08359e-3
#: (axis, k) of every joint as Python numbers, for the per-substep spring torques in plain floats
JOINT_SPRINGS = tuple(zip(JOINT_AXIS.tolist(), JOINT_STIFFNESS.tolist()))

#: hand layout (sim units): finger base positions, yaw per finger, roll of every finger
FINGER_BASE_POSITIONS = ((0.0, -0.7, 0.0), (0.7, 0.0, 0.0), (0.0, 0.7, 0.0), (-0.7, 0.0, 0.0))
FINGER_YAW_DEG = (0.0, 90.0, 180.0, 270.0)
FINGER_ROLL_DEG = 15.0
PALM = dict(radius=0.4, length=1.0, mass=1.5, center=(0.0, 0.0, 1.25), friction=0.15)
CUBE = dict(size=1.0, mass=0.01, center=(0.0, 0.0, 2.25), friction=1.2)
FINGER_FRICTION = 3.0
FINGER_RESTITUTION = 0.7


# ----------------------------------------------------------------------------------------------
# URDF generation
# ----------------------------------------------------------------------------------------------

def _inertial(mass: float, com: tuple, diag: tuple) -> str:
    return (f'<inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>'
            f'<mass value="{mass}"/>'
            f'<inertia ixx="{diag[0]}" ixy="0" ixz="0" iyy="{diag[1]}" iyz="0" izz="{diag[2]}"/>'
            f'</inertial>')


def _box(size: tuple, xyz: tuple) -> str:
    return (f'<collision><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
            f'<geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></collision>'
            f'<visual><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
            f'<geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></visual>')


def _finger_links(prefix: str = '', tip_mass_scale: float = 1.0) -> list[str]:
    """URDF elements of one finger: its base link (the root) and the 10-joint chain, the tip's
    mass and inertia multiplied by ``tip_mass_scale``."""
    out = [f'<link name="{prefix}base">{_inertial(0.6, (0, 0, 0.1), (0.0225, 0.0225, 0.041))}'
           f'{_box((0.64, 0.64, 0.20), (0, 0, 0.10))}</link>']
    for j in range(N_JOINTS):
        if j == TIP_LINK:
            inertial = _inertial(TIP_MASS * tip_mass_scale, (0, 0, 0.083612),
                                 (TIP_INERTIA * tip_mass_scale,) * 3)
        elif JOINT_AXIS[j] == 0:
            inertial = _inertial(0.00294294, (0, -0.00012, 0.0002),
                                 (8.2616e-5, 1.06513e-4, 8.2616e-5))
        else:
            inertial = _inertial(0.00294294, (0, 0, 0.0002), (6.3664e-5, 8.7560e-5, 8.2616e-5))
        height = 0.10 if j in (0, TIP_LINK) else 0.20
        # ax0 link frames sit 0.12 off the finger's centre line in y; the segments stay centred
        y_centre = -0.12 if JOINT_AXIS[j] == 0 else 0.0
        geometry = _box((0.46, 0.34, height), (0, y_centre, height / 2))
        if j == TIP_LINK:
            geometry += ('<collision><origin xyz="0 0.1 0.2" rpy="0 0 0"/>'
                         '<geometry><sphere radius="0.3"/></geometry></collision>')
        out.append(f'<link name="{prefix}link{j}">{inertial}{geometry}</link>')
        if j == 0:
            xyz = (0, 0.12, 0.30)
        elif JOINT_AXIS[j] == 1:
            xyz = (0, -0.12, 0.20)
        else:
            xyz = (0, 0.12, 0.20)
        axis = '1 0 0' if JOINT_AXIS[j] == 0 else '0 1 0'
        parent_link = f'{prefix}base' if j == 0 else f'{prefix}link{j - 1}'
        out.append(f'<joint name="{prefix}joint{j}" type="revolute"><parent link="{parent_link}"/>'
                   f'<child link="{prefix}link{j}"/>'
                   f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
                   f'<axis xyz="{axis}"/><limit lower="-3.141592" upper="3.141592" effort="1000" '
                   f'velocity="1000"/></joint>')
    return out


def finger_urdf(tip_mass_scale: float = 1.0) -> str:
    """URDF of one finger whose root is its base link (mounted by the base pose at load time);
    ``tip_mass_scale`` multiplies the tip link's mass and inertia (1: the nominal finger)."""
    return '<?xml version="1.0"?>\n<robot name="ihm_finger">\n' + '\n'.join(
        _finger_links(tip_mass_scale=tip_mass_scale)) + '\n</robot>\n'


def load_fingers(client: int, poses: list[tuple[tuple, tuple]],
                 tip_mass_scale: float = 1.0) -> list[int]:
    """Load one finger (:func:`finger_urdf`, fixed base, inertia from the file) per base pose.

    Args:
        client: PyBullet physics client id.
        poses: (position, quaternion [x, y, z, w]) of each finger's base, sim units.
        tip_mass_scale: factor on the tip link's mass and inertia (1: the nominal finger).

    Returns:
        The body id of each finger. PyBullet parses URDF from files only; the file is written to a
        temporary directory that is gone when this returns (the bodies do not need it).
    """
    with tempfile.TemporaryDirectory(prefix='sgs_urdf_') as d:
        path = Path(d) / 'finger.urdf'
        path.write_text(finger_urdf(tip_mass_scale))
        return [pb.loadURDF(str(path), pos, orn, useFixedBase=True,
                            flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
                for pos, orn in poses]


def finger_base_rpy(i: int) -> tuple[float, float, float]:
    """Roll-pitch-yaw of hand finger i's base: roll 15° about its x axis, then yaw.

    The roll is positive, so each finger leans away from the palm centre (a negative roll would
    put the fingertips inside the cube); +Y still points at the centre, so a negative u_ax0
    closes a finger toward the cube.
    """
    return (math.radians(FINGER_ROLL_DEG), 0.0, math.radians(FINGER_YAW_DEG[i]))


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """Rotation matrix of URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return np.array(pb.getMatrixFromQuaternion(pb.getQuaternionFromEuler(rpy))).reshape(3, 3)


class DirectClient:
    """A PyBullet DIRECT client that this object owns (``_client``): :meth:`close`, or leaving a
    ``with`` block, disconnects it."""

    def __init__(self) -> None:
        self._client = pb.connect(pb.DIRECT)

    def close(self) -> None:
        if self._client is not None and pb.isConnected(physicsClientId=self._client):
            pb.disconnect(physicsClientId=self._client)
        self._client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; close() is the API
        try:
            if getattr(self, '_client', None) is not None:
                self.close()
        except Exception:  # noqa: BLE001 — interpreter shutdown
            pass
