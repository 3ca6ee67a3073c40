"""A Koopman (EDMD with inputs) model of one finger: a linear model on lifted observables.

The baseline a data-driven soft-robot controller would use instead of the SDC networks: lift the
task-space state into observables ψ, fit z_{k+1} = A z_k + B u_k by ridge least squares on the
same excitation records, and control the linear lifted model (MPC or LQR,
:mod:`soft_gripper_sdre.control.laws.koopman`). Numpy only (no torch).

Observables at step k (s = [p − p₀, ṗ] scaled per component by its training standard deviation,
p the tip position in the finger's base frame, p₀ the settled rest tip), for a finger whose tip
has d coordinates (the hand: 2, so s has 4 components) and m inputs:

    z_k = [ s_k (2d),  (p_{k−j} − p₀)/σ_p for each delay j (d per delay),  monomials of s_k of
            degree 2 … ``degree`` ]

* **Polynomial terms** (the shipped model: degree ≤ 3) give the linear lifted model some of the
  configuration dependence of the stiffness and the input map.
* **Delay coordinates** of the position (optional; none in the shipped model) stand in for the
  states a 4-state model does not see (the bending of the 10-joint chain) and improve the one-step
  fit most. But their fitted evolution is a regression, not the exact shift it is physically, and
  a controller built on the lifted model feeds back on them as if it were: docs/results.md
  "Koopman baseline" has both measurements.
* No constant observable: the rest pose is z = 0 with u = 0, as f(0) = 0 for the SDC model.

The fit regresses the increment z_{k+1} − z_k on [z_k, u_k/σ_u] with ridge α (per sample, on
standardised columns), so the regularisation pulls A toward the identity ("nothing changes in
1 ms"), not toward zero. Deterministic: one linear solve, no randomness. The first of each
record's delayed samples repeat its first position (the finger rested before the record); the
law fills its history the same way at its first step.
"""
from __future__ import annotations

from dataclasses import dataclass
import itertools
import json
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
#: the model shipped with the package (tools/learning/koopman.py --install writes it)
DEFAULT_KOOPMAN = Path(__file__).resolve().parent.parent / 'models' / 'koopman.npz'


class KoopmanFileError(ValueError):
    """A Koopman model file cannot be used; the message names the file and the reason."""


@dataclass(frozen=True)
class KoopmanSettings:
    """The observables and the regression (see the module doc)."""

    delays: tuple[int, ...] = ()           # delay coordinates of the position [control periods]
    degree: int = 3                        # highest degree of the state monomials (1 = none)
    ridge: float = 1e-8                    # α per sample, on standardised columns

    def __post_init__(self) -> None:
        if (any(int(d) != d or d < 1 for d in self.delays)
                or len(set(self.delays)) != len(self.delays)):
            raise ValueError('delays must be distinct integers >= 1 (control periods), '
                             f'got {self.delays!r}')
        if int(self.degree) != self.degree or not 1 <= self.degree <= 4:
            raise ValueError(f'degree must be an integer in 1..4, got {self.degree!r}')
        if not (np.isfinite(self.ridge) and self.ridge >= 0):
            raise ValueError(f'ridge must be finite and >= 0, got {self.ridge!r}')


def monomial_indices(degree: int, n_state: int = 4) -> list[tuple[int, ...]]:
    """Index tuples of the monomials of degree 2 … ``degree`` in the ``n_state`` (2d) scaled
    state components."""
    return [c for d in range(2, degree + 1)
            for c in itertools.combinations_with_replacement(range(n_state), d)]


