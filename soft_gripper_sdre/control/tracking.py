"""What every tracking law shares (no ROS): weights, the step type, the protocol, and the plumbing
around each law's own arithmetic.

Every law takes each finger's estimated tip position and velocity and its reference in the
finger's base frame (SI, untranslated) and works in the model's translated coordinates (origin at
the settled rest pose, where f(0) = 0),

    x   = [X − X₀, Y − Y₀, Ẋ, Ẏ],
    x_d = [X_d − X₀, Y_d − Y₀, Ẋ_d, Ẏ_d]       (:class:`RestFrame`),

saturates its torques at ``u_max`` and passes them through the same first-order roll-off
(:class:`RollOff`), so laws differ only in their own arithmetic. The laws are in
:mod:`soft_gripper_sdre.control.laws`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from soft_gripper_sdre.control.riccati import Check
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE


@dataclass(frozen=True)
class Weights:
    """Diagonal SDRE weights in SI: Q = diag(q_pos, q_pos, q_vel, q_vel), R = diag(r, r)."""

    q_pos: float
    q_vel: float
    r: float

    def __post_init__(self) -> None:
        for name in ('q_pos', 'q_vel'):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0.0:
                raise ValueError(f'{name} must be finite and >= 0 (Q positive semi-definite), '
                                 f'got {v!r}')
        if not np.isfinite(self.r) or self.r <= 0.0:
            raise ValueError(f'r must be finite and > 0 (R positive definite), got {self.r!r}')

    @property
    def Q(self) -> np.ndarray:
        return np.diag([self.q_pos, self.q_pos, self.q_vel, self.q_vel])

    @property
    def R(self) -> np.ndarray:
        return np.diag([self.r, self.r])


def paper_weights_si() -> tuple[np.ndarray, np.ndarray]:
    """The paper's Q = diag(2,2,2,2), R = diag(0.1,0.1) (sim units) in SI.

    Positions and velocities scale by 20 (x_sim = 20 x_si) and torques by 400, so the cost
    x_simᵀ Q_sim x_sim + u_simᵀ R_sim u_sim equals
    x_siᵀ (400 Q_sim) x_si + u_siᵀ (160000 R_sim) u_si.
    """
    return (LENGTH_SCALE**2 * np.diag([2.0, 2.0, 2.0, 2.0]),
            TORQUE_SCALE**2 * np.diag([0.1, 0.1]))


#: tuned defaults (SI); docs/results.md "Noise, gains and the finger's bending modes" has the sweep
#: behind them
DEFAULT_WEIGHTS = dict(q_pos=1.0e6, q_vel=0.0, r=1.6e4)
#: first-order roll-off of the torque command [Hz]: cuts the loop's feed into the finger's
#: unmodelled ~59 Hz bending mode (README), well above the 3 and 9 Hz modes the model captures
DEFAULT_LOWPASS_HZ = 40.0
#: the roll-off's corner is at most this fraction of the sampling rate 1/Δt
#: (:func:`roll_off_corner_hz`)
ROLL_OFF_RATE_FRACTION = 0.1


def roll_off_corner_hz(hz: float, dt: float) -> float:
    """The corner the roll-off uses at control period ``dt`` [s]: ``hz``, or a tenth of the sampling
    rate where that is lower, min(hz, 0.1 / dt); 0 (off) stays 0.

    The command is held for a whole period, which lags the loop by about Δt/2. With a corner fixed
    in Hz, that lag destabilises the finger's unmodelled ~23 Hz bending mode at long periods, a mode
    the 40 Hz corner hardly attenuates (docs/design/control_period.md). A corner at a tenth of the
    sampling rate cuts that mode harder the longer the period; up to 2.5 ms the cap is above 40 Hz
    and the default corner is the one asked for.

    Raises:
        ValueError: ``hz`` is not finite and >= 0, or ``dt`` is not finite and > 0.
    """
    if not (np.isfinite(hz) and hz >= 0.0):
        raise ValueError(f'lowpass_hz must be finite and >= 0 (0 = off), got {hz!r}')
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f'the control period dt must be finite and > 0 s, got {dt!r}')
    return float(min(hz, ROLL_OFF_RATE_FRACTION / dt)) if hz > 0 else 0.0


class RollOff:
    """First-order roll-off of a command, the same for every law:

        u_k = a u_{k−1} + (1 − a) v_k,    a = e^{−2π f Δt},    u_0 = v_0,

    with v_k the law's saturated command and f the corner asked for, capped at a tenth of the
    sampling rate (:func:`roll_off_corner_hz`). f = 0 turns it off (u_k = v_k).

    Args:
        hz: corner frequency asked for [Hz], finite and >= 0.
        dt: control period Δt [s], finite and > 0.

    ``hz`` is the corner in use [Hz].
    """

    def __init__(self, hz: float, dt: float) -> None:
        self.hz = roll_off_corner_hz(hz, dt)
        self.alpha = float(np.exp(-2.0 * np.pi * self.hz * dt)) if self.hz > 0 else 0.0
        self._beta = 1.0 - self.alpha
        self._u = None

    def reset(self) -> None:
        """Forget the filter state: the next output is the next input."""
        self._u = None

    def __call__(self, v: np.ndarray) -> np.ndarray:
        if self.alpha > 0.0:
            v = v if self._u is None else self.alpha * self._u + self._beta * v
            self._u = v
        return v

    def kernel_args(self, v: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """(α, the previous output, whether there is one) for a compiled step that rolls off ``v``
        in place as :meth:`__call__` would, with 1 − α formed as here (before the first output the
        previous one is ``v`` itself, unused); then :meth:`keep` the result."""
        return self.alpha, v if self._u is None else self._u, self._u is not None

    def keep(self, u: np.ndarray) -> None:
        """``u`` was rolled off in place (:meth:`kernel_args`): it is the filter's last output."""
        if self.alpha > 0.0:
            self._u = u


