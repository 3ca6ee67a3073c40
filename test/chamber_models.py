"""Small SDC models of fingers unlike the hand and their data facts, for the derived-settings
tests (shared; no test imports another): a one-chamber finger with a planar tip and a
three-tendon segment with a 3-D tip."""
import numpy as np

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.sim.shape import InputBounds

P_MAX = 6e4                                     # the chamber's pressure range [Pa]
T_MAX = 4.0                                     # the tendons' tension range [N]


class OneChamber:
    """d = 2, m = 1: ẍ = −k_i (1 + (p_i/a_i)²) p_i − c v + g u, springs hardening at different
    lengths along X and Y, so the equilibria under a constant pressure lie on a curve."""

    rest_tip = np.array([0.0, 0.06, 0.0])
    k, a, c = (900.0, 1600.0), (3e-3, 8e-3), 12.0
    g = (1.5e-4, 1.0e-4)                        # [m/s² per Pa]

    def AG(self, x):
        x = np.atleast_2d(x)
        if x.shape[1] != 4:
            raise ValueError('a planar finger')
        n = len(x)
        A = np.zeros((n, 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0
        for i in range(2):
            A[:, 2 + i, i] = -self.k[i] * (1 + (x[:, i] / self.a[i]) ** 2)
            A[:, 2 + i, 2 + i] = -self.c
        G = np.zeros((n, 4, 1))
        G[:, 2, 0], G[:, 3, 0] = self.g
        return A, G

    def statics(self, p: np.ndarray, u: float) -> np.ndarray:
        """k(p) p − g u at rest: zero on an equilibrium [m/s²]."""
        return np.array([self.k[i] * (1 + (p[i] / self.a[i]) ** 2) * p[i] - self.g[i] * u
                         for i in range(2)])


class ThreeTendons:
    """d = 3, m = 3: ẍ = −k p − c v + G₂ u, tendon i pulling the tip toward its angle 120° apart
    and shortening the segment (−Z)."""

    rest_tip = np.array([0.0, 0.0, 0.1])
    k, c = 1200.0, 15.0

    def __init__(self) -> None:
        ang = np.deg2rad([90.0, 210.0, 330.0])
        self.g2 = 0.8 * np.stack([np.cos(ang), np.sin(ang), -0.4 * np.ones(3)])   # [m/s² per N]

    def AG(self, x):
        x = np.atleast_2d(x)
        if x.shape[1] != 6:
            raise ValueError('a 3-D finger')
        n = len(x)
        A = np.zeros((n, 6, 6))
        A[:, :3, 3:] = np.eye(3)
        A[:, 3:, :3] = -self.k * np.eye(3)
        A[:, 3:, 3:] = -self.c * np.eye(3)
        G = np.zeros((n, 6, 3))
        G[:, 3:, :] = self.g2
        return A, G


def _chamber_facts(travel=6e-3, **kw) -> ls.DataFacts:
    return ls.DataFacts(period=0.01, noise_std=2e-5, travel=travel, torque_limit=P_MAX,
                        accel_psd_ml=1.0, direction=kw.pop('direction', 60.0),
                        bounds=InputBounds([0.0], [P_MAX]), **kw)


def _tendon_facts(model) -> ls.DataFacts:
    axis = model.g2[:, 0] / np.linalg.norm(model.g2[:, 0])       # tendon 0 alone, held still
    return ls.DataFacts(period=0.01, noise_std=2e-5, travel=3e-3, torque_limit=T_MAX,
                        accel_psd_ml=10.0, axis=tuple(axis),
                        bounds=InputBounds(np.zeros(3), np.full(3, T_MAX)))


#: a shorter check move than the derivation's (2.2 s instead of 5.5 s) for tests of the search
SHORT_PROFILE = dict(t_start=0.3, t_close=0.8, t_hold=0.3, t_open=0.8)


def held_inputs(n: int, high: float, seed: int = 0, start: int = 0) -> np.ndarray:
    """(n, 1) inputs held for 5 to 30 samples each, uniform in [0, ``high``], 0 before sample
    ``start``: a chamber's pressures as an excitation plays them."""
    rng = np.random.default_rng(seed)
    u = np.zeros((n, 1))
    k = start
    while k < n:
        hold = int(rng.integers(5, 31))
        u[k:k + hold] = rng.uniform(0.0, high)
        k += hold
    return u
