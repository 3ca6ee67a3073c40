"""Linear algebra on stacks of small matrices that reports a failure as NaN instead of raising.

The reference path's checks and the feedforward law's model inversion work on 2×2 matrices of all
fingers at once. A finger whose matrix is singular must not stop the others, so every function
here works on a stack and marks a failed matrix with NaN or False (which the callers' checks then
reject). docs/design/compiled_kernel.md ("The batched 2×2 solve") says why the solve goes through
numpy's gufunc directly.
"""
from __future__ import annotations

import numpy as np

#: for a 2×2 M flattened to f = [m00, m01, m10, m11]: f[_LEFT] ∘ f[_RIGHT] =
#: [m00², m01², m10², m11², m00 m11, m01 m10, m10 m01, m11 m00], which @ _FROBENIUS2_AND_DET sums
#: to (‖M‖_F², det M)
_LEFT = np.array([0, 1, 2, 3, 0, 1, 2, 3])
_RIGHT = np.array([0, 1, 2, 3, 3, 2, 1, 0])
_FROBENIUS2_AND_DET = np.array([[1.0, 0.0]] * 4
                               + [[0.0, 0.5], [0.0, -0.5], [0.0, -0.5], [0.0, 0.5]])


def well_conditioned_2x2(M: np.ndarray, cond_max: float) -> tuple[np.ndarray, np.ndarray]:
    """For a stack of 2×2 matrices: (cond₂(M) < cond_max, det M), in closed form (no SVD).

    Uses ‖M‖_F² < (cond_max + 1/cond_max) |det M| (the design note derives it). A singular or
    non-finite M gives False. Call inside ``np.errstate(invalid='ignore')`` when M may hold NaN.
    """
    f = M.reshape(-1, 4)                                                    # [m00, m01, m10, m11]
    fro2_det = (f.take(_LEFT, axis=1)
                * f.take(_RIGHT, axis=1)) @ _FROBENIUS2_AND_DET  # [‖M‖_F², det M]
    det = fro2_det[:, 1]
    return fro2_det[:, 0] < (cond_max + 1.0 / cond_max) * np.abs(det), det


def portable_batched_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:data:`batched_solve` through numpy's public ``np.linalg.solve`` (the fallback)."""
    try:
        return np.linalg.solve(L, b[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        out = np.full(b.shape, np.nan)
        for i in range(b.shape[0]):
            try:
                out[i] = np.linalg.solve(L[i], b[i])
            except np.linalg.LinAlgError:
                pass
        return out


def _gufunc_or_portable():
    """numpy's private gufunc ``solve1`` when it answers as the public function on a small example
    (a regular and a singular matrix), else :func:`portable_batched_solve`."""
    try:
        from numpy.linalg import _umath_linalg as gufuncs
        solve = gufuncs.solve1
        L = np.array([[[4.0, 1.0], [1.0, 3.0]], [[1.0, 2.0], [2.0, 4.0]]])     # regular; singular
        b = np.array([[1.0, 2.0], [1.0, 1.0]])
        with np.errstate(all='ignore'):
            x = solve(L, b)
        if not (np.allclose(x[0], np.linalg.solve(L[0], b[0])) and np.isnan(x[1]).all()):
            raise ValueError('numpy.linalg._umath_linalg answers differently')
        return solve
    except (ImportError, AttributeError, TypeError, ValueError):
        return portable_batched_solve


#: ``batched_solve(L (m,k,k), b (m,k)) -> x (m,k)`` with L x = b per matrix, NaN where L is
#: singular.
#: It may warn about invalid values: call it inside ``np.errstate(invalid='ignore')``.
batched_solve = _gufunc_or_portable()
