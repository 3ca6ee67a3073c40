"""Foreign fingers: planar tendon-driven and stiff serial-link fingers unlike the SoMo finger.

They stand in for "your own gripper" when testing the identify → train → deploy recipe: other
link counts, sizes, masses, stiffnesses, friction, actuation and speeds than the 10-joint,
~100 mm PyBullet finger of docs/finger.md. Plain numpy and floats, no PyBullet, no ROS.

**Frame.** Each finger hangs from its base like a gripper finger and bends in one vertical plane.
The task space is that plane: X points down along the hanging finger (gravity is +X), Y
horizontally toward the palm's centre, the closing direction; the tip (x, y) is given in this
base frame [m]. (For a planar finger the axis beside the grasp direction Y is the one along the
finger.) Joint angles q are relative, positive bending toward +Y; the absolute angle of link i
from +X is θᵢ = q₀ + … + qᵢ, so θ = S q with S the lower-triangular matrix of ones.

**Dynamics.** Link i (length lᵢ, mass mᵢ, uniform: centre of mass at cᵢ = lᵢ/2, inertia
Jᵢ = mᵢlᵢ²/12) carries everything beyond it; a point mass m_t sits at the tip. With the first
moments μⱼ = mⱼcⱼ + (Σ_{k>j} mₖ + m_t) lⱼ, in absolute angles the chain obeys

    Σⱼ Dᵢⱼ(θ) θ̈ⱼ + Σⱼ aᵢⱼ sin(θᵢ − θⱼ) θ̇ⱼ² = −g μᵢ sin θᵢ + τᵢ − τᵢ₊₁,
    Dᵢⱼ = aᵢⱼ cos(θᵢ − θⱼ),   aᵢⱼ = l_min(i,j) μ_max(i,j) (i ≠ j),
    aᵢᵢ = Jᵢ + mᵢcᵢ² + (Σ_{k>i} mₖ + m_t) lᵢ²,

where τᵢ is the torque at joint i (τₙ = 0); in joint coordinates the mass matrix is
M_q = Sᵀ D S. The joint torques are

    τ = Bᵀ u − k ∘ (q − q_r) − k₃ ∘ (q − q_r)³ − c ∘ q̇ − σ ∘ z,     u = clip(u, ±torque_limit),

with B ∈ R^{2×n} the transmission (tendon moment arm over the actuator's pulley radius: both
actuators reach every joint), q_r the spring rest angles, k and k₃ linear and hardening
stiffness, c viscous damping. Coulomb friction of level F_c is the smooth Dahl model, one
bristle deflection zᵢ per joint:

    ż = q̇ − v(q̇) σ z / F_c,     v(q̇) = v_s tanh(|q̇| / v_s) ≈ |q̇| below v_s,

which slides at exactly ±F_c (σz → F_c sign q̇) and, below breakaway, holds the load on the
bristle stiffness σ: a small constant torque leaves a steady offset. (A friction tanh(q̇/v_ε)
exerts no force at rest, so the finger creeps to the frictionless equilibrium with time constant
F_c/(v_ε k); making that creep slow needs a v_ε so small that fixed-step RK4 would need
sub-microsecond steps.) The energy

    E = ½ q̇ᵀ M_q q̇ − g Σ mᵢ x_cᵢ − g m_t x_tip + Σ (½ kᵢΔqᵢ² + ¼ k₃ᵢΔqᵢ⁴ + ½ σᵢ zᵢ²)

obeys dE/dt = uᵀB q̇ − Σ cᵢq̇ᵢ² − Σ σᵢ² zᵢ² v(q̇ᵢ) / F_cᵢ, so it only falls without input.
The state (q, q̇, z) is integrated by fixed-step RK4 with the plant's own ``substep``, fine
against its fastest linearised mode and its bristle relaxation rate σ v(q̇) / F_c.

**The presets** (:data:`PLANTS`; :func:`plant_pair` gives a gripper's two fingers). Measured by
this module: the rest tip (x, y); the natural frequencies and modal damping ratios of the
frictionless finger linearised at rest (:meth:`FingerPlant.modes`); the static tip displacement
per mN·m on each input, frictionless (:meth:`FingerPlant.static_gain`), the direction of each
input's tip motion (from +X toward +Y) and the angle between the two (:func:`input_angle`):

=============  =============  ================  =====  ============  ==========  =====
preset         rest tip [mm]  modes [Hz]        ζ₁     mm per mN·m   directions  angle
=============  =============  ================  =====  ============  ==========  =====
tendon3_index  (78.3, 44.2)   5.4, 21.4, 71.2   0.15   1.49, 1.34    125°, 138°  12.7°
tendon3_thumb  (81.3, 39.1)   5.1, 22.0, 82.8   0.14   0.89, 0.83    122°, 135°  13.5°
stiff2_a       (71.6, 38.5)   28.1, 124.5       0.073  0.015, 0.014  121°, 133°  11.9°
stiff2_b       (71.7, 38.4)   20.0, 100.2       0.055  0.013, 0.012  121°, 133°  11.9°
=============  =============  ================  =====  ============  ==========  =====

* ``tendon3_*``: three links of 45/30/20 mm and 12/7/4 g (uniform), a fingertip of 4 g (index)
  or 12 g (thumb); linear springs of 0.12/0.08/0.05 N·m/rad (index) or 0.20/0.13/0.08 (thumb)
  curling the finger at rest; two flexor tendons over all three joints, one pulling mostly on
  the proximal joint, the other mostly on the distal ones; Dahl friction of 0.5/0.35/0.2 mN·m
  (a tendon in its sheath) with a 5 mrad presliding range. Torque limit 20 mN·m (the index's tip
  then moves ~25 mm); RK4 steps of 0.25 ms. Soft and slow, unlike the SoMo finger's 10 joints,
  ~110 mm and 3.1/8.9 Hz with one input per bending axis.
* ``stiff2_*``: two links of 50/35 mm and 30/18 g, a 10 g (a) or 40 g (b) tip; springs of
  6.0/3.5 (a) or 7.0/4.0 N·m/rad (b) with a hardening k₃ = 60 k (+60 % stiffness at 0.1 rad);
  a coupled 2 × 2 transmission (1.0/0.2 and 0.3/1.0); lightly damped; Dahl friction 3/2 mN·m
  with a 2 mrad presliding range. Torque limit 0.25 N·m (tip ~4 mm); RK4 steps of 0.2 ms.

Friction above ``friction_speed`` v_s (20 rad/s tendon, 10 rad/s stiff) grows like F_c|q̇|/v_s:
v(q̇) = v_s tanh(|q̇|/v_s) bounds the bristles' relaxation rate σv/F_c, which keeps RK4 stable
(checked against ``substep``) at the speeds a torque-limited bang-bang input reaches.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate
import math
from typing import Callable

import numpy as np

GRAVITY = 9.81


@dataclass(frozen=True)
class FingerParams:
    """A planar serial-link finger; per-joint tuples have one entry per joint (SI units)."""

    name: str
    lengths: tuple[float, ...]           # m
    masses: tuple[float, ...]            # kg, uniform links
    tip_mass: float                      # kg, a point mass at the tip
    rest_angles: tuple[float, ...]       # rad, the springs' rest angles q_r
    stiffness: tuple[float, ...]         # N·m/rad, k
    hardening: tuple[float, ...]         # N·m/rad³, k₃
    damping: tuple[float, ...]           # N·m·s/rad, c
    coulomb: tuple[float, ...]           # N·m, F_c (0 = no friction at that joint)
    presliding: tuple[float, ...]        # N·m/rad, σ, the Dahl bristle stiffness
    friction_speed: float                # rad/s, v_s: friction turns viscous above it
    transmission: tuple[tuple[float, ...], tuple[float, ...]]   # B, 2 × n, dimensionless
    torque_limit: float                  # N·m, |u| is clipped to it
    substep: float                       # s, the RK4 step
    gravity: float = GRAVITY             # m/s², along +X

    def __post_init__(self) -> None:
        n = len(self.lengths)
        per_joint = ('masses', 'rest_angles', 'stiffness', 'hardening', 'damping', 'coulomb',
                     'presliding')
        for name in per_joint:
            if len(getattr(self, name)) != n:
                raise ValueError(f'{self.name}: {name} has {len(getattr(self, name))} entries, '
                                 f'expected one per joint ({n})')
        if len(self.transmission) != 2 or any(len(row) != n for row in self.transmission):
            raise ValueError(f'{self.name}: transmission must be 2 × {n}')
        if min(self.lengths) <= 0 or min(self.masses) <= 0 or self.tip_mass < 0:
            raise ValueError(f'{self.name}: lengths and masses must be positive')
        if min(self.stiffness) <= 0 or min(self.damping) < 0 or min(self.hardening) < 0:
            raise ValueError(f'{self.name}: stiffness must be positive, damping and hardening >= 0')
        if any(f < 0 or s < 0 or (f > 0) != (s > 0) for f, s in zip(self.coulomb, self.presliding)):
            raise ValueError(f'{self.name}: coulomb and presliding must both be positive '
                             '(friction) or both zero (none) at each joint')
        if self.torque_limit <= 0 or self.substep <= 0 or self.friction_speed <= 0:
            raise ValueError(f'{self.name}: torque_limit, substep and friction_speed must be '
                             'positive')
        rate = self.friction_speed * max(s / f if f else 0.0
                                         for s, f in zip(self.presliding, self.coulomb))
        if rate * self.substep > 1.5:
            raise ValueError(f'{self.name}: the bristles relax at up to {rate:.0f}/s, too fast '
                             f'for RK4 steps of {self.substep} s (keep the product <= 1.5)')

    @property
    def n(self) -> int:
        return len(self.lengths)


@dataclass
class FingerState:
    """Joint angles q [rad], rates q̇ [rad/s], Dahl bristle deflections z [rad], time t [s]."""

    q: np.ndarray
    qd: np.ndarray
    z: np.ndarray
    t: float = 0.0

    def copy(self) -> 'FingerState':
        return FingerState(self.q.copy(), self.qd.copy(), self.z.copy(), self.t)


class FingerPlant:
    """One planar finger (module doc), stepped in real or simulated time.

    ``reset()`` puts it at rest: the static equilibrium under gravity and springs at u = 0, no
    friction load. ``step(u, dt)`` advances ``dt`` seconds at the held input ``u`` (2,) [N·m];
    ``tip()`` is the tip (x, y) [m] in the base frame.
    """

    def __init__(self, params: FingerParams) -> None:
        self.params = p = params
        n = p.n
        self.n = n
        ahead = [sum(p.masses[k] for k in range(j + 1, n)) + p.tip_mass for j in range(n)]
        com = [0.5 * length for length in p.lengths]
        self._mu = [p.masses[j] * com[j] + ahead[j] * p.lengths[j] for j in range(n)]
        self._a = [[(p.masses[i] * p.lengths[i] ** 2 / 12 + p.masses[i] * com[i] ** 2
                     + ahead[i] * p.lengths[i] ** 2) if i == j
                    else p.lengths[min(i, j)] * self._mu[max(i, j)] for j in range(n)]
                   for i in range(n)]
        self._gmu = [p.gravity * m for m in self._mu]
        self._b = np.array(p.transmission, dtype=float)        # (2, n)
        # per-joint constants as float lists for _derivative
        self._q_r, self._k, self._k3 = list(p.rest_angles), list(p.stiffness), list(p.hardening)
        self._c, self._sigma = list(p.damping), list(p.presliding)
        self._sof = [s / f if f > 0 else 0.0 for s, f in zip(p.presliding, p.coulomb)]   # σ/F_c
        self._v_s = p.friction_speed
        #: the state's time derivative: written out for two and three joints, general otherwise
        self.derivative = {2: self._derivative2, 3: self._derivative3}.get(n, self._derivative)
        self.state = FingerState(np.zeros(n), np.zeros(n), np.zeros(n))
        self.rest_q = self.equilibrium()
        self.rest_tip = self.tip_of(self.rest_q)
        self.reset()

    # -- kinematics ------------------------------------------------------------------------
    def tip_of(self, q: np.ndarray) -> np.ndarray:
        """Tip (x, y) [m] of joint angles ``q``: Σ lᵢ (cos θᵢ, sin θᵢ)."""
        theta = np.cumsum(q)
        lengths = np.asarray(self.params.lengths)
        return np.array([lengths @ np.cos(theta), lengths @ np.sin(theta)])

    def tip_jacobian(self, q: np.ndarray) -> np.ndarray:
        """∂tip/∂q (2, n) at ``q``: column j sums lᵢ(−sin θᵢ, cos θᵢ) over the links i ≥ j."""
        theta = np.cumsum(q)
        lengths = np.asarray(self.params.lengths)
        dx = lengths * -np.sin(theta)
        dy = lengths * np.cos(theta)
        return np.array([np.cumsum(dx[::-1])[::-1], np.cumsum(dy[::-1])[::-1]])

    def tip(self) -> np.ndarray:
        """The tip (x, y) [m] now."""
        return self.tip_of(self.state.q)

    # -- statics and linearisation ---------------------------------------------------------
    def _potential_gradient(self, q: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """∂V/∂q − τ and its Jacobian (V: gravity and springs) for the equilibrium search."""
        p = self.params
        theta = np.cumsum(q)
        gmu = np.asarray(self._gmu)
        dq = q - np.asarray(p.rest_angles)
        k, k3 = np.asarray(p.stiffness), np.asarray(p.hardening)
        s = np.tril(np.ones((self.n, self.n)))
        grad = s.T @ (gmu * np.sin(theta)) + k * dq + k3 * dq ** 3 - tau
        hess = s.T @ np.diag(gmu * np.cos(theta)) @ s + np.diag(k + 3 * k3 * dq ** 2)
        return grad, hess

    def equilibrium(self, u=(0.0, 0.0)) -> np.ndarray:
        """Joint angles where gravity, springs and the held input ``u`` balance, without friction:
        Newton's method on ∂V/∂q = Bᵀu from the springs' rest angles.

        Raises:
            RuntimeError: Newton's method did not converge.
        """
        tau = self._b.T @ np.clip(np.asarray(u, dtype=float), -self.params.torque_limit,
                                  self.params.torque_limit)
        q = np.asarray(self.params.rest_angles, dtype=float).copy()
        for _ in range(100):
            grad, hess = self._potential_gradient(q, tau)
            step = np.linalg.solve(hess, grad)
            q -= step
            if np.max(np.abs(step)) < 1e-15:
                return q
        raise RuntimeError(f'{self.params.name}: no equilibrium found for u = {u}')

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M_q = Sᵀ D(θ) S (n, n) [kg·m²]."""
        theta = np.cumsum(q)
        d = np.asarray(self._a) * np.cos(theta[:, None] - theta[None, :])
        s = np.tril(np.ones((self.n, self.n)))
        return s.T @ d @ s

    def natural_frequencies(self) -> np.ndarray:
        """Undamped natural frequencies [Hz] of the frictionless finger linearised at rest,
        ascending: √eig(M_q⁻¹ K_q) / 2π with K_q the Hessian of the potential."""
        return self.modes()[0]

    def modes(self) -> tuple[np.ndarray, np.ndarray]:
        """(natural frequencies [Hz], damping ratios) of the frictionless finger linearised at
        rest, slowest first: ωᵢ² and φᵢ from K_q φ = ω² M_q φ, and the modal damping ratio
        ζᵢ = φᵢᵀ C φᵢ / (2 ωᵢ φᵢᵀ M_q φᵢ) of the viscous damping C = diag(c)."""
        _, hess = self._potential_gradient(self.rest_q, np.zeros(self.n))
        m = self.mass_matrix(self.rest_q)
        omega2, phi = np.linalg.eig(np.linalg.solve(m, hess))
        order = np.argsort(omega2.real)
        omega = np.sqrt(omega2.real[order])
        phi = phi.real[:, order]
        zeta = (np.einsum('ij,i,ij->j', phi, np.asarray(self._c), phi)
                / (2 * omega * np.einsum('ij,ik,kj->j', phi, m, phi)))
        return omega / (2 * np.pi), zeta

    def static_gain(self) -> np.ndarray:
        """∂tip/∂u (2, 2) [m/(N·m)] at rest, frictionless: J K_q⁻¹ Bᵀ; column j is input j's."""
        _, hess = self._potential_gradient(self.rest_q, np.zeros(self.n))
        return self.tip_jacobian(self.rest_q) @ np.linalg.solve(hess, self._b.T)

    # -- state and energy ------------------------------------------------------------------
    def reset(self) -> None:
        """At rest: the equilibrium under gravity and springs, at rest, no bristle load, t = 0."""
        self.state = FingerState(self.rest_q.copy(), np.zeros(self.n), np.zeros(self.n))

    def energy(self) -> float:
        """E [J] of the module doc (kinetic, gravity, springs, bristles), zero-referenced at
        the straight, unloaded finger."""
        p, st = self.params, self.state
        theta = np.cumsum(st.q)
        dq = st.q - np.asarray(p.rest_angles)
        kinetic = 0.5 * st.qd @ self.mass_matrix(st.q) @ st.qd
        gravity = float(np.asarray(self._gmu) @ (1 - np.cos(theta)))
        springs = np.sum(0.5 * np.asarray(p.stiffness) * dq ** 2
                         + 0.25 * np.asarray(p.hardening) * dq ** 4)
        bristles = np.sum(0.5 * np.asarray(p.presliding) * st.z ** 2)
        return float(kinetic + gravity + springs + bristles)

    # -- dynamics --------------------------------------------------------------------------
    def _derivative(self, x: list[float], tau_in: list[float]) -> list[float]:
        """d/dt of the flat state [q, q̇, z] at the joint input torques ``tau_in`` = Bᵀu.

        Plain floats: for two or three joints this is several times faster than numpy."""
        n = self.n
        q_r, k, k3, c, sigma, sof = self._q_r, self._k, self._k3, self._c, self._sigma, self._sof
        a, gmu, v_s = self._a, self._gmu, self._v_s
        theta = list(accumulate(x[:n]))
        w = list(accumulate(x[n:2 * n]))
        cos_t = [math.cos(t) for t in theta]
        sin_t = [math.sin(t) for t in theta]
        tau = [0.0] * (n + 1)
        out = [0.0] * (3 * n)
        for i in range(n):
            dq = x[i] - q_r[i]
            qd = x[n + i]
            tau[i] = tau_in[i] - dq * (k[i] + k3[i] * dq * dq) - c[i] * qd - sigma[i] * x[2 * n + i]
            out[i] = qd
            if sof[i]:      # ż = q̇ − v(q̇) σ z / F_c, v(q̇) = v_s tanh(|q̇| / v_s)
                out[2 * n + i] = qd - v_s * math.tanh(abs(qd) / v_s) * sof[i] * x[2 * n + i]
        # D θ̈ = r: r_i = τ_i − τ_{i+1} − g μ_i sin θ_i − Σ_j a_ij sin(θ_i − θ_j) θ̇_j²
        mat = [[0.0] * n for _ in range(n)]
        r = [0.0] * n
        for i in range(n):
            ri = tau[i] - tau[i + 1] - gmu[i] * sin_t[i]
            ci, si, ai, row = cos_t[i], sin_t[i], a[i], mat[i]
            for j in range(n):
                if j == i:
                    row[i] = ai[i]
                else:
                    ri -= ai[j] * (si * cos_t[j] - ci * sin_t[j]) * w[j] * w[j]
                    row[j] = ai[j] * (ci * cos_t[j] + si * sin_t[j])
            r[i] = ri
        # Gaussian elimination (D is symmetric positive definite: no pivoting needed)
        for i in range(n):
            piv = mat[i][i]
            for j in range(i + 1, n):
                f = mat[j][i] / piv
                if f:
                    rowj, rowi = mat[j], mat[i]
                    for m in range(i + 1, n):
                        rowj[m] -= f * rowi[m]
                    r[j] -= f * r[i]
        for i in reversed(range(n)):
            s = r[i]
            for m in range(i + 1, n):
                s -= mat[i][m] * r[m]
            r[i] = s / mat[i][i]
        out[n] = r[0]
        for i in range(1, n):
            out[n + i] = r[i] - r[i - 1]
        return out

    def _derivative2(self, x: list[float], tau_in: list[float]) -> list[float]:
        """:meth:`_derivative` written out for two joints (the same equations, ~3× faster)."""
        q0, q1, qd0, qd1, z0, z1 = x
        (a00, a01), (_, a11) = self._a
        gmu0, gmu1 = self._gmu
        (r0, r1), (k0, k1), (h0, h1) = self._q_r, self._k, self._k3
        (c0, c1), (sg0, sg1), (f0, f1), v_s = self._c, self._sigma, self._sof, self._v_s
        th1 = q0 + q1
        w0, w1 = qd0, qd0 + qd1
        cos0, sin0, cos1, sin1 = math.cos(q0), math.sin(q0), math.cos(th1), math.sin(th1)
        d0, d1 = q0 - r0, q1 - r1
        t0 = tau_in[0] - d0 * (k0 + h0 * d0 * d0) - c0 * qd0 - sg0 * z0
        t1 = tau_in[1] - d1 * (k1 + h1 * d1 * d1) - c1 * qd1 - sg1 * z1
        m01 = a01 * (cos0 * cos1 + sin0 * sin1)
        n01 = a01 * (sin0 * cos1 - cos0 * sin1)            # a₀₁ sin(θ₀ − θ₁)
        b0 = t0 - t1 - gmu0 * sin0 - n01 * w1 * w1
        b1 = t1 - gmu1 * sin1 + n01 * w0 * w0
        det = a00 * a11 - m01 * m01
        acc0 = (a11 * b0 - m01 * b1) / det
        acc1 = (a00 * b1 - m01 * b0) / det
        zd0 = qd0 - v_s * math.tanh(abs(qd0) / v_s) * f0 * z0 if f0 else 0.0
        zd1 = qd1 - v_s * math.tanh(abs(qd1) / v_s) * f1 * z1 if f1 else 0.0
        return [qd0, qd1, acc0, acc1 - acc0, zd0, zd1]

    def _derivative3(self, x: list[float], tau_in: list[float]) -> list[float]:
        """:meth:`_derivative` written out for three joints (the same equations, ~3× faster)."""
        q0, q1, q2, qd0, qd1, qd2, z0, z1, z2 = x
        (a00, a01, a02), (_, a11, a12), (_, _, a22) = self._a
        gmu0, gmu1, gmu2 = self._gmu
        (r0, r1, r2), (k0, k1, k2), (h0, h1, h2) = self._q_r, self._k, self._k3
        (c0, c1, c2), (sg0, sg1, sg2) = self._c, self._sigma
        (f0, f1, f2), v_s = self._sof, self._v_s
        th1 = q0 + q1
        th2 = th1 + q2
        w0 = qd0
        w1 = w0 + qd1
        w2 = w1 + qd2
        cos0, sin0 = math.cos(q0), math.sin(q0)
        cos1, sin1 = math.cos(th1), math.sin(th1)
        cos2, sin2 = math.cos(th2), math.sin(th2)
        d0, d1, d2 = q0 - r0, q1 - r1, q2 - r2
        t0 = tau_in[0] - d0 * (k0 + h0 * d0 * d0) - c0 * qd0 - sg0 * z0
        t1 = tau_in[1] - d1 * (k1 + h1 * d1 * d1) - c1 * qd1 - sg1 * z1
        t2 = tau_in[2] - d2 * (k2 + h2 * d2 * d2) - c2 * qd2 - sg2 * z2
        m01 = a01 * (cos0 * cos1 + sin0 * sin1)
        m02 = a02 * (cos0 * cos2 + sin0 * sin2)
        m12 = a12 * (cos1 * cos2 + sin1 * sin2)
        n01 = a01 * (sin0 * cos1 - cos0 * sin1)            # aᵢⱼ sin(θᵢ − θⱼ)
        n02 = a02 * (sin0 * cos2 - cos0 * sin2)
        n12 = a12 * (sin1 * cos2 - cos1 * sin2)
        ww0, ww1, ww2 = w0 * w0, w1 * w1, w2 * w2
        b0 = t0 - t1 - gmu0 * sin0 - n01 * ww1 - n02 * ww2
        b1 = t1 - t2 - gmu1 * sin1 + n01 * ww0 - n12 * ww2
        b2 = t2 - gmu2 * sin2 + n02 * ww0 + n12 * ww1
        # Gaussian elimination of the symmetric D
        g1, g2 = m01 / a00, m02 / a00
        e11, e12, e22 = a11 - g1 * m01, m12 - g1 * m02, a22 - g2 * m02
        b1 -= g1 * b0
        b2 -= g2 * b0
        g = e12 / e11
        acc2 = (b2 - g * b1) / (e22 - g * e12)
        acc1 = (b1 - e12 * acc2) / e11
        acc0 = (b0 - m01 * acc1 - m02 * acc2) / a00
        zd0 = qd0 - v_s * math.tanh(abs(qd0) / v_s) * f0 * z0 if f0 else 0.0
        zd1 = qd1 - v_s * math.tanh(abs(qd1) / v_s) * f1 * z1 if f1 else 0.0
        zd2 = qd2 - v_s * math.tanh(abs(qd2) / v_s) * f2 * z2 if f2 else 0.0
        return [qd0, qd1, qd2, acc0, acc1 - acc0, acc2 - acc1, zd0, zd1, zd2]

    def step(self, u, dt: float) -> None:
        """Advance ``dt`` [s] with the input ``u`` (2,) [N·m] held (clipped to ±torque_limit),
        in RK4 steps of at most ``substep``.

        Raises:
            ValueError: ``u`` is not two finite numbers, or ``dt`` is negative or not finite.
        """
        u = np.asarray(u, dtype=float)
        if u.shape != (2,) or not np.all(np.isfinite(u)):
            raise ValueError(f'u must be two finite torques [N·m], got {u!r}')
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f'dt must be a finite duration >= 0 s, got {dt!r}')
        if dt == 0:
            return
        lim = self.params.torque_limit
        tau_in = (self._b.T @ np.clip(u, -lim, lim)).tolist()
        steps = max(1, math.ceil(dt / self.params.substep - 1e-9))
        h = dt / steps
        st = self.state
        x = st.q.tolist() + st.qd.tolist() + st.z.tolist()
        f = self.derivative
        for _ in range(steps):
            k1 = f(x, tau_in)
            k2 = f([a + 0.5 * h * b for a, b in zip(x, k1)], tau_in)
            k3 = f([a + 0.5 * h * b for a, b in zip(x, k2)], tau_in)
            k4 = f([a + h * b for a, b in zip(x, k3)], tau_in)
            x = [a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
                 for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]
        n = self.n
        self.state = FingerState(np.array(x[:n]), np.array(x[n:2 * n]), np.array(x[2 * n:]),
                                 st.t + dt)


