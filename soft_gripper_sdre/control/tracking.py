"""Task-space tracking control of the four fingers with a learned SDC model (no ROS).

:class:`TrackingController` is what the controller node wraps: it takes each finger's estimated
tip position and velocity and its reference in the finger's base frame (SI, untranslated), moves
both into the model's translated coordinates (origin at the settled rest pose, where f(0) = 0),

    x   = [X − X₀, Y − Y₀, Ẋ, Ẏ],        x_d = [X_d − X₀, Y_d − Y₀, Ẋ_d, Ẏ_d],

queries A(x), G(x) from the model for all fingers at once and applies the SDRE tracking law of
:mod:`soft_gripper_sdre.control.sdre` (u = K(x) x + K_s(x) x_d, saturated). One model serves every
finger: each finger is controlled in its own base frame with its own copy of the same dynamics.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soft_gripper_sdre.control.sdre import SdreController, SdreStep, paper_weights_si

#: named weight presets, SI (positions in m, velocities in m/s, torques in N·m)
WEIGHT_PRESETS = ('default', 'paper')


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
                raise ValueError(f'{name} must be finite and >= 0 (Q positive semi-definite), got {v!r}')
        if not np.isfinite(self.r) or self.r <= 0.0:
            raise ValueError(f'r must be finite and > 0 (R positive definite), got {self.r!r}')

    @property
    def Q(self) -> np.ndarray:
        return np.diag([self.q_pos, self.q_pos, self.q_vel, self.q_vel])

    @property
    def R(self) -> np.ndarray:
        return np.diag([self.r, self.r])


def weights_preset(name: str) -> Weights:
    """The named weights: ``'paper'`` = Q = diag(2,2,2,2), R = diag(0.1,0.1) in sim units
    (barely moves this finger), ``'default'`` = tuned for tracking on this plant."""
    if name == 'paper':
        Q, R = paper_weights_si()
        return Weights(float(Q[0, 0]), float(Q[2, 2]), float(R[0, 0]))
    if name == 'default':
        return Weights(**DEFAULT_WEIGHTS)
    raise ValueError(f'unknown weights preset {name!r}; known: {WEIGHT_PRESETS}')


#: tuned defaults (SI); see README "Noise, gains and the bending modes" for the sweep behind them
DEFAULT_WEIGHTS = dict(q_pos=1.0e6, q_vel=0.0, r=1.6e4)
#: first-order roll-off of the torque command [Hz]: cuts the loop's feed into the finger's
#: unmodelled ~59 Hz bending mode (README), well above the 3 and 9 Hz modes the model captures
DEFAULT_LOWPASS_HZ = 40.0


class RollOff:
    """First-order roll-off of a command, the same for every law:

        u_k = a u_{k−1} + (1 − a) v_k,    a = e^{−2π f Δt},    u_0 = v_0,

    with v_k the law's saturated command. f = 0 turns it off (u_k = v_k).

    Args:
        hz: corner frequency f [Hz], finite and >= 0.
        dt: control period Δt [s].
    """

    def __init__(self, hz: float, dt: float) -> None:
        if not (np.isfinite(hz) and hz >= 0.0):
            raise ValueError(f'lowpass_hz must be finite and >= 0 (0 = off), got {hz!r}')
        self.alpha = float(np.exp(-2.0 * np.pi * hz * dt)) if hz > 0 else 0.0
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
        shape = (self.n, 2)
        z = None
        if np.shape(pos) == np.shape(vel) == np.shape(ref_pos) == np.shape(ref_vel) == shape:
            try:
                z = np.concatenate((pos, vel, ref_pos, ref_vel), axis=1, dtype=float)
            except (ValueError, TypeError):
                pass
        if z is None:
            raise ValueError(f'pos, vel, ref_pos, ref_vel must each have shape {shape}, got '
                             f'{[np.shape(a) for a in (pos, vel, ref_pos, ref_vel)]}')
        z -= self._shift
        return z[:, :4], z[:, 4:]


class TrackingController:
    """SDRE tracking of every finger with one learned SDC model.

    Args:
        model: object with ``AG(x) -> (A (n,4,4), G (n,4,2))`` and ``rest_tip`` (3,) [m] (an
            :class:`soft_gripper_sdre.learning.model.SDCModel`); if it also has
            ``sdc_blocks(x) -> ([A21 A22] (n,2,4), G2 (n,2,2))``, only those lower rows are used.
        weights: SDRE weights (SI).
        u_max: torque saturation per input [N·m].
        n_fingers: number of fingers controlled together.
        method: ``'fast'`` (batched warm-started Newton–Kleinman) or ``'reference'`` (scipy).
        lowpass_hz, dt: the command's :class:`RollOff` (0 = off) and the control period [s].
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3) -> None:
        self.model = model
        self.weights = weights
        self.n_fingers = int(n_fingers)
        try:
            self.frame = RestFrame(model.rest_tip, self.n_fingers)
        except ValueError:
            raise ValueError(f'model.rest_tip must hold a finite rest position, got {model.rest_tip!r}') from None
        self.sdre = SdreController(weights.Q, weights.R, u_max, n=self.n_fingers, method=method)
        self._blocks = getattr(model, 'sdc_blocks', None)
        self.roll_off = RollOff(lowpass_hz, dt)

    @property
    def origin(self) -> np.ndarray:
        """(2,) rest tip position the model's coordinates are translated by [m]."""
        return self.frame.origin

    def reset(self) -> None:
        """Forget warm starts, last valid gains and the filter state (e.g. after a clock jump)."""
        self.sdre.reset()
        self.roll_off.reset()

    def compute(self, pos: np.ndarray, vel: np.ndarray, ref_pos: np.ndarray,
                ref_vel: np.ndarray) -> SdreStep:
        """Torques for every finger.

        Args:
            pos, vel: (n, 2) estimated tip position [m] and velocity [m/s] in each base frame.
            ref_pos, ref_vel: (n, 2) reference position and velocity, same frames.

        Returns:
            the SDRE step (``u`` (n, 2) [N·m], gains, checks, fallbacks).
        """
        x, xd = self.frame.states(pos, vel, ref_pos, ref_vel)   # f(0) = 0 at rest
        if self._blocks is not None:                 # a model in SDC form: only its lower rows
            out = self.sdre.step_sdc(*self._blocks(x), x, xd)
        else:
            out = self.sdre.step(*self.model.AG(x), x, xd)
        # keeps the loop from feeding the finger's unmodelled bending modes (README, "Noise")
        out.u = self.roll_off(out.u)
        return out
