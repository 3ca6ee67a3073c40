"""A three-tendon continuum segment ("trunk") with a 3-D tip: three pull-only tendons, three tip
coordinates. Plain floats, no PyBullet, no ROS.

**Frame.** The segment hangs from its base like a gripper finger: X points down along the
unbent backbone (gravity is +X), Y horizontally toward the palm's centre (the closing
direction), Z = X × Y. The tip p = (x, y, z) is given in this base frame [m].

**Kinematics: constant curvature.** The backbone is an arc of length L leaving the base along
+X and bending by the angle θ toward the direction φ in the (Y, Z) plane. Its configuration is
q = (β_y, β_z, L) with the bending vector β = θ (cos φ, sin φ) (smooth through the straight
segment). The tip is

    x = L sin θ / θ,     (y, z) = L (1 − cos θ) / θ² · β,

and from the tip back (x > 0), with ρ = |(y, z)|, s = |p|² and θ = 2 atan2(ρ, x):

    β = g (y, z),   L = g s / 2,   g = θ / ρ  (→ 2 / x as ρ → 0).

Its Jacobian J = ∂q/∂p is written out with g_x = −2/s and h = (∂g/∂ρ)/ρ = (2x/s − g)/ρ² (a
series in ρ/x near the straight segment). Tendon i runs at the distance r from the backbone at
the angle αᵢ (from +Y toward +Z); its length is ℓᵢ = L − r (β_y cos αᵢ + β_z sin αᵢ), linear in
q, so its tension Tᵢ ≥ 0 acts on q through the constant matrix B (3 × 3):

    Q_T = B T,   column i = (r cos αᵢ, r sin αᵢ, −1):

a tendon bends the segment toward its side and compresses the backbone; three tendons at 120°
reach the two bending directions and the axial compression (B is regular).

**Dynamics: the mass lumped at the tip.** The backbone is massless; the tip carries the mass m
(the end cap and the share of the segment's mass that moves with it), so in the tip's
coordinates the mass matrix is m I, without Coriolis terms:

    m p̈ = m g e_x + Jᵀ Q,
    Q = −K (q − q₀) − C q̇ − σ ∘ z + B T,     q̇ = J ṗ,     T = clip(T, 0, T_max),

with K = diag(k_b, k_b, k_a) the backbone's bending and axial stiffness about the straight,
unloaded q₀ = (0, 0, L₀), C = diag(c_b, c_b, c_a) its damping, and the Dahl friction of
:mod:`soft_gripper_sdre.sim.plants.chain` on each configuration coordinate (the tendons in their
guides): ż = q̇ − v(q̇) σ z / F_c, v(q̇) = v_s tanh(|q̇| / v_s), per coordinate. The energy

    E = ½ m |ṗ|² − m g x + ½ k_b |β|² + ½ k_a (L − L₀)² + Σ ½ σⱼ zⱼ²

obeys dE/dt = Tᵀ Bᵀ q̇ − q̇ᵀ C q̇ − Σ σⱼ² zⱼ² v(q̇ⱼ) / F_cⱼ: it only falls without tension. The
state (p, ṗ, z) is integrated by fixed-step RK4 of at most ``substep``.

**The presets** (:data:`TRUNKS`), measured on :class:`TrunkPlant`: the rest tip, the natural
frequencies and the first modal damping ratio of the frictionless segment linearised at rest
(two bending modes, then the axial one), and the static tip displacement per newton on each
tendon (the columns' norms; frictionless, at rest, :meth:`TrunkPlant.static_gain`, whose 3 × 3
has full rank):

=========  =============  ================  =====  ============  =====  ================
preset     rest tip [mm]  modes [Hz]        ζ₁     mm per N      T_max  σ_min/σ_max gain
=========  =============  ================  =====  ============  =====  ================
trunk3_a   (120.5, 0, 0)  5.1, 5.1, 22.5    0.10   6.7 (each)    4 N    0.36
trunk3_b   (120.7, 0, 0)  4.4, 4.4, 18.4    0.09   4.6 (each)    4 N    0.40
=========  =============  ================  =====  ============  =====  ================

* ``trunk3_a``: a 120 mm backbone, tendons at 12 mm and 0°/120°/240° (tendon 0 on the palm's
  side, +Y), a 30 g tip; k_b = 0.10 N·m/rad, k_a = 600 N/m; Dahl friction 2 mN·m in bending and
  50 mN axially, presliding ranges 5 mrad and 0.2 mm; tension 0 to 4 N; RK4 steps of 0.25 ms.
  Meant to be served at 200 to 500 Hz.
* ``trunk3_b``: the same backbone with a 60 g tip, stiffer (k_b = 0.14 N·m/rad, k_a = 800 N/m).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Callable

import numpy as np

from soft_gripper_sdre.sim.plants.chain_params import GRAVITY
from soft_gripper_sdre.sim.plants.dynamics import rk4
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

#: below this ρ/x the tip's inverse kinematics use their series about the straight segment
_SERIES_BELOW = 1e-2


@dataclass(frozen=True)
class TrunkParams:
    """A three-tendon constant-curvature segment (module doc); SI units. Per-coordinate pairs
    are (bending, axial)."""

    name: str
    length: float                            # m, L₀: the unloaded backbone
    radius: float                            # m, r: the tendons' distance from the backbone
    tendon_angles: tuple[float, float, float]   # rad, αᵢ from +Y toward +Z
    tip_mass: float                          # kg, m
    bending_stiffness: float                 # N·m/rad, k_b
    axial_stiffness: float                   # N/m, k_a
    bending_damping: float                   # N·m·s/rad, c_b
    axial_damping: float                     # N·s/m, c_a
    coulomb: tuple[float, float]             # (N·m, N), F_c (0 = no friction)
    presliding: tuple[float, float]          # (N·m/rad, N/m), σ, the bristle stiffness
    friction_speed: tuple[float, float]      # (rad/s, m/s), v_s
    tension_limit: float                     # N, T_max: each tension is clipped to [0, T_max]
    substep: float                           # s, the RK4 step
    gravity: float = GRAVITY                 # m/s², along +X

    def __post_init__(self) -> None:
        positive = ('length', 'radius', 'tip_mass', 'bending_stiffness', 'axial_stiffness',
                    'tension_limit', 'substep')
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f'{self.name}: {name} must be finite and > 0, got {value!r}')
        if min(self.bending_damping, self.axial_damping) < 0:
            raise ValueError(f'{self.name}: damping must be >= 0')
        if len(self.tendon_angles) != 3:
            raise ValueError(f'{self.name}: tendon_angles must hold three angles')
        if any(len(getattr(self, k)) != 2 for k in ('coulomb', 'presliding', 'friction_speed')):
            raise ValueError(f'{self.name}: coulomb, presliding and friction_speed are '
                             '(bending, axial) pairs')
        if any(f < 0 or s < 0 or (f > 0) != (s > 0) for f, s in zip(self.coulomb, self.presliding)):
            raise ValueError(f'{self.name}: coulomb and presliding must both be positive '
                             '(friction) or both zero (none) per coordinate')
        if min(self.friction_speed) <= 0:
            raise ValueError(f'{self.name}: friction_speed must be positive')
        rate = max(v * s / f if f else 0.0
                   for v, s, f in zip(self.friction_speed, self.presliding, self.coulomb))
        if rate * self.substep > 1.5:
            raise ValueError(f'{self.name}: the bristles relax at up to {rate:.0f}/s, too fast '
                             f'for RK4 steps of {self.substep} s (keep the product <= 1.5)')
        if abs(np.linalg.det(_actuation(self))) < 1e-9 * self.radius ** 2:
            raise ValueError(f'{self.name}: the tendon angles do not reach both bending '
                             'directions and the axis (B is singular)')

    @property
    def shape(self) -> FingerShape:
        """A 3-D tip and three inputs."""
        return FingerShape(3, 3)

    @property
    def bounds(self) -> InputBounds:
        """Each tendon's tension [N] in [0, T_max]: pull only."""
        return InputBounds(np.zeros(3), np.full(3, self.tension_limit))


