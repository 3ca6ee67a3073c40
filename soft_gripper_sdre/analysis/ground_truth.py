"""Ground truth from the simulator for judging a learned model and a loop (no ROS).

* :func:`true_tips` — each finger's true tip position and velocity from recorded joint states
  (``joint_states``), the ground truth the figures compare the reference with.
* :func:`input_matrix_survey` — the finger's true input matrix J M⁻¹ B (tip acceleration per unit
  torque, friction off) at static poses across the workspace, beside the learned G2 at the same
  states: column directions and magnitudes.
* :func:`loop_spectral_radius` — the sampled loop (ZOH plant, steady-state constant-velocity KF,
  frozen SDRE gains, the roll-off) closed around the *full* linearised 10-joint finger with
  friction off, at any control period: the growth per step of its least stable mode. It explains
  why the loop leans on joint friction, and which bending mode a long period destabilises.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from soft_gripper_sdre.analysis.metrics import angle_difference, column_angles
from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.riccati import sdre_gains
from soft_gripper_sdre.control.tracking import RollOff
from soft_gripper_sdre.sim.dynamics import FingerDynamics
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.linear import linearize


def true_tips(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True tip positions and velocities of hand fingers from their joint states.

    Args:
        joints: (T, n, 2, 10) joint angles [rad] and rates [rad/s] per sample and finger, as
            :class:`soft_gripper_sdre.analysis.bag.Run` reads them from ``joint_states``.

    Returns:
        ((T, n, 2) tip X, Y [m], (T, n, 2) tip velocity [m/s]) in each finger's base frame: the
        forward kinematics of the simulator's own finger, without measurement noise.
    """
    joints = np.asarray(joints, dtype=float)
    if joints.ndim != 4 or joints.shape[2:] != (2, 10):
        raise ValueError(f'joints must have shape (T, n, 2, 10), got {joints.shape}')
    pos = np.empty(joints.shape[:2] + (2,))
    vel = np.empty_like(pos)
    with FingerDynamics() as finger:                    # the hand's fingers are all mounted alike
        for k in range(joints.shape[0]):
            for i in range(joints.shape[1]):
                pos[k, i], vel[k, i] = finger.tip_state(joints[k, i, 0], joints[k, i, 1])
    return pos, vel


@dataclass
class InputMatrixSurvey:
    """Learned vs true input matrices at P poses."""

    u: np.ndarray            # (P, 2) torque that holds each pose [N·m]
    x: np.ndarray            # (P, 4) the model's state there (translated, zero velocity)
    true: np.ndarray         # (P, 2, 2) J M⁻¹ B [m/s² per N·m]
    learned: np.ndarray      # (P, 2, 2) G2(x)

    @property
    def angle_error(self) -> np.ndarray:
        """(P, 2) direction error of each column [deg]."""
        return angle_difference(column_angles(self.learned), column_angles(self.true))

    @property
    def magnitude_ratio(self) -> np.ndarray:
        """(P, 2) |learned column| / |true column|."""
        return np.linalg.norm(self.learned, axis=-2) / np.linalg.norm(self.true, axis=-2)


def input_matrix_survey(model, torques: np.ndarray, settle: float = 2.0) -> InputMatrixSurvey:
    """Hold each torque pair on a fresh finger (mounted like a hand finger) for ``settle`` s, then
    compare J M⁻¹ B there with the model's G2 at the same state."""
    rows = {'u': [], 'x': [], 'true': [], 'learned': []}
    for u in np.atleast_2d(np.asarray(torques, dtype=float)):
        with GripperSim(SimConfig(scene='finger')) as sim:
            for _ in range(int(round(settle / sim.config.control_period))):
                sim.step(u[None])
            M, _, B, J = linearize(sim)
            tip = sim.truth().tip_pos[0]
        x = np.concatenate([tip[:2] - model.rest_tip[:2], [0.0, 0.0]])
        rows['u'].append(u)
        rows['x'].append(x)
        rows['true'].append(J[:2] @ np.linalg.solve(M, B))
        rows['learned'].append(model.AG(x)[1][0, 2:, :])
    return InputMatrixSurvey(**{k: np.asarray(v) for k, v in rows.items()})


def linear_finger(dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZOH discretisation (Ad (20,20), Bd (20,2)) and tip output C (2,20) of the finger at rest,
    friction off, SI."""
    with GripperSim(SimConfig(scene='finger')) as sim:
        M, K, B, J = linearize(sim)
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    Ac = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, np.zeros((n, n))]])
    Bc = np.vstack([np.zeros((n, 2)), Minv @ B])
    E = expm(np.block([[Ac, Bc], [np.zeros((2, 2 * n + 2))]]) * dt)
    return E[:2 * n, :2 * n], E[:2 * n, 2 * n:], np.hstack([J[:2], np.zeros((2, n))])


def loop_spectral_radius(plant, model, Q: np.ndarray, R: np.ndarray, accel_psd: float,
                         meas_std: float, dt: float = 1e-3,
                         lowpass_hz: float = 0.0, capped: bool = True) -> tuple[float, float]:
    """(largest |eigenvalue|, its frequency [Hz]) of the sampled loop: plant (Ad, Bd, C) from
    :func:`linear_finger`, steady-state KF, gains frozen at the model's origin, and the optional
    first-order roll-off on the command (:class:`~soft_gripper_sdre.control.tracking.RollOff`, its
    corner capped at a tenth of the sampling rate as every law caps it; ``capped=False``: the
    corner as asked, for comparison). > 1 means a mode that grows when nothing but the linear
    dynamics act on it."""
    Ad, Bd, C = plant
    A0, G0 = model.AG(np.zeros(4))
    K, _, _ = sdre_gains(A0[0], G0[0], Q, R)
    kf = ConstantVelocityKF(dt, accel_psd, meas_std, n=1)
    _, L = kf.steady_state()
    Af = (np.eye(4) - L @ kf.H) @ kf.F
    # state [z_k, x̂_{k−1}, u_{k−1}]:  x̂_k = Af x̂_{k−1} + L C z_k,
    # u_k = a u_{k−1} + (1 − a) K x̂_k (a = 0 without roll-off),  z_{k+1} = Ad z_k + Bd u_k
    hz = RollOff(lowpass_hz, dt).hz if capped else lowpass_hz
    a = float(np.exp(-2.0 * np.pi * hz * dt)) if hz > 0 else 0.0
    Uz, Ux, Uu = (1 - a) * K @ L @ C, (1 - a) * K @ Af, a * np.eye(2)
    closed = np.block([[Ad + Bd @ Uz, Bd @ Ux, Bd @ Uu],
                       [L @ C, Af, np.zeros((4, 2))],
                       [Uz, Ux, Uu]])
    ev = np.linalg.eigvals(closed)
    k = int(np.argmax(np.abs(ev)))
    return float(np.abs(ev[k])), float(abs(np.angle(ev[k])) / (2 * np.pi * dt))
