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

    τ = Bᵀ a − k ∘ (q − q_r) − k₃ ∘ (q − q_r)³ − c ∘ q̇ − σ ∘ z,     u = clip(u, [u_lo, u_hi]),

with B ∈ R^{m×n} the transmission (a tendon's moment arm over the actuator's pulley radius, or a
chamber's torque per pascal at each joint: every actuator reaches every joint), q_r the spring
rest angles, k and k₃ linear and hardening stiffness, c viscous damping. The delivered input a
is the clipped command u, or with an actuator lag τ_a > 0 (``input_lag``) follows it,
ȧ = (u − a) / τ_a, a state of its own (a chamber's pressure behind its valve). Coulomb
friction of level F_c is the smooth Dahl model, one bristle deflection zᵢ per joint:

    ż = q̇ − v(q̇) σ z / F_c,     v(q̇) = v_s tanh(|q̇| / v_s) ≈ |q̇| below v_s,

which slides at exactly ±F_c (σz → F_c sign q̇) and, below breakaway, holds the load on the
bristle stiffness σ: a small constant torque leaves a steady offset. (A friction tanh(q̇/v_ε)
exerts no force at rest, so the finger creeps to the frictionless equilibrium with time constant
F_c/(v_ε k); making that creep slow needs a v_ε so small that fixed-step RK4 would need
sub-microsecond steps.) The energy

    E = ½ q̇ᵀ M_q q̇ − g Σ mᵢ x_cᵢ − g m_t x_tip + Σ (½ kᵢΔqᵢ² + ¼ k₃ᵢΔqᵢ⁴ + ½ σᵢ zᵢ²)

obeys dE/dt = aᵀB q̇ − Σ cᵢq̇ᵢ² − Σ σᵢ² zᵢ² v(q̇ᵢ) / F_cᵢ, so it only falls without input.
The state (q, q̇, z), with a lag also a, is integrated by fixed-step RK4 with the plant's own
``substep``, fine against its fastest linearised mode and its bristle relaxation rate
σ v(q̇) / F_c.

The parameters and the presets (two grippers of two fingers each) are in
:mod:`soft_gripper_sdre.sim.plants.chain_params`, the one-chamber pneumatic fingers in
:mod:`soft_gripper_sdre.sim.plants.pneumatic`; the state derivative the RK4 steps evaluate is
:mod:`soft_gripper_sdre.sim.plants.dynamics`'s.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from soft_gripper_sdre.sim.plants.chain_params import PAIRS, PLANTS, FingerParams
from soft_gripper_sdre.sim.plants.dynamics import ChainDynamics, rk4


@dataclass
class FingerState:
    """Joint angles q [rad], rates q̇ [rad/s], Dahl bristle deflections z [rad], time t [s], and
    with an actuator lag the delivered inputs a (m,) [input unit] (None: no lag)."""

    q: np.ndarray
    qd: np.ndarray
    z: np.ndarray
    t: float = 0.0
    a: np.ndarray | None = None

    def copy(self) -> 'FingerState':
        return FingerState(self.q.copy(), self.qd.copy(), self.z.copy(), self.t,
                           None if self.a is None else self.a.copy())


class FingerPlant:
    """One planar finger (module doc), stepped in real or simulated time.

    ``reset()`` puts it at rest: the static equilibrium under gravity and springs at the rest
    input (each input's value nearest 0), no friction load. ``step(u, dt)`` advances ``dt``
    seconds at the held input ``u`` (m,) [input unit]; ``tip()`` is the tip (x, y) [m] in the
    base frame. ``shape`` (d = 2, m) and ``bounds`` are the parameters'.
    """

    def __init__(self, params: FingerParams) -> None:
        self.params = p = params
        n = p.n
        self.n = n
        #: the chain's constants and equations of motion
        self.dynamics = ChainDynamics(p)
        #: the state's time derivative: written out for two and three joints, general otherwise
        self.derivative = self.dynamics.derivative
        self._b = np.array(p.transmission, dtype=float)        # (m, n)
        #: the finger's shape (a planar tip, m inputs) and its inputs' bounds
        self.shape = p.shape
        self.bounds = p.bounds
        self.m = p.m
        self._lo, self._hi = self.bounds.lower, self.bounds.upper
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
        gmu = np.asarray(self.dynamics.gmu)
        dq = q - np.asarray(p.rest_angles)
        k, k3 = np.asarray(p.stiffness), np.asarray(p.hardening)
        s = np.tril(np.ones((self.n, self.n)))
        grad = s.T @ (gmu * np.sin(theta)) + k * dq + k3 * dq ** 3 - tau
        hess = s.T @ np.diag(gmu * np.cos(theta)) @ s + np.diag(k + 3 * k3 * dq ** 2)
        return grad, hess

    def equilibrium(self, u=None) -> np.ndarray:
        """Joint angles where gravity, springs and the held input ``u`` (m,) (default: the rest
        input) balance, without friction: Newton's method on ∂V/∂q = Bᵀu from the springs' rest
        angles.

        Raises:
            RuntimeError: Newton's method did not converge.
        """
        u = self.bounds.rest if u is None else np.asarray(u, dtype=float)
        tau = self._b.T @ np.clip(u, self._lo, self._hi)
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
        d = np.asarray(self.dynamics.a) * np.cos(theta[:, None] - theta[None, :])
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
        zeta = (np.einsum('ij,i,ij->j', phi, np.asarray(self.params.damping), phi)
                / (2 * omega * np.einsum('ij,ik,kj->j', phi, m, phi)))
        return omega / (2 * np.pi), zeta

    def static_gain(self) -> np.ndarray:
        """∂tip/∂u (2, m) [m per input unit] at rest, frictionless: J K_q⁻¹ Bᵀ; column j is
        input j's."""
        _, hess = self._potential_gradient(self.rest_q, np.zeros(self.n))
        return self.tip_jacobian(self.rest_q) @ np.linalg.solve(hess, self._b.T)

    # -- state and energy ------------------------------------------------------------------
    def reset(self) -> None:
        """At rest: the equilibrium under gravity and springs, at rest, no bristle load, t = 0
        (with an actuator lag: delivering the rest input)."""
        self.state = FingerState(self.rest_q.copy(), np.zeros(self.n), np.zeros(self.n),
                                 a=self.bounds.rest.copy() if self.params.input_lag > 0 else None)

    def energy(self) -> float:
        """E [J] of the module doc (kinetic, gravity, springs, bristles), zero-referenced at
        the straight, unloaded finger."""
        p, st = self.params, self.state
        theta = np.cumsum(st.q)
        dq = st.q - np.asarray(p.rest_angles)
        kinetic = 0.5 * st.qd @ self.mass_matrix(st.q) @ st.qd
        gravity = float(np.asarray(self.dynamics.gmu) @ (1 - np.cos(theta)))
        springs = np.sum(0.5 * np.asarray(p.stiffness) * dq ** 2
                         + 0.25 * np.asarray(p.hardening) * dq ** 4)
        bristles = np.sum(0.5 * np.asarray(p.presliding) * st.z ** 2)
        return float(kinetic + gravity + springs + bristles)

    # -- stepping --------------------------------------------------------------------------
    def step(self, u, dt: float) -> None:
        """Advance ``dt`` [s] with the input ``u`` (m,) held (clipped to the bounds), in RK4
        steps of at most ``substep``.

        Raises:
            ValueError: ``u`` is not m finite numbers, or ``dt`` is negative or not finite.
        """
        u = np.asarray(u, dtype=float)
        if u.shape != (self.m,) or not np.all(np.isfinite(u)):
            what = 'two finite torques [N·m]' if self.m == 2 else f'{self.m} finite input(s)'
            raise ValueError(f'u must be {what}, got {u!r}')
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f'dt must be a finite duration >= 0 s, got {dt!r}')
        if dt == 0:
            return
        if self.params.input_lag > 0:
            self._step_lagged(np.clip(u, self._lo, self._hi), dt)
            return
        lim = self.params.torque_limit
        u = np.clip(u, -lim, lim) if self.params.lower_limits is None else np.clip(
            u, self._lo, self._hi)
        tau_in = (self._b.T @ u).tolist()
        st = self.state
        x = rk4(self.derivative, st.q.tolist() + st.qd.tolist() + st.z.tolist(), tau_in, dt,
                self.params.substep)
        n = self.n
        self.state = FingerState(np.array(x[:n]), np.array(x[n:2 * n]), np.array(x[2 * n:]),
                                 st.t + dt)

    def _step_lagged(self, u: np.ndarray, dt: float) -> None:
        """:meth:`step` with the actuator lag: RK4 on [q, q̇, z, a] with ȧ = (u − a) / τ_a."""
        steps = max(1, math.ceil(dt / self.params.substep - 1e-9))
        h = dt / steps
        st = self.state
        n3, rate = 3 * self.n, 1.0 / self.params.input_lag
        bt = self._b.T.tolist()                 # (n, m)
        target = u.tolist()
        f = self.derivative

        def g(x):
            a = x[n3:]
            tau = [sum(b * ak for b, ak in zip(row, a)) for row in bt]
            return f(x[:n3], tau) + [rate * (c - ak) for c, ak in zip(target, a)]

        x = st.q.tolist() + st.qd.tolist() + st.z.tolist() + st.a.tolist()
        for _ in range(steps):
            k1 = g(x)
            k2 = g([a + 0.5 * h * b for a, b in zip(x, k1)])
            k3 = g([a + 0.5 * h * b for a, b in zip(x, k2)])
            k4 = g([a + h * b for a, b in zip(x, k3)])
            x = [a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
                 for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]
        n = self.n
        self.state = FingerState(np.array(x[:n]), np.array(x[n:2 * n]), np.array(x[2 * n:n3]),
                                 st.t + dt, np.array(x[n3:]))


def plant_pair(kind: str) -> tuple[FingerPlant, FingerPlant]:
    """The two fingers of a gripper, at rest: ``'tendon3'`` → (index, thumb), ``'stiff2'`` →
    (a, b); and the grippers of :mod:`soft_gripper_sdre.sim.plants.presets` (``pneumatic1``,
    ``trunk3``).

    Raises:
        ValueError: an unknown kind.
    """
    if kind in PAIRS:
        return tuple(FingerPlant(PLANTS[name]()) for name in PAIRS[kind])
    from soft_gripper_sdre.sim.plants import presets  # it builds on this module
    return presets.plant_pair(kind)


def input_angle(gain: np.ndarray) -> float:
    """The angle [deg] between the tip directions of the two inputs, columns of ``gain`` (2, 2),
    as lines (0 to 90°): acos(|g₀·g₁| / (|g₀||g₁|))."""
    g0, g1 = gain[:, 0], gain[:, 1]
    cos = abs(g0 @ g1) / (np.linalg.norm(g0) * np.linalg.norm(g1))
    return float(np.degrees(np.arccos(min(1.0, cos))))
