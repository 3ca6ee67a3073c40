"""A simulated linear spring–damper finger for the excitation tests (shared; no test imports
another)."""
import numpy as np

REST = np.array([0.0, -0.0105, 0.1076])
RATE = 200.0                      # the driver's rate [Hz]
NOISE = 5e-5                      # tip noise σ [m]


class SpringDamper:
    """A 2-D linear finger: ẍ = −K x − C ẋ + B u, measured at ``RATE`` with Gaussian noise;
    ``gain`` scales B (amplitude 1 of the built-in signals swings it about 100 mm at gain 1)."""

    def __init__(self, gain: float = 1.0, seed: int = 0) -> None:
        w = 2 * np.pi * np.array([3.0, 4.0])
        self.K, self.C = np.diag(w ** 2), np.diag(2 * 0.3 * w)
        self.B = gain * np.array([[400.0, 150.0], [-100.0, 500.0]])
        self.x, self.v = np.zeros(2), np.zeros(2)
        self.rng = np.random.default_rng(seed)

    def tips(self) -> np.ndarray:
        tip = REST.copy()
        tip[:2] += self.x + self.rng.normal(0.0, NOISE, 2)
        return tip[None, :]

    def step(self, u: np.ndarray, substeps: int = 20) -> None:
        h = 1.0 / RATE / substeps
        for _ in range(substeps):
            self.v += h * (-self.K @ self.x - self.C @ self.v + self.B @ u)
            self.x += h * self.v