def _actuation(p: TrunkParams) -> np.ndarray:
    """B (3, 3): column i is tendon i's generalized force per newton, (r cos αᵢ, r sin αᵢ, −1)."""
    a = np.asarray(p.tendon_angles, dtype=float)
    return np.array([p.radius * np.cos(a), p.radius * np.sin(a), -np.ones(3)])


def tip_of(q) -> np.ndarray:
    """The tip (x, y, z) [m] of the configuration q = (β_y, β_z, L) (module doc)."""
    by, bz, length = (float(v) for v in q)
    t2 = by * by + bz * bz
    if t2 < 1e-8:           # series of sin θ / θ and (1 − cos θ) / θ²
        axial = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        lateral = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        t = math.sqrt(t2)
        axial, lateral = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    return np.array([length * axial, length * lateral * by, length * lateral * bz])


def _inverse(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """(g, h, g_x, s) at the tip (x, y, z): g = θ/ρ, h = (∂g/∂ρ)/ρ, g_x = ∂g/∂x, s = |p|²."""
    r2 = y * y + z * z
    s = x * x + r2
    if x > 0 and r2 < (_SERIES_BELOW * x) ** 2:
        u2 = r2 / (x * x)
        g = 2.0 / x * (1.0 - u2 / 3.0 + u2 * u2 / 5.0 - u2 * u2 * u2 / 7.0)
        h = (-4.0 / 3.0 + 1.6 * u2 - 12.0 / 7.0 * u2 * u2 + 16.0 / 9.0 * u2 * u2 * u2) / x ** 3
    else:
        rho = math.sqrt(r2)
        g = 2.0 * math.atan2(rho, x) / rho
        h = (2.0 * x / s - g) / r2
    return g, h, -2.0 / s, s


def configuration(p) -> np.ndarray:
    """q = (β_y, β_z, L) of the tip ``p`` (x > 0) (module doc)."""
    x, y, z = (float(v) for v in p)
    g, _, _, s = _inverse(x, y, z)
    return np.array([g * y, g * z, 0.5 * g * s])


def configuration_jacobian(p) -> np.ndarray:
    """J = ∂q/∂p (3, 3) at the tip ``p`` (module doc)."""
    x, y, z = (float(v) for v in p)
    g, h, gx, s = _inverse(x, y, z)
    return np.array([[gx * y, g + h * y * y, h * y * z],
                     [gx * z, h * y * z, g + h * z * z],
                     [0.5 * gx * s + g * x, 0.5 * h * y * s + g * y, 0.5 * h * z * s + g * z]])


class TrunkDynamics:
    """The state derivative of the segment ``params`` describes, on Python floats:
    ``derivative(x, q_in)`` with x = [p, ṗ, z] (9) and q_in = B T (3) → ẋ."""

    def __init__(self, params: TrunkParams) -> None:
        p = params
        self._m_inv = 1.0 / p.tip_mass
        self._g = p.gravity
        self._kb, self._ka, self._l0 = p.bending_stiffness, p.axial_stiffness, p.length
        self._cb, self._ca = p.bending_damping, p.axial_damping
        self._sb, self._sa = p.presliding
        (vb, va), (fb, fa) = p.friction_speed, p.coulomb
        self._vb, self._va = vb, va
        self._rb = self._sb / fb if fb > 0 else 0.0       # σ/F_c
        self._ra = self._sa / fa if fa > 0 else 0.0

    def derivative(self, x: list[float], q_in: list[float]) -> list[float]:
        px, py, pz, vx, vy, vz, z0, z1, z2 = x
        g, h, gx, s = _inverse(px, py, pz)
        hyz = h * py * pz
        j00, j01, j02 = gx * py, g + h * py * py, hyz
        j10, j11, j12 = gx * pz, hyz, g + h * pz * pz
        j20, j21, j22 = 0.5 * gx * s + g * px, 0.5 * h * py * s + g * py, 0.5 * h * pz * s + g * pz
        qd0 = j00 * vx + j01 * vy + j02 * vz
        qd1 = j10 * vx + j11 * vy + j12 * vz
        qd2 = j20 * vx + j21 * vy + j22 * vz
        f0 = q_in[0] - self._kb * g * py - self._cb * qd0 - self._sb * z0
        f1 = q_in[1] - self._kb * g * pz - self._cb * qd1 - self._sb * z1
        f2 = q_in[2] - self._ka * (0.5 * g * s - self._l0) - self._ca * qd2 - self._sa * z2
        mi = self._m_inv
        ax = self._g + mi * (j00 * f0 + j10 * f1 + j20 * f2)
        ay = mi * (j01 * f0 + j11 * f1 + j21 * f2)
        az = mi * (j02 * f0 + j12 * f1 + j22 * f2)
        vb, va, rb, ra = self._vb, self._va, self._rb, self._ra
        zd0 = qd0 - vb * math.tanh(abs(qd0) / vb) * rb * z0 if rb else 0.0
        zd1 = qd1 - vb * math.tanh(abs(qd1) / vb) * rb * z1 if rb else 0.0
        zd2 = qd2 - va * math.tanh(abs(qd2) / va) * ra * z2 if ra else 0.0
        return [vx, vy, vz, ax, ay, az, zd0, zd1, zd2]


@dataclass
class TrunkState:
    """Tip position p [m], velocity ṗ [m/s], Dahl bristle deflections z (rad, rad, m), time t."""

    p: np.ndarray
    v: np.ndarray
    z: np.ndarray
    t: float = 0.0

    def copy(self) -> 'TrunkState':
        return TrunkState(self.p.copy(), self.v.copy(), self.z.copy(), self.t)


class TrunkPlant:
    """One three-tendon segment (module doc), stepped in real or simulated time, with the
    interface of :class:`~soft_gripper_sdre.sim.plants.chain.FingerPlant`: ``reset()``,
    ``step(T, dt)`` with the tensions T (3,) [N], ``tip()`` (3,) [m], ``rest_tip``, ``shape``
    (d = 3, m = 3), ``bounds`` ([0, T_max] each)."""

    def __init__(self, params: TrunkParams) -> None:
        self.params = p = params
        self.dynamics = TrunkDynamics(p)
        self.derivative = self.dynamics.derivative
        self.shape = p.shape
        self.bounds = p.bounds
        self.m = 3
        self._b = _actuation(p)
        self.state = TrunkState(np.zeros(3), np.zeros(3), np.zeros(3))
        self.rest_tip = self.equilibrium()
        self.reset()

    def tip(self) -> np.ndarray:
        """The tip (x, y, z) [m] now."""
        return self.state.p.copy()

    def reset(self) -> None:
        """At rest: slack tendons, the static equilibrium under gravity, no bristle load, t = 0."""
        self.state = TrunkState(self.rest_tip.copy(), np.zeros(3), np.zeros(3))

    # -- statics and linearisation ---------------------------------------------------------
    def _force(self, p: np.ndarray, q_in: np.ndarray) -> np.ndarray:
        """The tip's acceleration at rest (ṗ = 0, z = 0) at ``p`` with the input ``q_in``."""
        x = list(map(float, p)) + [0.0] * 6
        return np.array(self.derivative(x, list(map(float, q_in)))[3:6])

    def _stiffness(self, p: np.ndarray, q_in: np.ndarray) -> np.ndarray:
        """−∂p̈/∂p (3, 3) [1/s²] at rest at ``p``, by central differences."""
        step = 1e-7
        cols = [(self._force(p - step * e, q_in) - self._force(p + step * e, q_in)) / (2 * step)
                for e in np.eye(3)]
        return np.array(cols).T

    def equilibrium(self, tension=None) -> np.ndarray:
        """The tip where gravity, the backbone and the held tensions (3,) [N] (default: slack)
        balance, without friction: Newton's method from the straight, unloaded segment.

        Raises:
            RuntimeError: Newton's method did not converge.
        """
        t = self.bounds.rest if tension is None else self.bounds.clip(np.asarray(tension, float))
        q_in = self._b @ t
        p = np.array([self.params.length, 0.0, 0.0])
        for _ in range(100):
            step = np.linalg.solve(self._stiffness(p, q_in), self._force(p, q_in))
            p = p + step
            if np.max(np.abs(step)) < 1e-15:
                break
        if not np.max(np.abs(self._force(p, q_in))) < 1e-9:
            raise RuntimeError(f'{self.params.name}: no equilibrium found for T = {t}')
        return p

    def modes(self) -> tuple[np.ndarray, np.ndarray]:
        """(natural frequencies [Hz], modal damping ratios) of the frictionless segment
        linearised at rest, slowest first: ω² and φ from K_p φ = ω² φ (K_p = −∂p̈/∂p), ζ =
        φᵀ Jᵀ C J φ / (2 ω m φᵀ φ)."""
        k = self._stiffness(self.rest_tip, np.zeros(3))
        omega2, phi = np.linalg.eig(k)
        order = np.argsort(omega2.real)
        omega = np.sqrt(omega2.real[order])
        phi = phi.real[:, order]
        j = configuration_jacobian(self.rest_tip)
        c = np.diag([self.params.bending_damping] * 2 + [self.params.axial_damping])
        cp = j.T @ c @ j
        zeta = (np.einsum('ij,ik,kj->j', phi, cp, phi)
                / (2 * omega * self.params.tip_mass * np.einsum('ij,ij->j', phi, phi)))
        return omega / (2 * np.pi), zeta

    def natural_frequencies(self) -> np.ndarray:
        """Undamped natural frequencies [Hz] at rest, ascending."""
        return self.modes()[0]

    def static_gain(self) -> np.ndarray:
        """∂tip/∂T (3, 3) [m/N] at rest, frictionless: K_p⁻¹ Jᵀ B / m; column i is tendon
        i's."""
        k = self._stiffness(self.rest_tip, np.zeros(3))
        j = configuration_jacobian(self.rest_tip)
        return np.linalg.solve(k, j.T @ self._b) / self.params.tip_mass

    def energy(self) -> float:
        """E [J] of the module doc, zero-referenced at the base with the unloaded backbone."""
        p, st = self.params, self.state
        by, bz, length = configuration(st.p)
        return float(0.5 * p.tip_mass * st.v @ st.v - p.tip_mass * p.gravity * st.p[0]
                     + 0.5 * p.bending_stiffness * (by * by + bz * bz)
                     + 0.5 * p.axial_stiffness * (length - p.length) ** 2
                     + 0.5 * (p.presliding[0] * (st.z[0] ** 2 + st.z[1] ** 2)
                              + p.presliding[1] * st.z[2] ** 2))

    # -- stepping --------------------------------------------------------------------------
    def step(self, tension, dt: float) -> None:
        """Advance ``dt`` [s] with the tensions (3,) [N] held (clipped to [0, T_max]), in RK4
        steps of at most ``substep``.

        Raises:
            ValueError: not three finite tensions, or ``dt`` negative or not finite.
        """
        tension = np.asarray(tension, dtype=float)
        if tension.shape != (3,) or not np.all(np.isfinite(tension)):
            raise ValueError(f'the tensions must be three finite numbers [N], got {tension!r}')
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f'dt must be a finite duration >= 0 s, got {dt!r}')
        if dt == 0:
            return
        q_in = (self._b @ self.bounds.clip(tension)).tolist()
        st = self.state
        x = rk4(self.derivative, st.p.tolist() + st.v.tolist() + st.z.tolist(), q_in, dt,
                self.params.substep)
        if not all(map(math.isfinite, x)) or x[0] <= 0:
            raise FloatingPointError(f'{self.params.name}: the state left the model '
                                     f'(tip {x[:3]}): a step too coarse?')
        self.state = TrunkState(np.array(x[:3]), np.array(x[3:6]), np.array(x[6:]), st.t + dt)