# -- the presets -----------------------------------------------------------------------------

#: the tendon finger's links [m] and masses [kg]: ~95 mm, 23 g without the tip
_TENDON_LINKS = dict(lengths=(0.045, 0.030, 0.020), masses=(0.012, 0.007, 0.004))
#: the stiff finger's links [m] and masses [kg]: 85 mm, 48 g without the tip
_STIFF_LINKS = dict(lengths=(0.050, 0.035), masses=(0.030, 0.018))


def tendon3_index() -> FingerParams:
    """Three-link tendon finger, soft and light (4 g tip): a flexor tendon that pulls mostly on
    the proximal joint (moment arms 1.6/0.6/0.3 of the pulley radius) and one that pulls mostly
    on the distal joints (0.5/0.9/1.4); Dahl friction 0.5/0.35/0.2 mN·m."""
    return FingerParams(
        'tendon3_index', **_TENDON_LINKS, tip_mass=0.004, rest_angles=(0.25, 0.45, 0.45),
        stiffness=(0.12, 0.08, 0.05), hardening=(0.0, 0.0, 0.0), damping=(1.2e-3, 0.8e-3, 0.4e-3),
        coulomb=(5e-4, 3.5e-4, 2e-4), presliding=(0.1, 0.07, 0.04), friction_speed=20.0,
        transmission=((1.6, 0.6, 0.3), (0.5, 0.9, 1.4)), torque_limit=0.02, substep=2.5e-4)


