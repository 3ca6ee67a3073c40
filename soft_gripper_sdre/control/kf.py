"""The paper's constant-velocity Kalman filter (appendix), batched over fingers.

State per finger x = [X, Y, Ẋ, Ẏ] [m, m/s] (a tip of d = 3 coordinates: x = [X, Y, Z, Ẋ, Ẏ, Ż],
the same model with I the d × d identity); continuous model ẋ = A x + D ṽ with

    A = [[0, I], [0, 0]],    H = [I, 0],    F = e^{AΔt} = [[I, Δt I], [0, I]],

and the discrete process noise Σ_v = ∫₀^Δt e^{As} D q Dᵀ e^{Aᵀs} ds for white acceleration noise of
intensity q [(m/s²)²/Hz]. The paper writes D = [0 0 1 1]ᵀ: one scalar noise drives both axes, so
their accelerations are modelled as perfectly correlated (``process_noise='paper'``). The tip's
X and Y accelerations are not correlated like that, so the default (``'independent'``) gives each
axis its own noise, D = [[0,0],[0,0],[1,0],[0,1]].

    predict:  x̂ = F x̂,                 S = F S Fᵀ + Σ_v
    update:   K = S Hᵀ (H S Hᵀ + Σ_r)⁻¹,  x̂ = x̂ + K (z − H x̂),
              S = (I − K H) S (I − K H)ᵀ + K Σ_r Kᵀ     (Joseph form: stays symmetric PSD)

Each step may have its own Δt (a sensor whose stamps are not evenly spaced): F and Σ_v are then
built for that Δt inside the compiled step. A step of the filter's own ``dt`` uses the matrices
built once at construction, so a fixed-rate run does the same arithmetic whichever way it is called.
The compiled steps are the planar tip's (d = 2); a 3-D tip runs the same equations in numpy.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_are

from soft_gripper_sdre.control.kernels import kernel_array, kf_step, kf_step_dt
from soft_gripper_sdre.sim.shape import FingerShape

PROCESS_NOISE_MODELS = ('independent', 'paper')


def cv_matrices(dt: float, accel_psd: float, process_noise: str = 'independent', d: int = 2):
    """F (2d,2d) and Σ_v (2d,2d) of the constant-velocity model for step ``dt`` and a tip of ``d``
    coordinates."""
    if process_noise not in PROCESS_NOISE_MODELS:
        raise ValueError(f'process_noise must be one of {PROCESS_NOISE_MODELS}, '
                         f'got {process_noise!r}')
    I2 = np.eye(d)
    F = np.block([[I2, dt * I2], [np.zeros((d, d)), I2]])
    # ∫ e^{As} D q Dᵀ e^{Aᵀs} ds = q [[Δt³/3 C, Δt²/2 C], [Δt²/2 C, Δt C]],  C = D₂ D₂ᵀ
    C = I2 if process_noise == 'independent' else np.ones((d, d))
    Q = accel_psd * np.block([[dt**3 / 3 * C, dt**2 / 2 * C], [dt**2 / 2 * C, dt * C]])
    return F, Q


class ConstantVelocityKF:
    """Constant-velocity KF for ``n`` fingers at once; each step is one call of the compiled
    :func:`~soft_gripper_sdre.control.kernels.kf.kf_step`.

    Args:
        dt: sample period [s].
        accel_psd: white-acceleration intensity q [(m/s²)²/Hz] (Σ_v scale).
        meas_std: measurement standard deviation σ_r [m] (Σ_r = σ_r² I).
        n: number of fingers.
        process_noise: ``'independent'`` (default) or ``'paper'`` (D = [0 0 1 1]ᵀ).
        d: the tip's coordinates, 2 (X, Y) or 3 (X, Y, Z).

    ``x`` (n, 2d) and ``P`` (n, 2d, 2d) are the estimate and its covariance, updated in place.

    Raises:
        ValueError: a setting out of range (:class:`~soft_gripper_sdre.sim.shape.ShapeError` for
            ``d``).
    """

    def __init__(self, dt: float, accel_psd: float, meas_std: float, n: int = 4,
                 process_noise: str = 'independent', d: int = 2) -> None:
        self.d = FingerShape(d, 1).d
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f'dt must be finite and > 0, got {dt!r}')
        if not (np.isfinite(accel_psd) and accel_psd >= 0):
            raise ValueError(f'accel_psd must be finite and >= 0, got {accel_psd!r}')
        if not (np.isfinite(meas_std) and meas_std > 0):
            raise ValueError(f'meas_std must be finite and > 0, got {meas_std!r}')
        if int(n) < 1:
            raise ValueError(f'n must be >= 1, got {n!r}')
        self.dt, self.n = float(dt), int(n)
        self._process_noise = process_noise
        self._F, self._Q = cv_matrices(dt, accel_psd, process_noise, self.d)
        self._accel_psd = float(accel_psd)
        self._axis_coupling = 0.0 if process_noise == 'independent' else 1.0
        self._F_dt, self._Q_dt = np.empty((4, 4)), np.empty((4, 4))     # kf_step_dt's scratch
        self._H = np.hstack([np.eye(self.d), np.zeros((self.d, self.d))])
        self._R = meas_std**2 * np.eye(self.d)
        self._p0 = max(1.0, 1e6 * meas_std**2)     # broad initial velocity covariance
        self._all_valid = np.ones(self.n, dtype=np.bool_)
        self.reset()

    F = property(lambda self: self._F.copy())
    Q = property(lambda self: self._Q.copy())
    H = property(lambda self: self._H.copy())
    R = property(lambda self: self._R.copy())

    def reset(self, z0: np.ndarray | None = None) -> None:
        """Start over: positions at z0 (n, d) (zero if None), zero velocity, broad covariance."""
        d = self.d
        self.x = np.zeros((self.n, 2 * d))
        if z0 is not None:
            z0 = np.asarray(z0, dtype=float)
            if z0.shape != (self.n, d):
                raise ValueError(f'z0 must have shape ({self.n}, {d}), got {z0.shape}')
            self.x[:, :d] = z0
        self.P = np.tile(np.diag(list(np.diag(self._R)) + [self._p0] * d), (self.n, 1, 1))

    def step(self, z: np.ndarray, valid: np.ndarray | None = None,
             dt: float | None = None) -> np.ndarray:
        """Predict over ``dt`` seconds (None: the filter's own ``dt``) and update with
        measurements z (n, d); rows with ``valid`` False (or a non-finite z) only predict.
        Returns a copy of x̂ (n, 2d).

        Raises:
            ValueError: z of the wrong shape, or ``dt`` not finite and > 0.
        """
        z = kernel_array(z)
        if z.shape != (self.n, self.d):
            raise ValueError(f'z must have shape ({self.n}, {self.d}), got {z.shape}')
        if valid is None:
            valid = self._all_valid
        else:
            valid = kernel_array(np.broadcast_to(np.asarray(valid, dtype=np.bool_), (self.n,)),
                                 np.bool_)
        if self.d != 2:
            if not (dt is None or (np.isfinite(dt) and dt > 0)):
                raise ValueError(f'dt must be finite and > 0, got {dt!r}')
            F, Q = ((self._F, self._Q) if dt is None or dt == self.dt
                    else cv_matrices(float(dt), self._accel_psd, self._process_noise, self.d))
            self._general_step(z, valid, F, Q)
            return self.x.copy()
        if dt is None or dt == self.dt:
            kf_step(self.x, self.P, z, valid, self._F, self._Q, self._R)
        elif np.isfinite(dt) and dt > 0:
            kf_step_dt(self.x, self.P, z, valid, float(dt), self._accel_psd, self._axis_coupling,
                       self._F_dt, self._Q_dt, self._R)
        else:
            raise ValueError(f'dt must be finite and > 0, got {dt!r}')
        return self.x.copy()

    def _general_step(self, z: np.ndarray, valid: np.ndarray, F: np.ndarray,
                      Q: np.ndarray) -> None:
        """The compiled step's equations in numpy, for any d: x, P in place."""
        d = self.d
        xp = self.x @ F.T
        Pp = F @ self.P @ F.T + Q
        upd = valid & np.isfinite(z).all(axis=1)
        self.x[:], self.P[:] = xp, Pp
        if not upd.any():
            return
        Pu = Pp[upd]
        S = Pu[:, :d, :d] + self._R                                    # H S Hᵀ + Σ_r
        K = np.linalg.solve(S, Pu[:, :d, :]).transpose(0, 2, 1)        # S Hᵀ (H S Hᵀ + Σ_r)⁻¹
        self.x[upd] = xp[upd] + np.einsum('nij,nj->ni', K, z[upd] - xp[upd, :d])
        IKH = np.broadcast_to(np.eye(2 * d), Pu.shape).copy()
        IKH[:, :, :d] -= K
        self.P[upd] = (IKH @ Pu @ IKH.transpose(0, 2, 1)
                       + K @ self._R @ K.transpose(0, 2, 1))            # Joseph form

    def steady_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Steady-state prior covariance S∞ (from the DARE) and gain K∞ of one finger."""
        S = solve_discrete_are(self._F.T, self._H.T, self._Q, self._R)
        K = S @ self._H.T @ np.linalg.inv(self._H @ S @ self._H.T + self._R)
        return S, K
