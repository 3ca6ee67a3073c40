"""SDRE tracking control (the paper's eq. 22–24 with the checks of Remarks 2–3), batched over fingers.

For each finger, with A = A(x), G = G(x) from the learned model:

    P A + Aᵀ P + Q − P G R⁻¹ Gᵀ P = 0                       (24, stabilising solution)
    K = −R⁻¹ Gᵀ P,   A_cl = A − G R⁻¹ Gᵀ P,   K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q      (23)
    u = K x + K_s x_d, saturated to ±u_max                  (22)

Checks at every step (Remarks 2–3): (A, G) stabilisable, (A, Q^½) detectable, A_cl Hurwitz and
invertible, P symmetric positive definite, everything finite, small Riccati residual. A finger whose
step fails any check uses its last valid gains (fallback), or the gains of a nominal model before it
has any, or zero torque; the failure is counted. ``u`` is always finite.

Two solvers give the same P:

* ``'reference'`` — scipy's ``solve_continuous_are`` per finger (Schur method), general checks (PBH
  tests, eigenvalues of A_cl, condition number of A_cl). It is the yardstick.
* ``'fast'`` — for the SDC form A = [[0, I], [A21, A22]], G = [[0], [G2]] (write a = [A21 A22]):
  Newton–Kleinman warm-started from each finger's previous P, all fingers at once, with
  structure-aware checks that are each a handful of batched numpy calls (see :meth:`_fast_gains`).
  A finger that is cold (first step, or its last step was rejected), or fails any fast check, takes
  the exact path: scipy's solve and the general checks, for that finger only. Inputs that are not in
  SDC form always take the exact path.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag
import math

import numpy as np
from scipy.linalg import solve_continuous_are

from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE

METHODS = ('fast', 'reference')


class Check(IntFlag):
    """Bits of :attr:`SdreStep.failed_checks`."""

    STABILIZABLE = 1
    DETECTABLE = 2
    HURWITZ = 4
    ACL_SINGULAR = 8
    SOLVE_FAILED = 16
    NONFINITE = 32
    RESIDUAL = 64
    P_NOT_PD = 128


@dataclass
class SdreStep:
    """One control step for n fingers."""

    u: np.ndarray                # (n, 2) saturated torques, always finite
    u_unsat: np.ndarray          # (n, 2)
    K: np.ndarray                # (n, 2, 4) gains in use (fast path: read-only, shared with the
    Ks: np.ndarray               # (n, 2, 4)  controller's fallback gains, which it never writes into)
    P: np.ndarray                # (n, 4, 4) (NaN where the solve failed)
    residual: np.ndarray         # (n,) ‖PA + AᵀP + Q − PGR⁻¹GᵀP‖_F / ‖Q‖_F
    ok: np.ndarray               # (n,) every check passed
    fallback: np.ndarray         # (n,) fallback gains (or zero) used
    failed_checks: np.ndarray    # (n,) int bitmask of Check
    saturated: np.ndarray        # (n, 2)
    nk_iterations: np.ndarray    # (n,) Newton–Kleinman iterations (0 = exact solve)


def paper_weights_si() -> tuple[np.ndarray, np.ndarray]:
    """The paper's Q = diag(2,2,2,2), R = diag(0.1,0.1) (sim units) in SI.

    Positions and velocities scale by 20 (x_sim = 20 x_si) and torques by 400, so the cost
    x_simᵀ Q_sim x_sim + u_simᵀ R_sim u_sim equals x_siᵀ (400 Q_sim) x_si + u_siᵀ (160000 R_sim) u_si.
    """
    return (LENGTH_SCALE**2 * np.diag([2.0, 2.0, 2.0, 2.0]),
            TORQUE_SCALE**2 * np.diag([0.1, 0.1]))


def _check_weights(Q, R, u_max) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    Q = np.asarray(Q, dtype=float)
    R = np.asarray(R, dtype=float)
    if Q.shape != (4, 4) or not np.all(np.isfinite(Q)):
        raise ValueError(f'Q must be a finite (4, 4) matrix, got shape {Q.shape}')
    if not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q).min() < -1e-12 * max(1.0, np.abs(Q).max()):
        raise ValueError('Q must be symmetric positive semi-definite')
    if R.shape != (2, 2) or not np.all(np.isfinite(R)):
        raise ValueError(f'R must be a finite (2, 2) matrix, got shape {R.shape}')
    if not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0:
        raise ValueError('R must be symmetric positive definite')
    u_max = np.broadcast_to(np.asarray(u_max, dtype=float), (2,)).copy()
    if not np.all(np.isfinite(u_max)) or np.any(u_max <= 0):
        raise ValueError(f'u_max must be finite and > 0, got {u_max}')
    return Q, R, u_max


_CHECK_BITS = tuple((c.name, int(c)) for c in Check)
_I2 = np.eye(2)


def care(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Stabilising solution of PA + AᵀP + Q − PBR⁻¹BᵀP = 0 (reference: scipy, one system)."""
    return solve_continuous_are(A, B, Q, R)


