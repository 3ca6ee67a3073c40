"""What a finger's recordings say about it, for the loop settings derived from them
(:mod:`~soft_gripper_sdre.analysis.loop_settings`): the tip period, the measurement noise, the
torque range, the estimator intensity that best explains the tips, and the move a closed-loop
check makes: along the direction the finger moved most, by a share of its reach that way.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from soft_gripper_sdre.control.kf import cv_matrices

#: the check's move: along the data's principal direction by a share of the data's reach that way
#: (the 99th percentile of the tips projected on it), on the trajectory node's default timing
TRAVEL_SHARE = 0.5
REACH_PERCENTILE = 99.0
#: the torque limit is this many times the largest torque of the excitation
TORQUE_MARGIN = 2.0


def unit_vector(degrees: float) -> np.ndarray:
    """(cos, sin) of an angle from +X toward +Y [deg]."""
    a = math.radians(degrees)
    return np.array([math.cos(a), math.sin(a)])


@dataclass(frozen=True)
class DataFacts:
    """What the recordings say about the finger (SI)."""

    period: float                 # median tip period [s]
    noise_std: float              # measurement σ [m]
    travel: float                 # length of the move the check makes along ``direction`` [m]
    torque_limit: float           # the loop's torque limit [N·m]
    accel_psd_ml: float           # the CV model's likelihood-best intensity [(m/s²)²/Hz]
    # TRAVEL_SHARE of the data's reach that way [m] (None: travel)
    reach_travel: float | None = None
    direction: float = 90.0       # of the move, from +X toward +Y [deg] (90: closing along +Y)

    @property
    def unit(self) -> np.ndarray:
        """The move's direction as a unit vector (X, Y)."""
        return unit_vector(self.direction)

    def move(self) -> tuple[float, float]:
        """The move as the trajectory node's ``(close_distance, side_distance)`` [m]: its Y and X
        parts."""
        x, y = self.travel * self.unit
        return float(y), float(x)


def cv_loglik(t: np.ndarray, pos: np.ndarray, accel_psd: float, meas_std: float) -> float:
    """Innovation log-likelihood of tips ``pos`` (N, 2) at times ``t`` under the estimator's
    constant-velocity model (each axis on its own)."""
    R = meas_std ** 2
    ll = 0.0
    for axis in range(pos.shape[1]):
        x = np.array([pos[0, axis], 0.0])
        P = np.diag([R, 1.0])
        for k in range(1, len(t)):
            F, Q = cv_matrices(t[k] - t[k - 1], accel_psd)
            F, Q = F[np.ix_([0, 2], [0, 2])], Q[np.ix_([0, 2], [0, 2])]
            x = F @ x
            P = F @ P @ F.T + Q
            S = P[0, 0] + R
            v = pos[k, axis] - x[0]
            ll -= 0.5 * (math.log(2 * math.pi * S) + v * v / S)
            K = P[:, 0] / S
            x = x + K * v
            P = P - np.outer(K, P[0, :])
    return ll


def tune_accel_psd(t: np.ndarray, pos: np.ndarray, meas_std: float,
                   grid: np.ndarray | None = None) -> float:
    """The estimator's intensity that best explains the tips (:func:`cv_loglik` on a log grid)."""
    grid = np.logspace(-3, 5, 17) if grid is None else grid
    sigma = max(meas_std, 1e-7)
    return float(max(grid, key=lambda q: cv_loglik(t, pos, q, sigma)))


def closing_direction(positions: np.ndarray) -> float:
    """The direction [deg from +X toward +Y, in [0, 180)] the tips ``positions`` (N, 2), as
    displacements from the rest pose, moved most: the principal axis of their second moment about
    the rest, turned toward +Y (the closing side; toward +X when it lies along X)."""
    p = np.asarray(positions, dtype=float)
    _, vecs = np.linalg.eigh(p.T @ p)
    x, y = vecs[:, -1]
    if y < 0 or (y == 0 and x < 0):
        x, y = -x, -y
    return float(math.degrees(math.atan2(y, x)))


def data_facts(positions: np.ndarray, torques: np.ndarray, period: float, noise_std: float,
               tune: list[tuple[np.ndarray, np.ndarray]]) -> DataFacts:
    """:class:`DataFacts` from the training samples: translated positions (N, 2), held torques
    (N, 2), the tip period, the measured σ, and (t, tips) of stretches to tune the estimator on
    (the largest intensity any of them asks for: the loop must follow the fastest motion)."""
    direction = closing_direction(positions)
    along = positions @ unit_vector(direction)
    travel = TRAVEL_SHARE * max(float(np.percentile(along, REACH_PERCENTILE)), 0.0)
    limit = TORQUE_MARGIN * float(np.percentile(np.abs(torques).max(axis=1), 99.9))
    psd = max(tune_accel_psd(t, tips, noise_std) for t, tips in tune)
    return DataFacts(period=float(period), noise_std=float(noise_std), travel=float(travel),
                     torque_limit=limit, accel_psd_ml=psd, reach_travel=float(travel),
                     direction=direction)