def tendon3_thumb() -> FingerParams:
    """The index's links with a 12 g tip, stiffer springs (×1.6–1.7), another rest curl and
    tendon routing (1.5/0.7/0.3 and 0.4/1.0/1.5)."""
    return FingerParams(
        'tendon3_thumb', **_TENDON_LINKS, tip_mass=0.012, rest_angles=(0.2, 0.4, 0.5),
        stiffness=(0.20, 0.13, 0.08), hardening=(0.0, 0.0, 0.0), damping=(2e-3, 1.3e-3, 0.7e-3),
        coulomb=(5e-4, 3.5e-4, 2e-4), presliding=(0.1, 0.07, 0.04), friction_speed=20.0,
        transmission=((1.5, 0.7, 0.3), (0.4, 1.0, 1.5)), torque_limit=0.02, substep=2.5e-4)


def stiff2_a() -> FingerParams:
    """Two-link stiff finger (10 g tip), hardening springs k₃ = 60 k, a coupled 2 × 2
    transmission (1.0/0.2 and 0.3/1.0), lightly damped; Dahl friction 3/2 mN·m."""
    return FingerParams(
        'stiff2_a', **_STIFF_LINKS, tip_mass=0.010, rest_angles=(0.25, 0.6),
        stiffness=(6.0, 3.5), hardening=(360.0, 210.0), damping=(5e-3, 3e-3),
        coulomb=(3e-3, 2e-3), presliding=(1.5, 1.0), friction_speed=10.0,
        transmission=((1.0, 0.2), (0.3, 1.0)), torque_limit=0.25, substep=2e-4)