class KoopmanModel:
    """The lifted linear model z_{k+1} = A z_k + B u_k (u in each input's SI unit) and its
    observables, for a tip of d coordinates (2 or 3: the size of ``state_scale`` is 2d) and m
    inputs (1 to 4: the columns of ``B``).

    Args:
        A: (n_z, n_z), B: (n_z, m) the lifted model at the control period ``dt``.
        state_scale: (2d,) σ of [p − p₀, ṗ] per component the observables divide by [m, m/s].
        rest_tip: (≥d,) the rest tip p₀ [m]; dt: control period [s].
        settings: the observables (delays in control periods, degree) and the ridge used.
        info: what the fit was made from and how well it fits (JSON-able).
    """

    def __init__(self, A, B, state_scale, rest_tip, dt: float, settings: KoopmanSettings,
                 info: dict | None = None) -> None:
        self.settings = settings
        self.state_scale = np.array(state_scale, dtype=float)
        if self.state_scale.ndim != 1 or self.state_scale.size not in (4, 6) \
                or not np.all(self.state_scale > 0):
            raise ValueError('state_scale must be 2d positive numbers for a tip of d = 2 or 3 '
                             f'coordinates (4 or 6), got {state_scale!r}')
        n_s = self.state_scale.size
        self.d = n_s // 2
        self.monomials = monomial_indices(settings.degree, n_s)
        # the monomials as one gather: index 2d is a column of ones padding lower degrees
        self.monomial_table = np.array([c + (n_s,) * (settings.degree - len(c))
                                        for c in self.monomials],
                                       dtype=int).reshape(len(self.monomials), settings.degree)
        self.n_z = n_s + self.d * len(settings.delays) + len(self.monomials)
        self.A = np.array(A, dtype=float)
        self.B = np.array(B, dtype=float)
        self.rest_tip = np.array(rest_tip, dtype=float).reshape(-1)
        self.dt = float(dt)
        self.info = dict(info or {})
        if (self.A.shape != (self.n_z, self.n_z) or self.B.ndim != 2
                or self.B.shape[0] != self.n_z or not 1 <= self.B.shape[1] <= 4):
            raise ValueError(f'A must be ({self.n_z}, {self.n_z}) and B ({self.n_z}, m), m = 1 '
                             f'to 4 inputs, for {settings} and a tip of {self.d} coordinates, '
                             f'got {self.A.shape} and {self.B.shape}')
        self.m = self.B.shape[1]
        if self.rest_tip.size < self.d or not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f'rest_tip needs {self.d} coordinates and dt must be > 0')
        for name in ('A', 'B', 'state_scale', 'rest_tip'):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f'{name} holds non-finite values')
        #: output map: [p − p₀, ṗ] (SI) = C z
        self.C = np.zeros((n_s, self.n_z))
        self.C[:, :n_s] = np.diag(self.state_scale)

    @property
    def max_delay(self) -> int:
        """The longest delay [control periods]: the history a lift needs."""
        return max(self.settings.delays, default=0)

    def lift(self, x: np.ndarray, delayed_pos: np.ndarray) -> np.ndarray:
        """Observables z (…, n_z) from the translated state x (…, 2d) = [p − p₀, ṗ] and the
        translated positions ``delayed_pos`` (…, n_delays, d) at the model's delays (in
        ``settings.delays`` order)."""
        s = np.asarray(x, dtype=float) / self.state_scale
        d = np.asarray(delayed_pos, dtype=float) / self.state_scale[:self.d]
        parts = [s, d.reshape(d.shape[:-2] + (-1,))]
        if self.monomials:
            ones = np.ones(s.shape[:-1] + (1,))
            parts.append(np.concatenate([s, ones], axis=-1)[..., self.monomial_table].prod(axis=-1))
        return np.concatenate(parts, axis=-1)

    def lift_series(self, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Observables (N, n_z) along a record: translated positions and velocities (N, d) at
        consecutive control periods; the delays before the first sample repeat it."""
        pos, vel = np.asarray(pos, dtype=float), np.asarray(vel, dtype=float)
        padded = np.concatenate([np.repeat(pos[:1], self.max_delay, axis=0), pos])
        n = len(pos)
        delayed = np.stack([padded[self.max_delay - d:self.max_delay - d + n]
                            for d in self.settings.delays]
                           or [np.empty((n, 0))], axis=1).reshape(n, -1, self.d)
        return self.lift(np.hstack([pos, vel]), delayed)

    def predict_acceleration(self, pos: np.ndarray, vel: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Mean tip acceleration over each period the model predicts along a record,
        (ṗ_{k+1|k} − ṗ_k)/Δt (N, d): the quantity the SDC model's R² is scored on."""
        z = self.lift_series(pos, vel)
        z_next = z @ self.A.T + np.asarray(u, dtype=float) @ self.B.T
        return ((z_next @ self.C.T)[:, self.d:] - np.asarray(vel, dtype=float)) / self.dt

    # -- file -------------------------------------------------------------------------------
    def save(self, path: Path | str) -> Path:
        """Write the model as an uncompressed ``.npz`` of plain arrays (no pickles)."""
        path = Path(path)
        np.savez(path, format_version=np.int64(FORMAT_VERSION), A=self.A, B=self.B,
                 state_scale=self.state_scale, rest_tip=self.rest_tip, dt=np.float64(self.dt),
                 delays=np.asarray(self.settings.delays, dtype=np.int64),
                 degree=np.int64(self.settings.degree), ridge=np.float64(self.settings.ridge),
                 info=np.str_(json.dumps(self.info, sort_keys=True)))
        return path

    @classmethod
    def load(cls, path: Path | str | None = None) -> 'KoopmanModel':
        """Read a model file (default: the shipped one).

        Raises:
            KoopmanFileError: missing, not an npz, wrong version, missing or inconsistent arrays.
        """
        path = Path(path) if path is not None else DEFAULT_KOOPMAN
        if not path.is_file():
            raise KoopmanFileError(f'{path}: no such Koopman model file '
                                   '(python -m soft_gripper_sdre.tools.learning.koopman '
                                   '--data DIR --out DIR writes one)')
        try:
            with np.load(path, allow_pickle=False) as f:
                arrays = {k: f[k] for k in f.files}
        except Exception as exc:  # noqa: BLE001  zip, pickle and format errors alike
            raise KoopmanFileError(f'{path}: not a readable .npz of plain arrays ({exc})') from None
        missing = {'format_version', 'A', 'B', 'state_scale', 'rest_tip', 'dt', 'delays', 'degree',
                   'ridge'} - set(arrays)
        if missing:
            raise KoopmanFileError(f'{path}: missing arrays {sorted(missing)}')
        if int(arrays['format_version']) != FORMAT_VERSION:
            raise KoopmanFileError(f'{path}: format version {int(arrays["format_version"])}, '
                                   f'this code reads {FORMAT_VERSION}')
        try:
            settings = KoopmanSettings(tuple(int(d) for d in arrays['delays']),
                                       int(arrays['degree']), float(arrays['ridge']))
            info = json.loads(str(arrays['info'])) if 'info' in arrays else {}
            return cls(arrays['A'], arrays['B'], arrays['state_scale'], arrays['rest_tip'],
                       float(arrays['dt']), settings, info)
        except (ValueError, TypeError) as exc:
            raise KoopmanFileError(f'{path}: {exc}') from None


def fit_koopman(series: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rest_tip, dt: float,
                settings: KoopmanSettings = KoopmanSettings(),
                info: dict | None = None) -> KoopmanModel:
    """Fit the lifted model to records by ridge least squares (module doc).

    Args:
        series: per record (pos, vel, u): translated tip positions [m] and velocities [m/s],
            each (N, d), d = 2 or 3, and the inputs applied over each period (N, m), m = 1 to 4
            (the hand: torques [N·m], (N, 2)), at consecutive control periods.
        rest_tip: the rest tip p₀ the positions are translated by; dt: the control period [s].

    Raises:
        ValueError: no record, shapes that disagree, non-finite data, or too few samples.
    """
    if not series:
        raise ValueError('fit_koopman needs at least one record')
    d0, m0 = np.shape(series[0][0])[-1], np.shape(series[0][2])[-1]
    for i, (p, v, u) in enumerate(series):
        if not (np.shape(p) == np.shape(v) and np.ndim(p) == 2 and np.ndim(u) == 2
                and np.shape(u)[0] == np.shape(p)[0] and np.shape(p)[1] == d0 in (2, 3)
                and np.shape(u)[1] == m0 and 1 <= m0 <= 4):
            raise ValueError(f'record {i}: pos and vel must each be (N, d), d = 2 or 3, and u '
                             f'(N, m), m = 1 to 4, alike in every record, got '
                             f'{np.shape(p)}, {np.shape(v)}, {np.shape(u)}')
        if not all(np.all(np.isfinite(a)) for a in (p, v, u)):
            raise ValueError(f'record {i}: holds non-finite samples')
    x_all = np.vstack([np.hstack([p, v]) for p, v, _ in series])
    u_all = np.vstack([u for _, _, u in series])
    scale = x_all.std(axis=0)
    u_scale = u_all.std(axis=0)
    if not (np.all(scale > 0) and np.all(u_scale > 0)):
        raise ValueError('every state component and every input must vary in the data')
    n_z = 2 * d0 + d0 * len(settings.delays) + len(monomial_indices(settings.degree, 2 * d0))
    lifter = KoopmanModel(np.eye(n_z), np.zeros((n_z, m0)), scale, rest_tip, dt, settings)
    z_now, z_next, u_now = [], [], []
    for p, v, u in series:
        z = lifter.lift_series(p, v)
        z_now.append(z[:-1])
        z_next.append(z[1:])
        u_now.append(u[:-1] / u_scale)
    Z, Zn, U = np.vstack(z_now), np.vstack(z_next), np.vstack(u_now)
    if len(Z) < 10 * (n_z + m0):
        raise ValueError(f'{len(Z)} samples are too few to fit {n_z + m0} columns')
    X = np.hstack([Z, U])
    gram = X.T @ X + settings.ridge * len(X) * np.eye(n_z + m0)
    W = np.linalg.solve(gram, X.T @ (Zn - Z))                      # [A − I; B σ_u]ᵀ
    A = np.eye(n_z) + W[:n_z].T
    B = W[n_z:].T / u_scale
    return KoopmanModel(A, B, scale, rest_tip, dt, settings, info)
