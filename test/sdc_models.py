"""Small SDC models with known structure for the law tests (shared; no test imports another)."""
import numpy as np

#: rest tip of the test models [m]
REST = np.array([0.01, -0.02, 0.3])


class StiffeningModel:
    """A state-dependent SDC model (AG only): ẍ = −k(1 + (p/p₀)²) p − c v + G₂(p) u, G₂ rotating
    with p."""

    rest_tip = REST

    def AG(self, x):
        x = np.atleast_2d(x)
        n = len(x)
        A = np.zeros((n, 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0
        s = 1.0 + (x[:, :2] / 5e-3) ** 2
        A[:, 2, 0], A[:, 3, 1] = -300.0 * s[:, 0], -900.0 * s[:, 1]
        A[:, 2, 2] = A[:, 3, 3] = -2.0
        th = 20.0 * x[:, 1]
        G = np.zeros((n, 4, 2))
        G[:, 2, 0], G[:, 2, 1] = 10.0 * np.cos(th), 600.0 + 50.0 * np.sin(th)
        G[:, 3, 0], G[:, 3, 1] = -600.0, 5.0 + 100.0 * x[:, 0]
        return A, G