class RestFrame:
    """The model's translated coordinates: origin at the settled rest tip p₀, where f(0) = 0.

        x = [p − p₀, ṗ],    x_d = [p_d − p₀, ṗ_d]

    Args:
        rest_tip: the model's rest tip position (at least X₀, Y₀) [m].
        n: number of fingers.
    """

    def __init__(self, rest_tip, n: int) -> None:
        rest = np.asarray(rest_tip, dtype=float).reshape(-1)
        if rest.size < 2 or not np.all(np.isfinite(rest[:2])):
            raise ValueError(f'rest_tip must hold a finite rest position, got {rest_tip!r}')
        self.origin = rest[:2].copy()
        self.n = int(n)
        # [p₀, 0, p₀, 0] for every finger (an array of z's shape: no broadcasting in z −= shift)
        self._shift = np.tile(np.concatenate([self.origin, [0.0, 0.0]] * 2), (self.n, 1))

    def states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray]:
        """(x, x_d), each (n, 4), from (n, 2) positions and velocities in the base frames.

        Raises:
            ValueError: when an input is not (n, 2).
        """
        z = self.stacked(pos, vel, ref_pos, ref_vel)
        z -= self._shift
        return z[:, :4], z[:, 4:]

    def stacked(self, *arrays) -> np.ndarray:
        """The (n, 2) arrays side by side as one new (n, 2k) float64 array: [pos, vel, ref_pos,
        ref_vel, …] in the order given (the rows the compiled kernels take).

        Raises:
            ValueError: when one is not (n, 2) (named as the law's inputs pos, vel, ref_pos,
                ref_vel).
        """
        z = None
        shape = (self.n, 2)
        if all(np.shape(a) == shape for a in arrays):
            try:
                z = np.concatenate(arrays, axis=1, dtype=float)
            except (ValueError, TypeError):
                pass
        if z is None:
            raise ValueError(f'pos, vel, ref_pos, ref_vel must each have shape {shape}, got '
                             f'{[np.shape(a) for a in arrays]}')
        return z


