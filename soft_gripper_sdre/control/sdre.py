"""The SDRE supervisor: the paper's law u = K(x) x + K_s(x) x_d (eq. 22, saturated) for n fingers.

K, K_s and the checks are those of eq. 23–24 and Remarks 2–3 (:mod:`~soft_gripper_sdre.control.riccati`).
``method='reference'`` solves with scipy; ``'fast'`` with the kernel (:mod:`~soft_gripper_sdre.control.kernel`,
warm-started Newton–Kleinman on the SDC form), and a finger that is cold (first step, or its last step
was rejected) or fails a kernel check takes the exact path (scipy and the general checks) alone;
inputs not in SDC form always do. The supervisor owns the warm starts, the last valid gains and the
counters: a finger whose step fails any check uses its last valid gains (fallback), or a nominal
model's before it has any, or zero torque, and ``u`` is always finite. docs/design/fast_riccati.md
has the derivations.
"""
from __future__ import annotations

import math

import numpy as np

from soft_gripper_sdre.control.kernel import (SDC_TOP_ROWS, checks_passed, every_check_passed,
                                              full_sdc_matrices, kernel_constants, structured_gains,
                                              upper_triangle)
from soft_gripper_sdre.control.riccati import (Check, care, checked_gains, checked_weights, riccati_cost,
                                               sdre_gains, solvability)
from soft_gripper_sdre.control.tracking import LawStep