# -- the presets -----------------------------------------------------------------------------

_TENDONS = dict(length=0.12, radius=0.012,
                tendon_angles=(0.0, math.radians(120.0), math.radians(240.0)))
_FRICTION = dict(coulomb=(2e-3, 0.05), presliding=(0.4, 250.0), friction_speed=(5.0, 0.5))


def trunk3_a() -> TrunkParams:
    """120 mm, 30 g tip, k_b = 0.10 N·m/rad, k_a = 600 N/m (module doc)."""
    return TrunkParams('trunk3_a', **_TENDONS, tip_mass=0.030, bending_stiffness=0.10,
                       axial_stiffness=600.0, bending_damping=7e-4, axial_damping=0.8,
                       **_FRICTION, tension_limit=4.0, substep=2.5e-4)


def trunk3_b() -> TrunkParams:
    """The same backbone with a 60 g tip, stiffer (module doc)."""
    return TrunkParams('trunk3_b', **_TENDONS, tip_mass=0.060, bending_stiffness=0.14,
                       axial_stiffness=800.0, bending_damping=1.1e-3, axial_damping=1.2,
                       **_FRICTION, tension_limit=4.0, substep=2.5e-4)


#: preset name → its parameters (a plant: ``TrunkPlant(TRUNKS[name]())``)
TRUNKS: dict[str, Callable[[], TrunkParams]] = {'trunk3_a': trunk3_a, 'trunk3_b': trunk3_b}


def frictionless(params: TrunkParams) -> TrunkParams:
    """``params`` without Dahl friction."""
    return replace(params, coulomb=(0.0, 0.0), presliding=(0.0, 0.0))
