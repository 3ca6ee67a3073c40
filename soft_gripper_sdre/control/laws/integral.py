"""Integral action for a tracking law: removes the steady offset joint friction leaves where the
reference is constant and reachable, without winding up at the torque limit or against the cube."""
from __future__ import annotations

import math

import numpy as np

from soft_gripper_sdre.control.kernels import (
    IntegralSettings,
    integral_roll_off,
    integral_step,
    integral_update,
    kernel_array,
)
from soft_gripper_sdre.control.tracking import LawStep, RollOff
from soft_gripper_sdre.sim.shape import InputBounds

#: the default law's integral action: gain k_i [1/s³] (0 = off) and the error band [m] inside which
#: it integrates; docs/results.md "Integral action" has the tuning behind them
DEFAULT_INTEGRAL = dict(gain=1.0e5, band=5e-4)
#: time constant [s] with which the integral decays while the error is outside the band
INTEGRAL_LEAK_S = 0.1


def _check_gain_and_band(gain: float, band: float) -> None:
    """ValueError naming ``gain`` or ``band`` unless each is finite and > 0."""
    if not (math.isfinite(gain) and gain > 0):
        raise ValueError(f'integral gain must be finite and > 0 (0 = no integral action), '
                         f'got {gain!r}')
    if not (math.isfinite(band) and band > 0):
        raise ValueError(f'integral band must be finite and > 0 m, got {band!r}')


class IntegralAction:
    """u_I = k_i G₂(0)⁻¹ ξ,  ξ = ∫ (p_d − p) dt  per finger, with conditional integration.

    The integral is a desired tip acceleration k_i ξ turned into torques by the learned input map
    at rest (as the PD's gains are), so one gain serves both axes. Each step first adds u_I (from
    the integral so far) to the law's unsaturated command, then updates ξ by Δt (p_d − p), but only
    where that is safe:

    * **saturated** (either torque of the finger beyond ``u_max`` with u_I added): ξ is frozen, so
      the integral cannot wind up while the actuator cannot deliver more;
    * **error outside the band** (‖p − p_d‖ > ``band``): the reference is not reachable now. That
      is a grasping finger pressing on the cube, whose reference lies inside it so that the law's
      stiffness sets the grip force; an integral there would keep raising the grip until the
      torque saturates. ξ decays instead (time constant :data:`INTEGRAL_LEAK_S`), so in a held
      contact the grip force returns to that of the law without integral action, and a finger
      leaving the cube does not start from an integral built for the other direction of motion;
    * a finger whose state is not finite: ξ is left as it is and gets no u_I this step.

    ξ is also bounded so that |u_I| ≤ u_max on each torque. :meth:`reset` zeroes it.

    Args:
        g2_rest: (2, 2) the learned G₂ at rest [m/s² per N·m].
        gain: k_i [1/s³], finite and > 0.
        band: the error norm [m] inside which ξ integrates, finite and > 0.
        u_max: torque saturation [N·m].
        n_fingers: number of fingers.
        dt: control period [s].
    """

    def __init__(self, g2_rest, gain: float, band: float, u_max: float, n_fingers: int,
                 dt: float) -> None:
        _check_gain_and_band(gain, band)
        if not (math.isfinite(u_max) and u_max > 0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max!r}')
        g2 = np.asarray(g2_rest, dtype=float)
        if g2.shape != (2, 2) or not np.all(np.isfinite(g2)) or abs(np.linalg.det(g2)) == 0.0:
            raise ValueError(f'g2_rest must be a finite, invertible (2, 2) input map, '
                             f'got {g2_rest!r}')
        self.gain, self.band, self.u_max, self.dt = (float(gain), float(band), float(u_max),
                                                     float(dt))
        self.to_torque = self.gain * np.linalg.inv(g2)          # u_I = to_torque ξ
        self.from_torque = g2 / self.gain                        # ξ = from_torque u_I
        self.decay = math.exp(-self.dt / INTEGRAL_LEAK_S)
        self.settings = IntegralSettings.of(self.to_torque, self.from_torque, self.dt, self.band,
                                            self.decay, self.u_max).records
        self.xi = np.zeros((int(n_fingers), 2))                  # ∫ (p_d − p) dt [m·s]

    def reset(self) -> None:
        self.xi[:] = 0.0

    def torque(self) -> np.ndarray:
        """(n, 2) u_I = k_i G₂(0)⁻¹ ξ [N·m] from the integral so far."""
        return self.xi @ self.to_torque.T

    def apply(self, step: LawStep, error: np.ndarray, finite: np.ndarray) -> None:
        """Add :meth:`torque` to ``step``'s unsaturated command where ``finite`` and saturate it
        again (``u``, ``u_unsat``, ``saturated`` in place, before the roll-off); then :meth:`update`
        with the tracking error ``error`` = p − p_d (n, 2) [m]. One compiled call."""
        for name in ('u', 'u_unsat', 'saturated'):
            setattr(step, name, kernel_array(getattr(step, name),
                                             np.bool_ if name == 'saturated' else np.float64))
        integral_step(self.xi, self.settings, kernel_array(error), kernel_array(finite, np.bool_),
                      step.u_unsat, step.u, step.saturated)

    def apply_and_roll_off(self, step: LawStep, z: np.ndarray, finite: np.ndarray,
                           roll_off: RollOff) -> None:
        """:meth:`apply` with the error p − p_d from the kernel rows z = [p, ṗ, p_d, …] (n, ≥ 6),
        then ``roll_off`` of ``step.u`` in place, all in one compiled call: the same arithmetic as
        :meth:`apply` followed by ``step.u = roll_off(step.u)``. ``step``'s ``u``, ``u_unsat`` and
        ``saturated`` must be arrays the kernels take (a compiled step's own)."""
        alpha, previous, has_previous = roll_off.kernel_args(step.u)
        integral_roll_off(self.xi, self.settings, z, kernel_array(finite, np.bool_), step.u_unsat,
                          step.u, step.saturated, alpha, previous, has_previous)
        roll_off.keep(step.u)

    def update(self, error: np.ndarray, saturated: np.ndarray, finite: np.ndarray) -> None:
        """One step of ξ from the error p − p_d (n, 2) [m], the (n, 2) saturation of the command
        that used it, and which fingers' inputs were finite (the rules in the class docstring)."""
        integral_update(self.xi, self.settings, kernel_array(error),
                        kernel_array(saturated, np.bool_), kernel_array(finite, np.bool_))