def sdre_gains(A, G, Q, R) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, K_s, P) of eq. 23–24 for one system, for readers and tests."""
    P = care(A, G, Q, R)
    Rinv_Gt = np.linalg.solve(R, G.T)
    K = -Rinv_Gt @ P
    A_cl = A + G @ K
    Ks = -Rinv_Gt @ np.linalg.solve(A_cl.T, Q)        # −R⁻¹ Gᵀ A_cl⁻ᵀ Q
    return K, Ks, P


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a``, made read-only (for arrays that several results share)."""
    a.flags.writeable = False
    return a


def _checked(**arrays) -> list[np.ndarray]:
    """Each ``name=(value, shape)`` as a float array of that shape, in order.

    Raises:
        ValueError: naming the first array whose shape is wrong.
    """
    out = []
    for name, (value, shape) in arrays.items():
        arr = np.asarray(value, dtype=float)
        if arr.shape != shape:
            raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
        out.append(arr)
    return out


def _pbh_fails(A: np.ndarray, B: np.ndarray, tol: float = 1e-9) -> bool:
    """True when some eigenvalue λ of A with Re λ ≥ 0 has rank [A − λI, B] < n (PBH test)."""
    n = A.shape[0]
    for lam in np.linalg.eigvals(A):
        if lam.real >= -tol:
            M = np.hstack([A - lam * np.eye(n), B])
            s = np.linalg.svd(M, compute_uv=False)
            if s[-1] < tol * max(1.0, s[0]):
                return True
    return False


# ----------------------------------------------------------------------------------------------
# the SDC structure, tabulated once
# ----------------------------------------------------------------------------------------------
#
# A symmetric 4×4 P has 10 unknowns p: its upper triangle, row by row. _UPPER picks them out of
# P.reshape(16); _FULL rebuilds P from p; _LOW picks P's lower two rows (2, 4) out of p: with
# G = [[0], [G2]] those rows are all of P that Gᵀ sees (Gᵀ P = G2ᵀ P[2:, :]).
_ROWS, _COLS = np.triu_indices(4)
_UPPER = 4 * _ROWS + _COLS
_FULL = np.array([[int(np.flatnonzero((_ROWS == min(i, j)) & (_COLS == max(i, j)))[0])
                   for j in range(4)] for i in range(4)]).reshape(16)
_LOW = _FULL.reshape(4, 4)[2:, :].reshape(8)
#: the rows of A the SDC form fixes: Ẋ, Ẏ = [0 I] x
_TOP = np.hstack([np.zeros((2, 2)), np.eye(2)])
#: adj(C)ᵀ = _CHECKER ∘ C[::-1, ::-1] for 2×2 C, so C⁻ᵀ = _CHECKER ∘ C[::-1, ::-1] / det C
_CHECKER = np.array([[1.0, -1.0], [-1.0, 1.0]])


def _lyapunov_tables() -> tuple[np.ndarray, np.ndarray]:
    """The Lyapunov operator of an SDC matrix as a linear function of its lower rows.

    For A_k = [[0, I], [c]] (c the 2×4 lower rows) and symmetric P = P(p),

        L(A_k) p := upper triangle of −(A_kᵀ P + P A_k) = (L0 + Σ_rs c_rs T_rs) p,

    since the operator is linear in A_k. Returns L0 (100,) and T (8, 100), both flattened row-major
    (10×10), so that L(A_k) = (L0 + c.reshape(8) @ T).reshape(10, 10). The entries are small integers,
    exact in floating point.
    """
    basis = [np.eye(10)[j][_FULL].reshape(4, 4) for j in range(10)]

    def operator(A: np.ndarray) -> np.ndarray:
        return np.stack([(-(A.T @ B + B @ A)).reshape(16)[_UPPER] for B in basis], axis=1)

    top = np.zeros((4, 4))
    top[:2] = _TOP
    tables = []
    for r in range(2):
        for s in range(4):
            E = np.zeros((4, 4))
            E[2 + r, s] = 1.0
            tables.append(operator(E).reshape(100))
    return operator(top).reshape(100), np.stack(tables)


_L0, _T8 = _lyapunov_tables()


#: for 2×2 M flattened to f: f[_TWICE] ∘ f[_CROSS] = [f ∘ f, f ∘ reversed f], which @ _FRO_DET
#: sums to (‖M‖_F², det M)
_TWICE = np.array([0, 1, 2, 3, 0, 1, 2, 3])
_CROSS = np.array([0, 1, 2, 3, 3, 2, 1, 0])
_FRO_DET = np.array([[1.0, 0.0]] * 4 + [[0.0, 0.5], [0.0, -0.5], [0.0, -0.5], [0.0, 0.5]])


