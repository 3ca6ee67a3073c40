"""Ground-truth task-space dynamics of one finger, from PyBullet's rigid-body model (no ROS).

The simulated finger is a 10-joint chain (:mod:`soft_gripper_sdre.sim.finger`). With the joint
equation M(q) q̈ + C(q, q̇) q̇ + g(q) = B u − K q (friction off) and the tip Jacobian J, the tip's
exact acceleration in its base frame is

    p̈ = J̇ q̇ + J M⁻¹ (B u − K q − C q̇ − g)  =  f(q, q̇) + G₂(q) u,     G₂ = J M⁻¹ B,

with the drift split into f_pos = J M⁻¹ (−K q − g) and f_vel = J̇ q̇ − J M⁻¹ C q̇. These depend on
the whole 20-dimensional joint state; the 4-state SDC model approximates them. Beside the exact
terms, :class:`TaskDynamics` carries their projection onto the chain's two static shapes
Φ = K⁻¹ B (``f_pos_r``, ``f_vel_r``, ``G2_r``): the part a 4-state model can hope to match, since
G₂ itself includes the chain's fast bending modes.

:class:`FingerDynamics` evaluates the terms in its own PyBullet DIRECT client (the simulator's
URDF, so one instance serves every hand finger, each in its own base frame). :func:`oracle_sdc`
turns them into one SDC pair A(x), G(x). The derivations are in docs/design/finger_dynamics.md.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.finger import (
    B_MATRIX,
    FINGER_ROLL_DEG,
    FRICTION_TORQUE,
    JOINT_STIFFNESS,
    N_JOINTS,
    TIP_LINK,
    WORLD_GRAVITY,
    DirectClient,
    load_fingers,
    rpy_matrix,
)
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE

#: step of the central difference J̇ q̇ ≈ (J(q + h q̇) − J(q − h q̇)) q̇ / 2h  [s]
_JDOT_STEP = 1e-6


@dataclass(frozen=True)
class TaskDynamics:
    """The exact task-space terms at one joint state (SI, the finger's base frame, X and Y)."""

    tip: np.ndarray        # (2,) tip position [m]
    tip_vel: np.ndarray    # (2,) tip velocity J q̇ [m/s]
    f_pos: np.ndarray      # (2,) J M⁻¹ (−K q − g) [m/s²]
    f_vel: np.ndarray      # (2,) J̇ q̇ − J M⁻¹ C q̇ [m/s²]
    G2: np.ndarray         # (2, 2) J M⁻¹ B [m/s² per N·m]
    S: np.ndarray          # (2, 2) static compliance J K⁻¹ B (spring stiffness only) [m per N·m]
    J: np.ndarray          # (2, 10) tip Jacobian [m/rad]
    # the same, Galerkin-projected onto the chain's static shapes Φ = K⁻¹ B, M_r = Φᵀ M Φ
    f_pos_r: np.ndarray    # (2,) S M_r⁻¹ Φᵀ (−K q − g) [m/s²]
    f_vel_r: np.ndarray    # (2,) J̇ q̇ − S M_r⁻¹ Φᵀ C q̇ [m/s²]
    G2_r: np.ndarray       # (2, 2) S M_r⁻¹ Φᵀ B [m/s² per N·m]

    def reduced(self) -> TaskDynamics:
        """The projected terms in the places of the exact ones (f_pos, f_vel, G2)."""
        return TaskDynamics(self.tip, self.tip_vel, self.f_pos_r, self.f_vel_r, self.G2_r, self.S,
                            self.J, self.f_pos_r, self.f_vel_r, self.G2_r)

    @property
    def f(self) -> np.ndarray:
        """(2,) drift f = f_pos + f_vel [m/s²]."""
        return self.f_pos + self.f_vel

    def accel(self, u: np.ndarray) -> np.ndarray:
        """(2,) tip acceleration p̈ = f + G₂ u for torques u (2,) [N·m]."""
        return self.f + self.G2 @ np.asarray(u, dtype=float)


class FingerDynamics(DirectClient):
    """The finger's rigid-body model in a private PyBullet client.

    Args:
        mount_roll_deg: roll of the finger's base (the hand's fingers and the training finger are
            rolled 15°; gravity in the base frame depends on it).
    """

    def __init__(self, mount_roll_deg: float = FINGER_ROLL_DEG) -> None:
        if not math.isfinite(mount_roll_deg):
            raise ValueError(f'mount_roll_deg must be finite, got {mount_roll_deg!r}')
        super().__init__()
        # The body is loaded upright with gravity turned into its base frame, g_b = Rᵀ (0, 0, −g):
        # PyBullet's calculateInverseDynamics ignores a fixed base's orientation and would apply
        # gravity as if the finger stood upright. Base frame = world frame here.
        rot = rpy_matrix((math.radians(mount_roll_deg), 0.0, 0.0))
        pb.setGravity(*(rot.T @ np.array(WORLD_GRAVITY)), physicsClientId=self._client)
        self._body, = load_fingers(self._client, [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))])
        # PyBullet's Jacobian point is in the link frame; the tip the simulator reports is link 9's
        # centre of mass, at its local inertial offset
        self._tip_offset = list(pb.getLinkState(self._body, TIP_LINK,
                                                physicsClientId=self._client)[2])
        # static compliance's inverse stiffness, SI: K_si = K_sim / TORQUE_SCALE
        self._Kinv_B = np.diag(1.0 / JOINT_STIFFNESS) @ B_MATRIX * TORQUE_SCALE
        self._Phi = self._Kinv_B / TORQUE_SCALE                      # Φ = K⁻¹ B, sim units

    def _jacobian(self, q: list, zeros: list) -> np.ndarray:
        """(3, 10) linear Jacobian of the tip (link 9's centre of mass) in the base frame, sim
        units."""
        lin, _ = pb.calculateJacobian(self._body, TIP_LINK, self._tip_offset, q, zeros, zeros,
                                      physicsClientId=self._client)
        return np.asarray(lin)

    def tip_state(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tip's (X, Y) position [m] and velocity [m/s] in the base frame at joint angles q
        (10,) [rad] and rates q̇ (10,) [rad/s]: the simulator's reported tip, from its joint
        state."""
        q = np.asarray(q, dtype=float).reshape(-1)
        qd = np.asarray(qd, dtype=float).reshape(-1)
        if q.shape != (N_JOINTS,) or qd.shape != (N_JOINTS,):
            raise ValueError(f'q and qd must have {N_JOINTS} entries, got {q.shape} and {qd.shape}')
        cid, body = self._client, self._body
        for j in range(N_JOINTS):
            pb.resetJointState(body, j, float(q[j]), float(qd[j]), physicsClientId=cid)
        state = pb.getLinkState(body, TIP_LINK, computeLinkVelocity=1, computeForwardKinematics=1,
                                physicsClientId=cid)
        return np.asarray(state[0][:2]) / LENGTH_SCALE, np.asarray(state[6][:2]) / LENGTH_SCALE

    def evaluate(self, q: np.ndarray, qd: np.ndarray, friction: bool = False) -> TaskDynamics:
        """The exact task-space terms at joint angles q (10,) [rad] and rates q̇ (10,) [rad/s].

        With ``friction`` the simulator's joint friction of a *slipping* joint, −F sign(q̇_j), is
        added to f_vel (a sticking joint's friction is a constraint force, not a function of the
        state; for checking against the simulator only).
        """
        q = np.asarray(q, dtype=float).reshape(-1)
        qd = np.asarray(qd, dtype=float).reshape(-1)
        if q.shape != (N_JOINTS,) or qd.shape != (N_JOINTS,):
            raise ValueError(f'q and qd must have {N_JOINTS} entries, got {q.shape} and {qd.shape}')
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            raise ValueError('q and qd must be finite')
        cid, body = self._client, self._body
        ql, qdl, zeros = q.tolist(), qd.tolist(), [0.0] * N_JOINTS
        M = np.asarray(pb.calculateMassMatrix(body, ql, physicsClientId=cid))  # sim units
        g = np.asarray(pb.calculateInverseDynamics(body, ql, zeros, zeros, physicsClientId=cid))
        h = np.asarray(pb.calculateInverseDynamics(body, ql, qdl, zeros,
                                                   physicsClientId=cid))  # C q̇ + g
        J = self._jacobian(ql, zeros)
        Jp = self._jacobian((q + _JDOT_STEP * qd).tolist(), zeros)
        Jm = self._jacobian((q - _JDOT_STEP * qd).tolist(), zeros)
        jdot_qd = (Jp - Jm) @ qd / (2 * _JDOT_STEP)                  # J̇ q̇ (sim units)
        for j in range(N_JOINTS):
            pb.resetJointState(body, j, ql[j], qdl[j], physicsClientId=cid)
        tip = np.asarray(pb.getLinkState(body, TIP_LINK, physicsClientId=cid)[0])
        JMinv = np.linalg.solve(M.T, J.T).T                          # J M⁻¹
        if friction:
            # τ_f = −F sign(q̇) moves to the left
            h = h + FRICTION_TORQUE * np.sign(qd)
        J2 = J[:2] / LENGTH_SCALE                                    # SI: m/rad
        Phi = self._Phi
        S_sim = J @ Phi                                              # static compliance, sim units
        proj = S_sim @ np.linalg.solve(Phi.T @ M @ Phi, Phi.T)       # S M_r⁻¹ Φᵀ
        return TaskDynamics(
            tip=tip[:2] / LENGTH_SCALE,
            tip_vel=J2 @ qd,
            f_pos=(JMinv @ (-JOINT_STIFFNESS * q - g))[:2] / LENGTH_SCALE,   # J M⁻¹ (−K q − g)
            f_vel=(jdot_qd - JMinv @ (h - g))[:2] / LENGTH_SCALE,            # J̇ q̇ − J M⁻¹ C q̇
            G2=(JMinv @ B_MATRIX)[:2] * TORQUE_SCALE / LENGTH_SCALE,         # J M⁻¹ B, SI
            S=J2 @ self._Kinv_B,                                             # J K⁻¹ B, SI
            J=J2,
            f_pos_r=(proj @ (-JOINT_STIFFNESS * q - g))[:2] / LENGTH_SCALE,
            f_vel_r=(jdot_qd - proj @ (h - g))[:2] / LENGTH_SCALE,
            G2_r=(proj @ B_MATRIX)[:2] * TORQUE_SCALE / LENGTH_SCALE)


#: below this distance from the origin [m] (and speed [m/s]) the rank-one corrections are skipped
_EPS_POS, _EPS_VEL = 1e-7, 1e-6


def oracle_sdc(d: TaskDynamics, rest_tip: np.ndarray,
               reduced: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """An SDC pair (A (4, 4), G (4, 2)) built from the true terms, translated by ``rest_tip``:
    the static-shape projection (``reduced``, default) or the paper's exact eq. (10)–(13).

    With p = tip − p₀ and v = ṗ, A = [[0, I], [A₂₁, A₂₂]], G = [[0], [G₂]] and

        A₂₁ = A_qs + (f_pos − A_qs p) pᵀ / pᵀp,      A_qs = −G₂ S⁻¹      (quasi-static stiffness)
        A₂₂ = f_vel vᵀ / vᵀv,

    so A x + G u = f + G₂ u holds exactly at this state. The factorisation is a choice: A_qs is the
    task-space stiffness the actuators see when the chain deforms along its static shapes (a held
    torque u gives p = S u, and then A_qs p + G₂ u = 0), and the rank-one terms add the minimum-norm
    correction that makes the product exact; any matrix N with N x = 0 could be added instead.
    """
    if reduced:
        d = d.reduced()
    p = d.tip - np.asarray(rest_tip, dtype=float)[:2]
    v = d.tip_vel
    A21 = -d.G2 @ np.linalg.inv(d.S)                         # A_qs = −G₂ S⁻¹
    pp = float(p @ p)
    if pp > _EPS_POS**2:
        A21 = A21 + np.outer(d.f_pos - A21 @ p, p) / pp      # exact along p
    A22 = np.zeros((2, 2))
    vv = float(v @ v)
    if vv > _EPS_VEL**2:
        A22 = np.outer(d.f_vel, v) / vv                      # exact along v
    A = np.zeros((4, 4))
    A[0, 2] = A[1, 3] = 1.0
    A[2:, :2], A[2:, 2:] = A21, A22
    G = np.zeros((4, 2))
    G[2:] = d.G2
    return A, G
