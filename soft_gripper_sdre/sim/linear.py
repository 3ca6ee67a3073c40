"""The simulated finger linearised about its pose, friction off (ground truth for analysis and
tests).

M δq̈ + K δq = B u with the tip δp = J δq, in SI, from PyBullet's own rigid-body model of the
finger scene of :class:`~soft_gripper_sdre.sim.hand.GripperSim`.
"""
from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.finger import (
    B_MATRIX,
    JOINT_STIFFNESS,
    N_JOINTS,
    TIP_LINK,
    WORLD_GRAVITY,
)
from soft_gripper_sdre.sim.hand import GripperSim
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE


def linearize(sim: GripperSim) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The finger linearised about its current pose with friction off, in SI (finger scene):
    M δq̈ + K δq = B u, tip position δp = J δq.

    M (10, 10) [kg·m²] and K (10, 10) [N·m/rad] (the simulator's joint springs, with its plant's
    scale, + gravity stiffness ∂g/∂q, by
    central differences of PyBullet's inverse dynamics with gravity as the mounted base sees
    it), B (10, 2) (u in N·m), and the tip Jacobian J (3, 10) [m/rad] in the finger's base
    frame (finite differences of the tip).
    """
    if sim.config.scene != 'finger':
        raise ValueError('linearize is defined for the finger scene')
    cid = sim.physics_client
    body = sim.finger_bodies[0]
    states = pb.getJointStates(body, list(range(N_JOINTS)), physicsClientId=cid)
    q = [s[0] for s in states]
    M = np.array(pb.calculateMassMatrix(body, q, physicsClientId=cid))
    zeros = [0.0] * N_JOINTS
    h = 1e-6
    dg = np.zeros((N_JOINTS, N_JOINTS))
    J = np.zeros((3, N_JOINTS))
    rot = sim.base_poses[1][0]
    # calculateInverseDynamics ignores a fixed base's orientation (gravity acts as if the finger
    # stood upright), so it runs with gravity turned into the base frame, g_b = Rᵀ (0, 0, −g),
    # as in dynamics.FingerDynamics; the world's gravity is put back right after
    pb.setGravity(*(rot.T @ np.array(WORLD_GRAVITY)).tolist(), physicsClientId=cid)
    try:
        for j in range(N_JOINTS):
            qp, qm = list(q), list(q)
            qp[j] += h
            qm[j] -= h
            gp = np.array(pb.calculateInverseDynamics(body, qp, zeros, zeros, physicsClientId=cid))
            gm = np.array(pb.calculateInverseDynamics(body, qm, zeros, zeros, physicsClientId=cid))
            dg[:, j] = (gp - gm) / (2 * h)                  # ∂g/∂q_j
    finally:
        pb.setGravity(*WORLD_GRAVITY, physicsClientId=cid)
    for j in range(N_JOINTS):
        qp, qm = list(q), list(q)
        qp[j] += h
        qm[j] -= h
        tips = []
        for qq in (qp, qm):
            for k in range(N_JOINTS):
                pb.resetJointState(body, k, qq[k], physicsClientId=cid)
            tips.append(np.asarray(pb.getLinkState(body, TIP_LINK, physicsClientId=cid)[0]))
        J[:, j] = rot.T @ (tips[0] - tips[1]) / (2 * h)
    for k, st in enumerate(states):                       # put the finger back exactly
        pb.resetJointState(body, k, st[0], st[1], physicsClientId=cid)
    # scaled world → SI: lengths /20, torques /400 (so inertia /400 too: τ = M q̈)
    K = (np.diag(JOINT_STIFFNESS * sim.config.plant.stiffness_scale) + dg) / TORQUE_SCALE
    return M / TORQUE_SCALE, K, B_MATRIX.copy(), J / LENGTH_SCALE

def linear_modes(sim: GripperSim) -> np.ndarray:
    """Natural frequencies [Hz] of the finger linearised about its current pose, friction off."""
    M, K, _, _ = linearize(sim)
    w2 = np.linalg.eigvals(np.linalg.solve(M, K))
    return np.sort(np.sqrt(np.abs(w2.real))) / (2 * math.pi)