def _cond2_below(M: np.ndarray, c_max: float) -> tuple[np.ndarray, np.ndarray]:
    """For a stack of 2×2 matrices: (cond₂(M) < c_max, det M), without an SVD.

    With singular values σ₁ ≥ σ₂: σ₁² + σ₂² = ‖M‖_F² and σ₁σ₂ = |det M|, so
    κ + 1/κ = ‖M‖_F² / |det M| for κ = σ₁/σ₂; t ↦ t + 1/t increases on [1, ∞), hence
    κ < c_max ⇔ ‖M‖_F² < (c_max + 1/c_max) |det M|. Singular or non-finite M gives False.
    """
    f = M.reshape(-1, 4)                                   # [m00, m01, m10, m11]
    fro2_det = (f.take(_TWICE, axis=1) * f.take(_CROSS, axis=1)) @ _FRO_DET     # [‖M‖_F², det M]
    det = fro2_det[:, 1]
    return fro2_det[:, 0] < (c_max + 1.0 / c_max) * np.abs(det), det


#: weights of the upper-triangle entries in ‖S‖_F² of a symmetric 4×4 S (off-diagonals count twice)
_FRO10 = np.where(_ROWS == _COLS, 1.0, 2.0)


def _upper(S: np.ndarray) -> np.ndarray:
    """(m, 4, 4) → (m, 10): the upper triangle, row by row (the order of p)."""
    return S.reshape(-1, 16).take(_UPPER, axis=1)


def _nan_where_it_raises(fn, *stacks: np.ndarray, shape: tuple) -> np.ndarray:
    """fn over stacks at once, or, if that raises LinAlgError, matrix by matrix with NaN where it does."""
    try:
        return fn(*stacks)
    except np.linalg.LinAlgError:
        out = np.full(shape, np.nan)
        for i in range(shape[0]):
            try:
                out[i] = fn(*(s[i:i + 1] for s in stacks))[0]
            except np.linalg.LinAlgError:
                pass
        return out


def _public_stack_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _nan_where_it_raises(lambda L, b: np.linalg.solve(L, b[:, :, None])[:, :, 0], L, b, shape=b.shape)


def _public_stack_cholesky(S: np.ndarray) -> np.ndarray:
    return _nan_where_it_raises(np.linalg.cholesky, S, shape=S.shape)


def _stack_linalg():
    """(solve, cholesky) for stacks of small float64 matrices, NaN where one is singular / not PD.

    ``solve(L (m,k,k), b (m,k)) -> (m,k)`` and ``cholesky(S (m,k,k)) -> lower factors``. At m = 4 the
    public np.linalg.solve / cholesky spend about half / 60 % of their time on argument checks
    and error-state set-up; the gufuncs they call, ``numpy.linalg._umath_linalg.solve1`` and
    ``cholesky_lo`` (private; numpy is pinned), run the same LAPACK routines (gesv, potrf) and write
    NaN into the result of a matrix whose factorisation fails (an exactly zero pivot, a non-positive
    one in Cholesky, NaN input) instead of raising. A matrix singular only to rounding solves to
    finite garbage, as with the public solve: the directly formed residual and the cond tests reject
    it. Call them inside
    ``np.errstate(invalid='ignore')``. If the private module is missing or answers differently from
    the public functions on a small example, the public functions (wrapped to NaN likewise) serve.
    test_sdre_fast.py checks both implementations against each other.
    """
    try:
        from numpy.linalg import _umath_linalg as gufuncs
        solve, cholesky = gufuncs.solve1, gufuncs.cholesky_lo
        L = np.array([[[4.0, 1.0], [1.0, 3.0]], [[1.0, 2.0], [2.0, 4.0]]])     # PD; singular
        b = np.array([[1.0, 2.0], [1.0, 1.0]])
        with np.errstate(all='ignore'):
            x, c = solve(L, b), cholesky(L)
        if not (np.allclose(x[0], np.linalg.solve(L[0], b[0])) and np.isnan(x[1]).all()
                and np.allclose(c[0], np.linalg.cholesky(L[0])) and np.isnan(c[1]).all()):
            raise ValueError('numpy.linalg._umath_linalg answers differently')
        return solve, cholesky
    except (ImportError, AttributeError, TypeError, ValueError):
        return _public_stack_solve, _public_stack_cholesky


_stack_solve, _stack_cholesky = _stack_linalg()


@dataclass
class _FastGains:
    """What :meth:`SdreController._fast_gains` found for a batch of fingers."""

    p: np.ndarray            # (m, 10) P's upper triangle, the next warm start
    P: np.ndarray            # (m, 4, 4)
    KKs: np.ndarray          # (m, 2, 8) [K K_s], read-only: u = [K K_s] [x; x_d]
    K: np.ndarray            # (m, 2, 4) view of KKs
    Ks: np.ndarray           # (m, 2, 4) view of KKs
    residual: np.ndarray     # (m,)
    iterations: int          # Newton–Kleinman iterations done (the same for the whole batch)
    passed: np.ndarray       # (2m,) [G2; C] well conditioned and [P; N − margin] ≻ 0
    residual_tol: float

    @property
    def good(self) -> np.ndarray:
        """(m,) every fast check passed."""
        m = self.residual.shape[0]
        return self.passed[:m] & self.passed[m:] & (self.residual < self.residual_tol)

    def all_good(self) -> bool:
        """``good.all()``, by counting the flags that hold (cheaper than combining them)."""
        return (np.count_nonzero(self.passed) == self.passed.shape[0]
                and np.count_nonzero(self.residual < self.residual_tol) == self.residual.shape[0])


