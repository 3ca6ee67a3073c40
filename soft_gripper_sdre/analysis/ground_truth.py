"""Ground truth from the simulator for judging a learned model and a loop (no ROS).

* :func:`true_tips` — each finger's true tip position and velocity from recorded joint states
  (``joint_states``), the ground truth the figures compare the reference with.
* :func:`input_matrix_survey` — the finger's true input matrix J M⁻¹ B (tip acceleration per unit
  torque, friction off) at static poses across the workspace, beside the learned G2 at the same
  states: column directions and magnitudes.
* :func:`score_model` — the learned model along a held-out excitation signal against the
  simulator's measured, the exact and the projected dynamics: R² of the acceleration and of the
  drift, the error of G2 and how far the learned SDC matrices lie from the oracle's.
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
from soft_gripper_sdre.sim.dynamics import FingerDynamics, oracle_sdc
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.linear import linearize
from soft_gripper_sdre.sim.signals import get_signal


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


#: what :func:`score_model` records at each sample: the time, state and torque, the tip
#: acceleration (measured by the simulator, exact, projected, learned), G2 (exact J M⁻¹ B,
#: projected, learned), the drift f (exact, projected, learned A(x)x) and [A₂₁ A₂₂] (learned, the
#: oracle's)
MODEL_SAMPLES = ('t', 'x', 'u', 'acc_sim', 'acc_exact', 'acc_proj', 'acc_learned', 'G2_exact',
                 'G2_proj', 'G2_learned', 'f_exact', 'f_proj', 'f_learned', 'A_learned',
                 'A_oracle')


def score_model(model, signal: str = 'u4', seconds: float = 4.0, every: int = 10) -> dict:
    """Drive the (hand-mounted) finger with a held-out excitation signal and compare, at every
    ``every``-th step: the learned ẍ = A(x)x + G(x)u with the exact, the projected and the
    simulator's measured tip acceleration; the learned G2 with J M⁻¹ B and with its projection;
    the learned drift A(x)x with the true f. Returns the samples (:data:`MODEL_SAMPLES`, arrays)
    and their summary statistics (:func:`model_truth_stats`)."""
    rows = {k: [] for k in MODEL_SAMPLES}
    sig = get_signal(signal)
    with GripperSim(SimConfig(scene='finger')) as sim, FingerDynamics() as fd:
        steps = int(round(seconds / sim.config.control_period))
        u_all = sig(np.arange(steps) * sim.config.control_period)
        for k in range(steps):
            if k % every == 0 and k > 0:
                _sample_step(rows, sim, fd, model, u_all[k])
            else:
                sim.step(u_all[k][None])
    r = {k: np.asarray(v) for k, v in rows.items()}
    return dict(stats=model_truth_stats(r, signal), samples=r)


def _sample_step(rows: dict, sim: GripperSim, fd: FingerDynamics, model, u: np.ndarray) -> None:
    """Take one step with torque ``u`` and append its :data:`MODEL_SAMPLES` to ``rows``: the model
    and the dynamics at the state before the step, the simulator's acceleration over it."""
    tr = sim.truth()
    d = fd.evaluate(tr.q[0], tr.qd[0])
    x = np.concatenate([tr.tip_pos[0, :2] - model.rest_tip[:2], tr.tip_vel[0, :2]])
    A, G = model.AG(x)
    sim.step(u[None])
    rows['t'].append(sim.t)
    rows['x'].append(x)
    rows['u'].append(u)
    rows['acc_sim'].append(sim.truth().tip_acc[0, :2])
    rows['acc_exact'].append(d.accel(u))
    rows['acc_proj'].append(d.reduced().accel(u))
    rows['acc_learned'].append((A[0] @ x + G[0] @ u)[2:])
    rows['G2_exact'].append(d.G2)
    rows['G2_proj'].append(d.G2_r)
    rows['G2_learned'].append(G[0, 2:])
    rows['f_exact'].append(d.f)
    rows['f_proj'].append(d.f_pos_r + d.f_vel_r)
    rows['f_learned'].append((A[0] @ x)[2:])
    rows['A_learned'].append(A[0, 2:])
    rows['A_oracle'].append(oracle_sdc(d, model.rest_tip)[0][2:])


def _r2(y: np.ndarray, yhat: np.ndarray) -> list[float]:
    """R² of ``yhat`` against ``y`` per column: 1 − Σ(y − ŷ)² / Σ(y − ȳ)²."""
    return (1.0 - ((y - yhat) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)).tolist()


def _g2_errors(learned: np.ndarray, G: np.ndarray) -> dict:
    """Medians over the samples of the learned G2's column direction error [deg] and magnitude
    ratio against ``G``, and of the relative Frobenius error."""
    ang = angle_difference(column_angles(learned), column_angles(G))
    mag = np.linalg.norm(learned, axis=-2) / np.linalg.norm(G, axis=-2)
    rel = np.linalg.norm(learned - G, axis=(1, 2)) / np.linalg.norm(G, axis=(1, 2))
    return dict(angle_median_deg=np.median(ang, 0).tolist(),
                magnitude_ratio_median=np.median(mag, 0).tolist(),
                rel_frobenius_median=float(np.median(rel)))


def model_truth_stats(r: dict, signal: str) -> dict:
    """The figures of :func:`score_model`'s samples ``r``: R² of the accelerations and drifts per
    axis, G2's errors, and the median relative difference of the learned [A₂₁ A₂₂] from the
    oracle's."""
    return dict(
        signal=signal, samples=int(r['t'].size),
        r2_learned_vs_sim=_r2(r['acc_sim'], r['acc_learned']),
        r2_exact_vs_sim=_r2(r['acc_sim'], r['acc_exact']),
        r2_proj_vs_sim=_r2(r['acc_sim'], r['acc_proj']),
        r2_learned_vs_exact=_r2(r['acc_exact'], r['acc_learned']),
        r2_learned_vs_proj=_r2(r['acc_proj'], r['acc_learned']),
        g2_vs_exact=_g2_errors(r['G2_learned'], r['G2_exact']),
        g2_vs_proj=_g2_errors(r['G2_learned'], r['G2_proj']),
        drift_r2_vs_exact=_r2(r['f_exact'], r['f_learned']),
        drift_r2_vs_proj=_r2(r['f_proj'], r['f_learned']),
        # the SDC factorisation is not unique: similar products A(x)x from different matrices
        a_rel_diff_median=float(np.median(
            np.linalg.norm(r['A_learned'] - r['A_oracle'], axis=(1, 2))
            / np.linalg.norm(r['A_oracle'], axis=(1, 2)))))


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
