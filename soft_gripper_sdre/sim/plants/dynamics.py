"""A foreign finger's equations of motion as its state's time derivative, in plain floats.

:class:`ChainDynamics` holds a chain's constants and evaluates

    ẋ = f(x, τ_in),     x = [q, q̇, z],     τ_in = Bᵀu,

the dynamics and the Dahl friction of :mod:`soft_gripper_sdre.sim.plants.chain` (whose module doc
derives them), for :class:`~soft_gripper_sdre.sim.plants.chain.FingerPlant`'s RK4 steps, four calls
per substep. It works on Python floats and lists, not numpy: for two or three joints, the sizes
of the presets, that is several times faster; and for two or three joints the equations are
written out, ~3× faster again than the general n-joint form.
"""
from __future__ import annotations

from itertools import accumulate
import math

from soft_gripper_sdre.sim.plants.chain_params import FingerParams


def rk4(f, x: list[float], u: list[float], dt: float, substep: float) -> list[float]:
    """``x`` advanced by ``dt`` under the held input ``u`` with fixed-step RK4 of
    ``f(x, u) -> ẋ``: dt split into the fewest equal steps no longer than ``substep``."""
    steps = max(1, math.ceil(dt / substep - 1e-9))
    h = dt / steps
    for _ in range(steps):
        k1 = f(x, u)
        k2 = f([a + 0.5 * h * b for a, b in zip(x, k1)], u)
        k3 = f([a + 0.5 * h * b for a, b in zip(x, k2)], u)
        k4 = f([a + h * b for a, b in zip(x, k3)], u)
        x = [a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
             for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]
    return x

class ChainDynamics:
    """The state derivative of the chain ``params`` describes (module doc).

    Attributes:
        n: the number of joints.
        a: aᵢⱼ (n × n nested lists) [kg·m²], with Dᵢⱼ = aᵢⱼ cos(θᵢ − θⱼ): aᵢᵢ = Jᵢ + mᵢcᵢ² +
            (Σ_{k>i} mₖ + m_t) lᵢ², aᵢⱼ = l_min(i,j) μ_max(i,j).
        gmu: g μᵢ (n,) [N·m], the first moments μᵢ of link i and all it carries times g.
        derivative: ``f(x, tau_in)`` → ẋ, written out for two and three joints,
            :meth:`general_derivative` otherwise.
    """

    def __init__(self, params: FingerParams) -> None:
        p = params
        n = p.n
        self.n = n
        ahead = [sum(p.masses[k] for k in range(j + 1, n)) + p.tip_mass for j in range(n)]
        com = [0.5 * length for length in p.lengths]
        mu = [p.masses[j] * com[j] + ahead[j] * p.lengths[j] for j in range(n)]
        self.a = [[(p.masses[i] * p.lengths[i] ** 2 / 12 + p.masses[i] * com[i] ** 2
                    + ahead[i] * p.lengths[i] ** 2) if i == j
                   else p.lengths[min(i, j)] * mu[max(i, j)] for j in range(n)]
                  for i in range(n)]
        self.gmu = [p.gravity * m for m in mu]
        # per-joint constants as float lists
        self._q_r, self._k, self._k3 = list(p.rest_angles), list(p.stiffness), list(p.hardening)
        self._c, self._sigma = list(p.damping), list(p.presliding)
        self._sof = [s / f if f > 0 else 0.0 for s, f in zip(p.presliding, p.coulomb)]   # σ/F_c
        self._v_s = p.friction_speed
        written_out = {2: self._derivative2, 3: self._derivative3}
        self.derivative = written_out.get(n, self.general_derivative)

    def general_derivative(self, x: list[float], tau_in: list[float]) -> list[float]:
        """d/dt of the flat state [q, q̇, z] at the joint input torques ``tau_in`` = Bᵀu, for any
        number of joints."""
        n = self.n
        q_r, k, k3, c, sigma, sof = self._q_r, self._k, self._k3, self._c, self._sigma, self._sof
        a, gmu, v_s = self.a, self.gmu, self._v_s
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
        """The general derivative written out for two joints (the same equations, ~3× faster)."""
        q0, q1, qd0, qd1, z0, z1 = x
        (a00, a01), (_, a11) = self.a
        gmu0, gmu1 = self.gmu
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
        """The general derivative written out for three joints (the same equations, ~3× faster)."""
        q0, q1, q2, qd0, qd1, qd2, z0, z1, z2 = x
        (a00, a01, a02), (_, a11, a12), (_, _, a22) = self.a
        gmu0, gmu1, gmu2 = self.gmu
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