@dataclass
class LawStep:
    """One step of a law for n fingers. The SDRE laws also fill the last four fields."""

    u: np.ndarray                # (n, 2) saturated, rolled-off torques [N·m], always finite
    u_unsat: np.ndarray          # (n, 2) before saturation
    ok: np.ndarray               # (n,) the law's own checks passed
    fallback: np.ndarray         # (n,) a fallback was used (last valid gains, zero, no feedforward)
    failed_checks: np.ndarray    # (n,) int bitmask of :class:`Check` (0 for laws without checks)
    saturated: np.ndarray        # (n, 2)
    residual: np.ndarray         # (n,) relative Riccati residual (0 for closed-form laws)
    K: np.ndarray | None = None              # (n, 2, 4) SDRE gains in use
    Ks: np.ndarray | None = None             # (n, 2, 4)
    P: np.ndarray | None = None              # (n, 4, 4) Riccati solution (NaN where it failed)
    nk_iterations: np.ndarray | None = None  # (n,) Newton–Kleinman iterations (0 = exact solve)


class Law(Protocol):
    """A control law for n fingers: what the controller node, the in-process loop and the tools
    call.

    A law that needs the plant's ground truth (the oracles,
    :mod:`soft_gripper_sdre.analysis.oracle`) also has ``observe(truth)``, which the in-process
    loop calls before each :meth:`compute`.
    """

    def compute(self, pos: np.ndarray, vel: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray,
                ref_acc: np.ndarray | None = None) -> LawStep:
        """Torques for every finger from (n, 2) tip positions [m] and velocities [m/s], their
        references, and the reference acceleration [m/s²] (used by the feedforward laws;
        None = 0)."""

    def reset(self) -> None:
        """Forget all state (warm starts, last valid gains, the filter), e.g. after a clock jump."""


class LawIO:
    """The plumbing a law composes around its own arithmetic: the translated states in (non-finite
    rows zeroed), saturation at ``u_max`` and the :class:`RollOff` out.

    Args:
        rest_tip: the model's rest tip position (at least X₀, Y₀) [m].
        u_max: torque saturation [N·m], finite and > 0.
        n_fingers: number of fingers.
        lowpass_hz, dt: the roll-off's corner frequency [Hz] (0 = off) and the control period [s].
    """

    def __init__(self, rest_tip, u_max: float, n_fingers: int, lowpass_hz: float,
                 dt: float) -> None:
        self.frame = RestFrame(rest_tip, n_fingers)
        if not (np.isfinite(u_max) and u_max > 0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max!r}')
        self.u_max = float(u_max)
        self.n_fingers = int(n_fingers)
        self.roll_off = RollOff(lowpass_hz, dt)

    @property
    def origin(self) -> np.ndarray:
        """(2,) rest tip position the model's coordinates are translated by [m]."""
        return self.frame.origin

    def reset(self) -> None:
        self.roll_off.reset()

    def states(self, pos, vel, ref_pos, ref_vel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, x_d, finite) in translated coordinates; non-finite rows are zeroed."""
        x, xd = self.frame.states(pos, vel, ref_pos, ref_vel)
        finite = np.isfinite(x).all(axis=1) & np.isfinite(xd).all(axis=1)
        if not finite.all():
            x[~finite] = 0.0
            xd[~finite] = 0.0
        return x, xd, finite

    def finish(self, u_unsat: np.ndarray, finite: np.ndarray) -> LawStep:
        """The step of a law without Riccati checks: u_unsat zeroed where not finite, saturated,
        rolled off; a non-finite finger is flagged (NONFINITE) and counts as a fallback."""
        u_unsat = np.where(np.isfinite(u_unsat) & finite[:, None], u_unsat, 0.0)
        u = self.roll_off(np.clip(u_unsat, -self.u_max, self.u_max))
        saturated = np.abs(u_unsat) > self.u_max
        return LawStep(u=u, u_unsat=u_unsat, ok=finite.copy(), fallback=~finite,
                       failed_checks=np.where(finite, 0, int(Check.NONFINITE)), saturated=saturated,
                       residual=np.zeros(self.n_fingers))