class SdreController:
    """The SDRE tracking law for ``n`` fingers with fallbacks and counters.

    Args:
        Q: (4, 4) state weight, symmetric PSD (SI).
        R: (2, 2) input weight, symmetric PD (SI).
        u_max: torque saturation per input [N·m] (scalar or (2,)).
        n: number of fingers.
        method: ``'fast'`` or ``'reference'``.
        residual_tol: largest accepted relative Riccati residual.
        cond_max: largest accepted condition number of G2 and of A_cl (``'fast'``: of A_cl's
            lower-left block, the only part of A_cl whose inverse the law uses).
        max_nk_iterations: most Newton–Kleinman iterations per step before the exact fallback.
            Newton–Kleinman stops once a bound on the next iterate's residual is below
            residual_tol / 2 (see :meth:`_fast_gains`).
        nominal: optional (A0, G0) whose gains serve as the fallback before any valid step.
    """

    def __init__(self, Q, R, u_max, n: int = 4, method: str = 'fast', residual_tol: float = 1e-6,
                 cond_max: float = 1e8, max_nk_iterations: int = 5,
                 nominal=None) -> None:
        self.Q, self.R, self.u_max = _check_weights(Q, R, u_max)
        if method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {method!r}')
        self.n, self.method = int(n), method
        self.residual_tol, self.cond_max = float(residual_tol), float(cond_max)
        self.max_nk = int(max_nk_iterations)
        if self.max_nk < 1:
            raise ValueError(f'max_nk_iterations must be >= 1, got {max_nk_iterations!r}')
        self._Rinv = np.linalg.inv(self.R)
        self._q_norm = max(np.linalg.norm(self.Q), 1e-300)
        self._q_pd = np.linalg.eigvalsh(self.Q).min() > 1e-12 * max(1.0, np.abs(self.Q).max())
        self._q_pos_pd = np.linalg.eigvalsh(self.Q[:2, :2]).min() > 1e-12 * max(1.0, np.abs(self.Q).max())
        w, V = np.linalg.eigh(self.Q)
        self._q_half = V @ np.diag(np.sqrt(np.clip(w, 0, None))) @ V.T
        # fast path constants: Q's upper triangle, Q's top rows (K_s), and Q shifted by the
        # Lyapunov test's margin (see _fast_gains)
        self._q10 = self.Q.reshape(16)[_UPPER]
        self._q_top = self.Q[:2, :].copy()
        self._q_shift = self.Q - 2.0 * self.residual_tol * self._q_norm * np.eye(4)
        self._neg_Rinv = -self._Rinv
        self._fro10_q = _FRO10 / self._q_norm**2          # ‖S‖_F² / ‖Q‖_F² from S's upper triangle
        self._half_tol_q = 0.5 * self.residual_tol * self._q_norm
        # the constants that meet (m, …) arrays elementwise, repeated for n fingers (slice [:m]):
        # a ufunc between arrays of one shape skips the broadcasting set-up (~0.6 µs a call here)
        tile = lambda c: np.ascontiguousarray(np.broadcast_to(c, (self.n,) + np.shape(c)))  # noqa: E731
        self._L0n, self._q10n, self._q_shift_n = tile(_L0), tile(self._q10), tile(self._q_shift)
        self._checker_n, self._u_max_n, self._u_min_n = tile(_CHECKER), tile(self.u_max), tile(-self.u_max)
        self._fast_ok = method == 'fast' and (self._q_pd or self._q_pos_pd)   # detectable by structure
        self._nominal = None
        if nominal is not None:
            K0, Ks0, _ = sdre_gains(np.asarray(nominal[0], float), np.asarray(nominal[1], float),
                                    self.Q, self.R)
            self._nominal = (K0, Ks0)
        # the flags of a step where every check passed, and nk_iterations per count: read-only,
        # shared by every such step (fresh arrays cost more than the rest of the bookkeeping)
        self._passed = tuple(_frozen(np.full(self.n, v, dtype=t))
                             for v, t in ((True, bool), (False, bool), (0, int)))
        self._iterations = [_frozen(np.full(self.n, k)) for k in range(self.max_nk + 1)]
        self.reset()

    def reset(self) -> None:
        """Forget warm starts and last valid gains; zero the counters."""
        self._p = np.zeros((self.n, 10))                 # warm start: upper triangle of the last P
        self._warm = np.zeros(self.n, dtype=bool)        # ... valid for these fingers
        self._all_warm = False
        self._K = np.zeros((self.n, 2, 4))
        self._Ks = np.zeros((self.n, 2, 4))
        self._have = np.zeros(self.n, dtype=bool)
        if self._nominal is not None:
            self._K[:] = self._nominal[0]
            self._Ks[:] = self._nominal[1]
        self.steps = 0
        self.fallbacks = 0
        self.exact_solves = 0
        self.check_failures = {c.name: 0 for c in Check}

    # -- entry points ------------------------------------------------------------------------
    def step(self, A, G, x, x_d) -> SdreStep:
        """Torques for every finger: A (n,4,4), G (n,4,2), x (n,4), x_d (n,4), translated SI."""
        n = self.n
        A, G, x, x_d = _checked(A=(A, (n, 4, 4)), G=(G, (n, 4, 2)), x=(x, (n, 4)), x_d=(x_d, (n, 4)))
        sdc = self.method == 'fast' and bool((A[:, :2, :] == _TOP).all()) and not G[:, :2, :].any()
        return self._step(A[:, 2:, :] if sdc else None, G[:, 2:, :] if sdc else None, A, G, x, x_d)

    def step_sdc(self, A2, G2, x, x_d) -> SdreStep:
        """:meth:`step` for a model in SDC form, given only its lower rows:
        A2 = [A21 A22] (n,2,4) and G2 (n,2,2), so that A = [[0, I], A2] and G = [[0], G2]."""
        n = self.n
        A2, G2 = np.asarray(A2, dtype=float), np.asarray(G2, dtype=float)
        x, x_d = np.asarray(x, dtype=float), np.asarray(x_d, dtype=float)
        if (A2.shape, G2.shape, x.shape, x_d.shape) != ((n, 2, 4), (n, 2, 2), (n, 4), (n, 4)):
            _checked(A2=(A2, (n, 2, 4)), G2=(G2, (n, 2, 2)), x=(x, (n, 4)), x_d=(x_d, (n, 4)))  # raises
        if self.method != 'fast':
            A, G = self._full(A2, G2)
            return self._step(None, None, A, G, x, x_d)
        return self._step(A2, G2, None, None, x, x_d)

    @staticmethod
    def _full(A2: np.ndarray, G2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A = [[0, I], A2], G = [[0], G2]."""
        n = A2.shape[0]
        A = np.zeros((n, 4, 4))
        A[:, :2, :] = _TOP
        A[:, 2:, :] = A2
        G = np.zeros((n, 4, 2))
        G[:, 2:, :] = G2
        return A, G

    def _step(self, a, g, A, G, x, x_d) -> SdreStep:
        """One step; ``a``, ``g`` are the SDC lower rows (None: not in SDC form), A, G the full
        matrices (None: build them from a, g if the exact path needs them)."""
        self.steps += 1
        fast, idx = None, None
        if a is not None and self._fast_ok and self._all_warm:
            fast = self._fast_gains(a, g, self._p)
            if fast.all_good():
                # the common path: every finger warm and every fast check passed
                u_unsat = np.matvec(fast.KKs, np.concatenate((x, x_d), axis=1))   # eq. 22: K x + K_s x_d
                # Σ u² is finite iff every u is (or it overflows beyond 1e154: then the careful path)
                if math.isfinite(np.vdot(u_unsat, u_unsat)):
                    # the gains are read-only and shared with the result: _careful_step rebinds
                    # self._K, self._Ks instead of writing into them (warm ⇒ have: unchanged)
                    self._p, self._K, self._Ks = fast.p, fast.K, fast.Ks
                    u = np.minimum(np.maximum(u_unsat, self._u_min_n), self._u_max_n)    # = np.clip, cheaper
                    ok, fallback, failed = self._passed
                    return SdreStep(u=u, u_unsat=u_unsat, K=fast.K, Ks=fast.Ks, P=fast.P,
                                    residual=fast.residual, ok=ok, fallback=fallback, failed_checks=failed,
                                    saturated=u != u_unsat,          # = |u_unsat| > u_max here
                                    nk_iterations=self._iterations[fast.iterations])
        elif a is not None and self._fast_ok and self._warm.any():
            idx = np.flatnonzero(self._warm)
            fast = self._fast_gains(a[idx], g[idx], self._p[idx])
        if A is None:
            A, G = self._full(a, g)
        return self._careful_step(A, G, x, x_d, a is not None, fast, idx)

    # -- the fast path -----------------------------------------------------------------------
    def _fast_gains(self, a: np.ndarray, g: np.ndarray, p0: np.ndarray) -> _FastGains:
        """Warm-started Newton–Kleinman and the structure-aware checks for m SDC fingers.

        Args:
            a: (m, 2, 4) lower rows [A21 A22] of A; g: (m, 2, 2) G2; p0: (m, 10) warm starts.

        Returns:
            the gains and which fingers passed every check (a failed solve gives NaN, which fails them).

        With S = G R⁻¹ Gᵀ = [[0, 0], [0, W]], W = G2 R⁻¹ G2ᵀ, every product with S only needs P's
        lower rows P_low = P[2:, :]: S P = [[0], [W P_low]], P S P = P_lowᵀ W P_low, and
        A_k = A − S P_k keeps the SDC form with lower rows a − W P_low.

        Newton–Kleinman: A_kᵀ P_{k+1} + P_{k+1} A_k = −(Q + P_k S P_k), solved as one 10×10 system
        per finger (P symmetric: 10 unknowns) whose matrix is linear in A_k's lower rows
        (:func:`_lyapunov_tables`); the batched solve and Cholesky go through :func:`_stack_linalg`.

        Stop rule. Subtracting the equations of two iterates gives the exact identity
        Res(P_{k+1}) = −Δ_k S Δ_k (Δ_k = P_{k+1} − P_k), and with S's structure
        Δ_k S Δ_k = Δ_lowᵀ W Δ_low, a positive semi-definite matrix (W = G2 R⁻¹ G2ᵀ ⪰ 0), whose
        Frobenius norm is at most its trace (√Σλ² ≤ Σλ for λ ≥ 0):

            ‖Res(P_{k+1})‖_F ≤ tr(Δ_lowᵀ W Δ_low) = ⟨Δ_low, W Δ_low⟩,

        and W Δ_low = W P_{k+1,low} − W P_{k,low} is the difference of two products the iteration
        forms anyway. The iteration stops at the first k with Σ_i ⟨Δ_low,i, W_i Δ_low,i⟩ <
        residual_tol ‖Q‖_F / 2, i.e. when every finger's new iterate has (in exact arithmetic) at
        most half the accepted residual; the other half is room for the solve's rounding. (This
        trace is ≤ ‖W‖_F ‖Δ_low‖_F², the bound of the previous rule, so it never stops later.) The
        identity only decides when to stop: the
        residual that the checks use is then formed directly from P (below), so a solve that rounded
        badly fails the check instead of passing unseen. The gains' error is of the order of the
        residual times the conditioning of the Lyapunov operator of A_cl (measured on the noisy
        closed-loop replay: ≤ 1.1e-5 of the largest torque against scipy; the stated tolerance is 1e-4).

        Checks (each finger; any failure sends that finger to the exact path):

        * stabilisable: rank [G, AG] = 4 iff G2 is invertible, so (A, G) is controllable when
          cond(G2) < cond_max (closed form for 2×2, :func:`_cond2_below`). Detectable: holds for
          Q ≻ 0, or for Q's position block ≻ 0 through the [0 I] rows (as in
          :meth:`_careful_step`); any other Q always takes the exact path;
        * residual ‖Res‖_F / ‖Q‖_F < residual_tol, formed directly from P, on its upper triangle:
          Res = Q − L(A) p − P S P, since L(A) p is the upper triangle of −(AᵀP + PA);
        * P ≻ 0 and A_cl Hurwitz, by Lyapunov. For any P, A_clᵀP + P A_cl = −N with
          N = Q + P S P − Res (expand A_cl = A − S P and the residual). If P ≻ 0 and N ≻ 0 then
          every eigenpair A_cl v = λv gives 2 Re λ · v*Pv = −v*Nv < 0, so Re λ < 0. By Weyl,
          λ_min(N) ≥ λ_min(Q + P S P) − ‖Res‖₂ and ‖Res‖₂ ≤ ‖Res‖_F < tol ‖Q‖_F, so it suffices that
          Q + P S P − 2 tol ‖Q‖_F I ≻ 0; the second tol ‖Q‖_F covers rounding in forming P S P
          and Res (of order 1e-16 (‖PA‖ + ‖PSP‖), far below it here). Both tests are one Cholesky
          of the stacked [P; Q + PSP − 2 tol ‖Q‖_F I]. Q + P S P ≻ 0 needs Q's position block ≻ 0
          (on x = [0; v], P S P = vᵀ P22 W P22 v > 0 for P ≻ 0); a Q without it always takes the
          exact path's eigenvalue test;
        * A_cl invertible: A_cl = [[0, I], [C, D]] has det A_cl = det C and A_cl⁻ᵀ = [[·, I], [C⁻ᵀ, 0]],
          so Gᵀ A_cl⁻ᵀ = G2ᵀ [C⁻ᵀ, 0] and K_s = −R⁻¹ G2ᵀ C⁻ᵀ Q[:2, :]: the only inverse the law uses
          is C⁻¹, and the check is cond(C) < cond_max.
        """
        m = a.shape[0]
        q10 = self._q10n[:m]
        # a non-finite model output or a failed factorisation gives NaN, which fails a check
        with np.errstate(all='ignore'):
            nGR = g @ self._neg_Rinv                           # −G2 R⁻¹ = (−R⁻¹ G2ᵀ)ᵀ, R symmetric
            W = nGR @ g.transpose(0, 2, 1)
            np.negative(W, out=W)                              # W = G2 R⁻¹ G2ᵀ
            L_open = a.reshape(m, 8) @ _T8
            L_open += self._L0n[:m]                            # L(A), flattened
            L_A = L_open.reshape(m, 10, 10)
            P_low = p0.take(_LOW, axis=1).reshape(m, 2, 4)
            WP = W @ P_low                                     # S P (lower rows)
            PSP10 = _upper(P_low.transpose(0, 2, 1) @ WP)      # P S P = P_lowᵀ W P_low
            for iterations in range(1, self.max_nk + 1):
                L = (L_open - WP.reshape(m, 8) @ _T8).reshape(m, 10, 10)       # L(A − S P_k)
                p = _stack_solve(L, PSP10 + q10)               # A_kᵀP + PA_k = −(Q + P_k S P_k)
                P_next = p.take(_LOW, axis=1).reshape(m, 2, 4)
                D = P_next - P_low                             # lower rows of Δ_k = P_k+1 − P_k
                WP_next = W @ P_next
                WD = WP_next - WP                              # W Δ_low
                P_low, WP = P_next, WP_next
                PSP = P_low.transpose(0, 2, 1) @ WP
                PSP10 = PSP.reshape(m, 16).take(_UPPER, axis=1)            # (its upper triangle)
                # stop rule: ‖Res(P_k+1)‖_F ≤ ⟨Δ_low, W Δ_low⟩ per finger (see the docstring)
                if np.vdot(D, WD) < self._half_tol_q:          # False for NaN: iterate on
                    break
            res = np.matvec(L_A, p)
            res += PSP10
            res -= q10                                         # −Res = L(A)p + PSP − Q (upper)
            residual = np.sqrt((res * res) @ self._fro10_q)    # ‖Res‖_F / ‖Q‖_F (off-diagonals twice)
            P = p.take(_FULL, axis=1).reshape(m, 4, 4)
            C = (a - WP)[:, :, :2]                             # A_cl = [[0, I], [C, D]] = A − S P
            # stabilisable (G2) and A_cl invertible (C), both 2×2 condition tests in one call
            well, det = _cond2_below(np.concatenate([g, C]), self.cond_max)
            # [K K_s] = −R⁻¹ G2ᵀ [P_low, C⁻ᵀ Q[:2, :]],  C⁻ᵀ = [[c11, −c10], [−c01, c00]] / det C
            CitQ = (C[:, ::-1, ::-1] * self._checker_n[:m]) @ self._q_top
            CitQ /= det[m:, None, None]
            KKs = _frozen(nGR.transpose(0, 2, 1) @ np.concatenate((P_low, CitQ), axis=2))
            # P ≻ 0 and N − margin ≻ 0: both Cholesky factors exist. A failed one is all NaN, and
            # L₃₃ depends on every entry of the lower triangle, so a NaN in the input reaches it too
            # (+inf on a diagonal can leave L₃₃ finite or +inf; the residual, NaN then, rejects it)
            chol = _stack_cholesky(np.concatenate([P, PSP + self._q_shift_n[:m]]))
            # (a factor that exists has a positive diagonal; NaN > 0 is False)
            passed = well & (chol[:, 3, 3] > 0.0)     # [G2; C] conditioned, [P; N − margin] ≻ 0
        return _FastGains(p=p, P=P, KKs=KKs, K=KKs[:, :, :4], Ks=KKs[:, :, 4:], residual=residual,
                          iterations=iterations, passed=passed, residual_tol=self.residual_tol)

    # -- the exact path ----------------------------------------------------------------------
    def _exact(self, A, G, i) -> np.ndarray:
        self.exact_solves += 1
        try:
            return care(A[i], G[i], self.Q, self.R)
        except (np.linalg.LinAlgError, ValueError):
            return np.full((4, 4), np.nan)

    def _solve(self, A, G, usable, fast, idx) -> tuple[np.ndarray, np.ndarray]:
        """P for every usable finger: the fast result where it passed, else scipy's solve."""
        P = np.full((self.n, 4, 4), np.nan)
        iters = np.zeros(self.n, dtype=int)
        done = np.zeros(self.n, dtype=bool)
        if fast is not None:
            rows = np.arange(self.n) if idx is None else idx
            take = fast.good & usable[rows]
            P[rows[take]] = fast.P[take]
            iters[rows[take]] = fast.iterations
            done[rows[take]] = True
        for i in np.flatnonzero(usable & ~done):
            P[i] = self._exact(A, G, i)
        return P, iters

    def _residual(self, A, G, P) -> np.ndarray:
        GRG = G @ self._Rinv @ G.transpose(0, 2, 1)
        Res = P @ A + A.transpose(0, 2, 1) @ P + self.Q - P @ GRG @ P
        return np.linalg.norm(Res, axis=(1, 2)) / self._q_norm

    def _careful_step(self, A, G, x, x_d, sdc: bool, fast: _FastGains | None, idx) -> SdreStep:
        """The law with every check in its general form and the fallbacks, finger by finger."""
        n = self.n
        failed = np.zeros(n, dtype=int)
        finite = (np.all(np.isfinite(A), axis=(1, 2)) & np.all(np.isfinite(G), axis=(1, 2))
                  & np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(x_d), axis=1))
        failed[~finite] |= Check.NONFINITE
        A = np.where(finite[:, None, None], A, 0.0)
        G = np.where(finite[:, None, None], G, 0.0)

        # Remark 3: (A, G) stabilisable, (A, Q^½) detectable
        if sdc:
            with np.errstate(all='ignore'):
                stab = finite & _cond2_below(G[:, 2:, :], self.cond_max)[0]
        else:
            stab = np.array([finite[i] and not _pbh_fails(A[i], G[i]) for i in range(n)])
        failed[finite & ~stab] |= Check.STABILIZABLE
        if self._q_pd:
            detect = np.ones(n, dtype=bool)
        elif self._q_pos_pd and np.all(A[:, :2, :2] == 0.0) and np.all(A[:, :2, 2:] == _I2):
            # SDC structure A = [[0, I], ·] with Q weighting both positions: C = Q^½ sees X, Y and,
            # through the [0 I] rows, their rates, so (A, Q^½) is observable for every x
            detect = np.ones(n, dtype=bool)
        else:
            detect = np.array([finite[i] and not _pbh_fails(A[i].T, self._q_half.T) for i in range(n)])
            failed[finite & ~detect] |= Check.DETECTABLE
        usable = finite & stab & detect

        P, iters = self._solve(A, G, usable, fast, idx)
        solved = usable & np.all(np.isfinite(P), axis=(1, 2))
        failed[usable & ~solved] |= Check.SOLVE_FAILED
        Psafe = np.where(solved[:, None, None], P, 0.0)
        residual = np.where(solved, self._residual(A, G, Psafe), np.nan)
        failed[solved & ~(residual < self.residual_tol)] |= Check.RESIDUAL
        pd = np.zeros(n, dtype=bool)
        if solved.any():
            pd[solved] = np.linalg.eigvalsh(Psafe[solved]).min(axis=1) > 0
        failed[solved & ~pd] |= Check.P_NOT_PD

        # eq. 23 and Remark 2: A_cl Hurwitz and invertible
        Rinv_Gt = self._Rinv @ G.transpose(0, 2, 1)                  # (n, 2, 4)
        K = -Rinv_Gt @ Psafe                                         # K = −R⁻¹GᵀP
        A_cl = A + G @ K                                             # A − G R⁻¹ Gᵀ P
        hurwitz = np.zeros(n, dtype=bool)
        invertible = np.zeros(n, dtype=bool)
        Ks = np.zeros((n, 2, 4))
        if solved.any():
            s = np.flatnonzero(solved)
            hurwitz[s] = np.all(np.linalg.eigvals(A_cl[s]).real < 0, axis=1)
            with np.errstate(all='ignore'):
                invertible[s] = np.linalg.cond(A_cl[s]) < self.cond_max
            ok_inv = s[invertible[s]]
            if ok_inv.size:
                # K_s = −R⁻¹ Gᵀ A_cl⁻ᵀ Q
                Ks[ok_inv] = -Rinv_Gt[ok_inv] @ np.linalg.solve(A_cl[ok_inv].transpose(0, 2, 1),
                                                                np.broadcast_to(self.Q, (ok_inv.size, 4, 4)))
        failed[solved & ~hurwitz] |= Check.HURWITZ
        failed[solved & ~invertible] |= Check.ACL_SINGULAR
        ok = failed == 0
        ok &= np.all(np.isfinite(K), axis=(1, 2)) & np.all(np.isfinite(Ks), axis=(1, 2))

        # accept or fall back; new arrays, not writes into the old ones: the fast path shares its
        # gains with the step it returned
        self._K = np.where(ok[:, None, None], K, self._K)
        self._Ks = np.where(ok[:, None, None], Ks, self._Ks)
        self._have |= ok
        self._p[ok] = P[ok].reshape(-1, 16)[:, _UPPER]
        self._warm = ok.copy()           # no warm start from a rejected solve
        self._all_warm = bool(ok.all())
        fallback = ~ok
        use_zero = fallback & ~self._have & (self._nominal is None)
        Kuse, Ksuse = self._K.copy(), self._Ks.copy()
        Kuse[use_zero] = 0.0
        Ksuse[use_zero] = 0.0
        xs = np.where(finite[:, None], x, 0.0)
        xds = np.where(finite[:, None], x_d, 0.0)
        u_unsat = np.einsum('nij,nj->ni', Kuse, xs) + np.einsum('nij,nj->ni', Ksuse, xds)   # eq. 22
        u_unsat = np.where(np.isfinite(u_unsat), u_unsat, 0.0)
        u_unsat[~finite] = 0.0            # no torque from a state we cannot read
        u = np.clip(u_unsat, -self.u_max, self.u_max)
        saturated = np.abs(u_unsat) > self.u_max

        self.fallbacks += int(fallback.sum())
        if failed.any():
            for name, bit in _CHECK_BITS:
                self.check_failures[name] += int(np.count_nonzero(failed & bit))
        return SdreStep(u=u, u_unsat=u_unsat, K=Kuse, Ks=Ksuse, P=P, residual=residual, ok=ok,
                        fallback=fallback, failed_checks=failed, saturated=saturated,
                        nk_iterations=iters)
