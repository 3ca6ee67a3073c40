"""Tracking and grasp metrics (SI in, mm and % out), shared by the demo, the report and the
tests."""
from __future__ import annotations

from dataclasses import asdict, dataclass
import itertools

import numpy as np


@dataclass(frozen=True)
class TrackingMetrics:
    """Free-space 2-D tip position error of one finger."""

    rmse_mm: float
    max_mm: float
    excursion_mm: float
    rmse_pct: float
    samples: int

    def as_dict(self) -> dict:
        return asdict(self)


def tracking_metrics(pos: np.ndarray, ref: np.ndarray, mask: np.ndarray,
                     excursion: np.ndarray) -> list[TrackingMetrics]:
    """Per-finger RMSE and max of the 2-D position error where ``mask`` is True.

    Args:
        pos: (T, n, 2) actual tip positions [m].
        ref: (T, n, 2) reference positions [m].
        mask: (T, n) bool, samples to score (free space).
        excursion: (n,) peak excursion of the reference from rest [m]; the RMSE is also given as a
            percentage of it (NaN for a finger whose reference does not move).
    """
    pos = np.asarray(pos, dtype=float)
    ref = np.asarray(ref, dtype=float)
    mask = np.asarray(mask, dtype=bool)
    if pos.shape != ref.shape or pos.ndim != 3 or pos.shape[2] != 2:
        raise ValueError(f'pos and ref must both have shape (T, n, 2), got {pos.shape} and '
                         f'{ref.shape}')
    if mask.shape != pos.shape[:2]:
        raise ValueError(f'mask must have shape {pos.shape[:2]}, got {mask.shape}')
    excursion = np.broadcast_to(np.asarray(excursion, dtype=float), (pos.shape[1],))
    err = np.linalg.norm(pos - ref, axis=2)          # ‖p − p_d‖ per sample and finger
    out = []
    for i in range(pos.shape[1]):
        e = err[mask[:, i], i]
        if e.size == 0:
            out.append(TrackingMetrics(float('nan'), float('nan'), excursion[i] * 1e3, float('nan'),
                                       0))
            continue
        rmse = float(np.sqrt(np.mean(e**2)))
        pct = 100.0 * rmse / excursion[i] if excursion[i] > 0 else float('nan')
        out.append(TrackingMetrics(rmse * 1e3, float(e.max()) * 1e3, float(excursion[i]) * 1e3,
                                   pct, int(e.size)))
    return out


def held_reference_error(pos: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray,
                         contact: np.ndarray) -> np.ndarray:
    """(n,) per finger: the mean 2-D distance [mm] of the tip from a reference that stands still and
    is reachable, i.e. over the samples where the reference velocity is exactly zero and the finger
    does not touch the cube (NaN for a finger without such samples).

    In the grasp these are the rest before the fingers move and after they are back, and the hold
    phase of the fingers that do not grasp (the grasping fingers hold a reference inside the cube:
    not reachable, not counted). It measures the steady offset joint friction leaves.

    Args:
        pos, ref_pos, ref_vel: (T, n, 2) tip position, reference position and velocity [m, m/s].
        contact: (T, n) bool, the finger touches the cube.
    """
    pos, ref_pos, ref_vel = (np.asarray(a, dtype=float) for a in (pos, ref_pos, ref_vel))
    if not (pos.shape == ref_pos.shape == ref_vel.shape and pos.ndim == 3 and pos.shape[2] == 2):
        raise ValueError(f'pos, ref_pos and ref_vel must all have shape (T, n, 2), '
                         f'got {pos.shape}, {ref_pos.shape} and {ref_vel.shape}')
    contact = np.asarray(contact, dtype=bool)
    if contact.shape != pos.shape[:2]:
        raise ValueError(f'contact must have shape {pos.shape[:2]}, got {contact.shape}')
    still = np.all(ref_vel == 0.0, axis=2) & ~contact
    err = np.linalg.norm(pos - ref_pos, axis=2)
    out = np.full(pos.shape[1], np.nan)
    for i in range(pos.shape[1]):
        if still[:, i].any():
            out[i] = 1e3 * float(err[still[:, i], i].mean())
    return out


def r2_score(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Coefficient of determination per column: 1 − Σ(y − ŷ)² / Σ(y − ȳ)²."""
    y_true = np.asarray(y_true, dtype=float)
    y_pred = np.asarray(y_pred, dtype=float)
    if y_true.shape != y_pred.shape:
        raise ValueError(f'y_true and y_pred shapes differ: {y_true.shape} vs {y_pred.shape}')
    ss_res = np.sum((y_true - y_pred) ** 2, axis=0)
    ss_tot = np.sum((y_true - y_true.mean(axis=0)) ** 2, axis=0)
    return 1.0 - ss_res / ss_tot


def poly_features(x: np.ndarray, u: np.ndarray, degree: int = 3) -> np.ndarray:
    """All monomials of (x, u) up to ``degree`` (with the constant): the features of the
    least-squares baseline that training reports beside the model's R²."""
    z = np.hstack([x, u])
    cols = [np.ones(len(z))]
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(z.shape[1]), d):
            cols.append(np.prod(z[:, combo], axis=1))
    return np.stack(cols, axis=1)


def column_angles(G2: np.ndarray) -> np.ndarray:
    """Direction [deg] of each column of G2 (…, 2, 2) in the (X, Y) plane."""
    G2 = np.asarray(G2, dtype=float)
    return np.degrees(np.arctan2(G2[..., 1, :], G2[..., 0, :]))


def angle_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a − b| wrapped to [0, 180] degrees."""
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)