class ReachableIntegralAction:
    """:class:`IntegralAction` for any shape and per-input bounds (the laws' general path):

        u_I = k_i G₂(0)⁺ ξ,    ξ = ∫ Π (p_d − p) dt,    Π = G₂(0) G₂(0)⁺,

    G₂(0) (d, m) the learned input map at rest and G₂(0)⁺ its pseudo-inverse. ξ integrates only the
    part of the error the inputs can reach (Π projects onto G₂(0)'s range: all of it where G₂(0)
    has full row rank; one direction for one input and a 2-D tip), so a reference the finger cannot
    reach is not chased into saturation. The rules per finger:

    * **an input at its bound that ξ would push further** (u_unsat at or above the upper bound with
      the step raising that input, or at or below the lower one with the step lowering it): ξ is
      frozen. This is anti-windup per input and per direction: a one-sided input resting at 0
      (a chamber, a tendon) does not freeze ξ while the step would raise it;
    * **error outside the band** (‖p − p_d‖ > ``band``): ξ decays with time constant
      :data:`INTEGRAL_LEAK_S`, as :class:`IntegralAction`'s;
    * a finger whose state is not finite: ξ is left as it is (the caller gives it no u_I).

    ξ is also bounded so that each input of u_I lies within ±max(|lower|, |upper|) of that input.

    Args:
        g2_rest: (d, m) the learned G₂ at rest [m/s² per input unit], finite and not zero.
        gain: k_i [1/s³], finite and > 0.
        band: the error norm [m] inside which ξ integrates, finite and > 0.
        bounds: the inputs' bounds.
        n_fingers: number of fingers.
        dt: control period [s].
    """

    def __init__(self, g2_rest, gain: float, band: float, bounds: InputBounds, n_fingers: int,
                 dt: float) -> None:
        _check_gain_and_band(gain, band)
        g2 = np.asarray(g2_rest, dtype=float)
        if (g2.ndim != 2 or g2.shape[1] != bounds.m or not np.all(np.isfinite(g2))
                or not np.any(g2)):
            raise ValueError(f'g2_rest must be a finite, non-zero (d, {bounds.m}) input map, '
                             f'got {g2_rest!r}')
        self.gain, self.band, self.dt = float(gain), float(band), float(dt)
        self.bounds = bounds
        pinv = np.linalg.pinv(g2, rcond=1e-8)
        self.to_torque = self.gain * pinv                        # u_I = to_torque ξ  (m, d)
        self.from_torque = g2 / self.gain                        # ξ = from_torque u_I on range
        self.projector = g2 @ pinv                               # Π (d, d)
        self.limit = np.maximum(np.abs(bounds.lower), np.abs(bounds.upper))
        self.decay = math.exp(-self.dt / INTEGRAL_LEAK_S)
        self.xi = np.zeros((int(n_fingers), g2.shape[0]))        # ∫ Π (p_d − p) dt [m·s]
        self._to_torque, self._from_torque, self._projector, self._limit = (
            kernel_array(a) for a in (self.to_torque, self.from_torque, self.projector,
                                      self.limit))

    def reset(self) -> None:
        self.xi[:] = 0.0

    def kernel_args(self) -> tuple:
        """What :func:`~soft_gripper_sdre.control.kernels.general.general_feedforward_finish`
        takes for this integral: (True, ξ (updated in place), to_torque, from_torque, Π, the
        inputs' limits, Δt, band, decay)."""
        return (True, self.xi, self._to_torque, self._from_torque, self._projector, self._limit,
                self.dt, self.band, self.decay)

    def torque(self) -> np.ndarray:
        """(n, m) u_I = k_i G₂(0)⁺ ξ from the integral so far."""
        return self.xi @ self.to_torque.T

    def update(self, error: np.ndarray, u_unsat: np.ndarray, finite: np.ndarray) -> None:
        """One step of ξ from the error p − p_d (n, d) [m], the (n, m) command before clipping
        that used it (u_I included), and which fingers' inputs were finite (the class's rules)."""
        error = np.where(finite[:, None], error, 0.0)
        inside = finite & (np.einsum('nd,nd->n', error, error) <= self.band * self.band)
        step = -self.dt * error @ self.projector.T                 # Δξ = Δt Π (p_d − p)
        du = step @ self.to_torque.T                               # what it adds to each input
        b = self.bounds
        pushes = ((u_unsat >= b.upper) & (du > 0.0)) | ((u_unsat <= b.lower) & (du < 0.0))
        grow = inside & ~pushes.any(axis=1)
        self.xi[grow] += step[grow]
        leak = finite & ~inside
        self.xi[leak] *= self.decay
        u_i = self.torque()
        over = finite & np.any(np.abs(u_i) > self.limit, axis=1)
        if over.any():
            self.xi[over] = np.clip(u_i[over], -self.limit, self.limit) @ self.from_torque.T