def stiff2_b() -> FingerParams:
    """The stiff finger with a 40 g tip (a heavier fingertip or a tool) and stiffer joints."""
    return FingerParams(
        'stiff2_b', **_STIFF_LINKS, tip_mass=0.040, rest_angles=(0.25, 0.6),
        stiffness=(7.0, 4.0), hardening=(420.0, 240.0), damping=(6e-3, 4e-3),
        coulomb=(3e-3, 2e-3), presliding=(1.5, 1.0), friction_speed=10.0,
        transmission=((1.0, 0.2), (0.3, 1.0)), torque_limit=0.25, substep=2e-4)


#: preset name → its parameters (build a plant with ``FingerPlant(PLANTS[name]())``)
PLANTS: dict[str, Callable[[], FingerParams]] = {
    'tendon3_index': tendon3_index, 'tendon3_thumb': tendon3_thumb,
    'stiff2_a': stiff2_a, 'stiff2_b': stiff2_b,
}
#: gripper kind → the presets of its two fingers
PAIRS = {'tendon3': ('tendon3_index', 'tendon3_thumb'), 'stiff2': ('stiff2_a', 'stiff2_b')}


def plant_pair(kind: str) -> tuple[FingerPlant, FingerPlant]:
    """The two fingers of a gripper, at rest: ``'tendon3'`` → (index, thumb), ``'stiff2'`` →
    (a, b).

    Raises:
        ValueError: an unknown kind.
    """
    if kind not in PAIRS:
        raise ValueError(f'unknown plant kind {kind!r}: expected one of {", ".join(PAIRS)}')
    return tuple(FingerPlant(PLANTS[name]()) for name in PAIRS[kind])


def input_angle(gain: np.ndarray) -> float:
    """The angle [deg] between the tip directions of the two inputs, columns of ``gain`` (2, 2),
    as lines (0 to 90°): acos(|g₀·g₁| / (|g₀||g₁|))."""
    g0, g1 = gain[:, 0], gain[:, 1]
    cos = abs(g0 @ g1) / (np.linalg.norm(g0) * np.linalg.norm(g1))
    return float(np.degrees(np.arccos(min(1.0, cos))))