METHODS = ('fast', 'reference')
_CHECK_BITS = tuple((c.name, int(c)) for c in Check)


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a``, made read-only (for arrays that several results share)."""
    a.flags.writeable = False
    return a


def _checked(**arrays) -> list[np.ndarray]:
    """Each ``name=(value, shape)`` as a float array, in order; ValueError naming the first of another shape."""
    out = []
    for name, (value, shape) in arrays.items():
        arr = np.asarray(value, dtype=float)
        if arr.shape != shape:
            raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
        out.append(arr)
    return out


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
        max_nk_iterations: most Newton–Kleinman iterations per step before the exact path.
        nominal: optional (A0, G0) whose gains serve as the fallback before any valid step.

    Counters: ``steps``, ``fallbacks`` (finger-steps), ``exact_solves``, ``check_failures`` (per :class:`Check`).
    """

    def __init__(self, Q, R, u_max, n: int = 4, method: str = 'fast', residual_tol: float = 1e-6,
                 cond_max: float = 1e8, max_nk_iterations: int = 5, nominal=None) -> None:
        self.Q, self.R, self.u_max = checked_weights(Q, R, u_max)
        if method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {method!r}')
        self.n, self.method = int(n), method
        self.residual_tol, self.cond_max = float(residual_tol), float(cond_max)
        if int(max_nk_iterations) < 1:
            raise ValueError(f'max_nk_iterations must be >= 1, got {max_nk_iterations!r}')
        self._cost = riccati_cost(self.Q, self.R)
        #: the fast kernel's constants (public for benchmarks that time the kernel alone)
        self.kernel_constants = kernel_constants(self.Q, self.R, self.n, self.residual_tol, self.cond_max,
                                                 int(max_nk_iterations))
        # (n, 2) bounds: np.minimum / np.maximum between arrays of one shape skip broadcasting
        self._u_max_n = np.ascontiguousarray(np.broadcast_to(self.u_max, (self.n, 2)))
        self._u_min_n = np.ascontiguousarray(np.broadcast_to(-self.u_max, (self.n, 2)))
        # the kernel's detectability argument needs Q ≻ 0 or Q's position block ≻ 0
        self._fast_ok = method == 'fast' and (self._cost.q_definite or self._cost.q_position_definite)
        self._nominal = None
        if nominal is not None:
            K0, Ks0, _ = sdre_gains(np.asarray(nominal[0], float), np.asarray(nominal[1], float), self.Q, self.R)
            self._nominal = (K0, Ks0)
        # the flags of a step where every check passed, and nk_iterations per count: read-only,
        # shared by every such step (fresh arrays cost more than the rest of the bookkeeping)
        self._passed = tuple(_frozen(np.full(self.n, v, dtype=t)) for v, t in ((True, bool), (False, bool), (0, int)))
        self._iterations = [_frozen(np.full(self.n, k)) for k in range(int(max_nk_iterations) + 1)]
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
        self.steps = self.fallbacks = self.exact_solves = 0
        self.check_failures = {c.name: 0 for c in Check}

    def warm_start(self, P) -> None:
        """Start every finger's next fast step from P (n, 4, 4) instead of its last solution (the
        kernel's checks still decide whether the result is used)."""
        self._p = upper_triangle(_checked(P=(P, (self.n, 4, 4)))[0])
        self._warm = np.ones(self.n, dtype=bool)
        self._all_warm = True

    def step(self, A, G, x, x_d) -> LawStep:
        """Torques for every finger: A (n,4,4), G (n,4,2), x (n,4), x_d (n,4), translated SI."""
        n = self.n
        A, G, x, x_d = _checked(A=(A, (n, 4, 4)), G=(G, (n, 4, 2)), x=(x, (n, 4)), x_d=(x_d, (n, 4)))
        sdc = self.method == 'fast' and bool((A[:, :2, :] == SDC_TOP_ROWS).all()) and not G[:, :2, :].any()
        return self._step(A[:, 2:, :] if sdc else None, G[:, 2:, :] if sdc else None, A, G, x, x_d)

    def step_sdc(self, A2, G2, x, x_d) -> LawStep:
        """:meth:`step` for a model in SDC form, given only its lower rows:
        A2 = [A21 A22] (n,2,4) and G2 (n,2,2), so that A = [[0, I], A2] and G = [[0], G2]."""
        n = self.n
        A2, G2 = np.asarray(A2, dtype=float), np.asarray(G2, dtype=float)
        x, x_d = np.asarray(x, dtype=float), np.asarray(x_d, dtype=float)
        if (A2.shape, G2.shape, x.shape, x_d.shape) != ((n, 2, 4), (n, 2, 2), (n, 4), (n, 4)):
            _checked(A2=(A2, (n, 2, 4)), G2=(G2, (n, 2, 2)), x=(x, (n, 4)), x_d=(x_d, (n, 4)))  # raises
        if self.method != 'fast':
            return self._step(None, None, *full_sdc_matrices(A2, G2), x, x_d)
        return self._step(A2, G2, None, None, x, x_d)

    def _step(self, a, g, A, G, x, x_d) -> LawStep:
        """One step; ``a``, ``g`` are the SDC lower rows (None: not in SDC form), A, G the full
        matrices (None: built from a, g if the exact path needs them)."""
        self.steps += 1
        fast, idx = None, None
        if a is not None and self._fast_ok and self._all_warm:
            fast = structured_gains(a, g, self._p, self.kernel_constants)
            if every_check_passed(fast, self.kernel_constants):
                # the common path: every finger warm and every kernel check passed
                u_unsat = np.matvec(fast.gains, np.concatenate((x, x_d), axis=1))   # eq. 22: K x + K_s x_d
                # Σ u² is finite iff every u is (or it overflows beyond 1e154: then the careful path)
                if math.isfinite(np.vdot(u_unsat, u_unsat)):
                    # the gains are read-only and shared with the result: _careful_step rebinds
                    # self._K, self._Ks instead of writing into them (warm ⇒ have: unchanged)
                    gains = _frozen(fast.gains)
                    self._p, self._K, self._Ks = fast.p, gains[:, :, :4], gains[:, :, 4:]
                    u = np.minimum(np.maximum(u_unsat, self._u_min_n), self._u_max_n)    # = np.clip, cheaper
                    ok, fallback, failed = self._passed
                    return LawStep(u=u, u_unsat=u_unsat, K=self._K, Ks=self._Ks, P=fast.P,
                                   residual=fast.residual, ok=ok, fallback=fallback, failed_checks=failed,
                                   saturated=u != u_unsat,          # = |u_unsat| > u_max here
                                   nk_iterations=self._iterations[fast.iterations])
        elif a is not None and self._fast_ok and self._warm.any():
            idx = np.flatnonzero(self._warm)
            fast = structured_gains(a[idx], g[idx], self._p[idx], self.kernel_constants)
        if A is None:
            A, G = full_sdc_matrices(a, g)
        return self._careful_step(A, G, x, x_d, a is not None, fast, idx)

    def _solve(self, A, G, usable, fast, idx) -> tuple[np.ndarray, np.ndarray]:
        """P for every usable finger: the kernel's where it passed its checks, else scipy's."""
        P = np.full((self.n, 4, 4), np.nan)
        iterations = np.zeros(self.n, dtype=int)
        done = np.zeros(self.n, dtype=bool)
        if fast is not None:
            rows = np.arange(self.n) if idx is None else idx
            take = checks_passed(fast, self.kernel_constants) & usable[rows]
            P[rows[take]] = fast.P[take]
            iterations[rows[take]] = fast.iterations
            done[rows[take]] = True
        for i in np.flatnonzero(usable & ~done):
            self.exact_solves += 1
            try:
                P[i] = care(A[i], G[i], self.Q, self.R)
            except (np.linalg.LinAlgError, ValueError):
                pass                                     # stays NaN: SOLVE_FAILED
        return P, iterations

    def _careful_step(self, A, G, x, x_d, sdc: bool, fast, idx) -> LawStep:
        """The law with every check in its general form and the fallbacks, finger by finger."""
        finite = (np.all(np.isfinite(A), axis=(1, 2)) & np.all(np.isfinite(G), axis=(1, 2))
                  & np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(x_d), axis=1))
        A = np.where(finite[:, None, None], A, 0.0)
        G = np.where(finite[:, None, None], G, 0.0)
        usable, failed = solvability(A, G, finite, sdc, self._cost, self.cond_max)   # Remark 3
        failed[~finite] |= Check.NONFINITE
        P, iterations = self._solve(A, G, usable, fast, idx)
        checked = checked_gains(A, G, P, usable, failed, self._cost, self.residual_tol, self.cond_max)
        ok = checked.ok

        # accept or fall back; new arrays, not writes into the old ones: the fast path shares its
        # gains with the step it returned
        self._K = np.where(ok[:, None, None], checked.K, self._K)
        self._Ks = np.where(ok[:, None, None], checked.Ks, self._Ks)
        self._have |= ok
        self._p[ok] = upper_triangle(P[ok])
        self._warm = ok.copy()           # no warm start from a rejected solve
        self._all_warm = bool(ok.all())
        fallback = ~ok
        use_zero = fallback & ~self._have & (self._nominal is None)
        K, Ks = self._K.copy(), self._Ks.copy()
        K[use_zero] = 0.0
        Ks[use_zero] = 0.0
        xs = np.where(finite[:, None], x, 0.0)
        xds = np.where(finite[:, None], x_d, 0.0)
        u_unsat = np.einsum('nij,nj->ni', K, xs) + np.einsum('nij,nj->ni', Ks, xds)   # eq. 22
        u_unsat = np.where(np.isfinite(u_unsat), u_unsat, 0.0)
        u_unsat[~finite] = 0.0            # no torque from a state we cannot read
        u = np.clip(u_unsat, -self.u_max, self.u_max)

        self.fallbacks += int(fallback.sum())
        if failed.any():
            for name, bit in _CHECK_BITS:
                self.check_failures[name] += int(np.count_nonzero(failed & bit))
        return LawStep(u=u, u_unsat=u_unsat, K=K, Ks=Ks, P=P, residual=checked.residual, ok=ok,
                       fallback=fallback, failed_checks=failed, saturated=np.abs(u_unsat) > self.u_max,
                       nk_iterations=iterations)
