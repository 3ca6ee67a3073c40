"""The SDRE feedback laws: the paper's (:class:`SdreLaw`) and one with a state-dependent Q(x)."""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.kernels import compiled_network
from soft_gripper_sdre.control.laws.registry import (
    WEIGHT_PARAMS,
    LawParam,
    LawSettings,
    register_law,
)
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    LawIO,
    LawStep,
    Weights,
    shape_of,
)
from soft_gripper_sdre.sim.shape import InputBounds


class SdreLaw:
    """The paper's law: SDRE tracking of every finger with one learned SDC model.

    Moves the estimates and the reference into the model's translated coordinates, queries A(x),
    G(x) for all fingers at once and applies :class:`~soft_gripper_sdre.control.sdre.SdreController`
    (u = K(x) x + K_s(x) x_d, saturated), then the roll-off. One model serves every finger: each is
    controlled in its own base frame with its own copy of the same dynamics. On the fast path a
    model with ``fused_network`` is evaluated inside the compiled step
    (:meth:`~soft_gripper_sdre.control.sdre.SdreController.track`).

    Args:
        model: object with ``AG(x) -> (A (n, 2d, 2d), G (n, 2d, m))`` and ``rest_tip`` (3,) [m]
            (an :class:`soft_gripper_sdre.learning.model.SDCModel`); if it also has
            ``sdc_blocks(x) -> ([A21 A22] (n, d, 2d), G2 (n, d, m))``, only those lower rows are
            used,
            and if it has ``fused_network`` (the layers
            :class:`~soft_gripper_sdre.control.kernels.SdcNetwork` packs), the compiled step
            evaluates it.
        weights: SDRE weights (SI).
        u_max: torque saturation per input [N·m].
        n_fingers: number of fingers controlled together.
        method: ``'fast'`` (the compiled kernels) or ``'reference'`` (scipy).
        lowpass_hz, dt: the command's :class:`~soft_gripper_sdre.control.tracking.RollOff` (0 = off)
            and the control period [s].
        bounds: per-input [lower, upper] (None: ±``u_max`` on each of the model's inputs).

    Any shape (d, m) (:func:`~soft_gripper_sdre.control.tracking.shape_of`): the state is 2d, the
    weights ``weights.Q(d)``, ``weights.R(m)``, and u = K x + K_s x_d with K, K_s (m, 2d) (eq.
    22–24 as they stand); off the hand's path
    (:func:`~soft_gripper_sdre.control.tracking.hand_path`) the supervisor runs the general path
    (with ``method='fast'`` the general kernels, network included, unless ``compiled`` is False:
    numpy).
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ,
                 dt: float = 1e-3, bounds: InputBounds | None = None,
                 compiled: bool = True) -> None:
        self.model = model
        self.weights = weights
        shape = shape_of(model)
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape, bounds)
        if self.io.hand:
            self.sdre = SdreController(weights.Q, weights.R, self.io.u_max,
                                       n=self.io.n_fingers, method=method)
        else:
            self.sdre = SdreController(*weights.for_shape(shape), u_max, n=self.io.n_fingers,
                                       method=method, bounds=self.io.bounds, compiled=compiled)
        self._blocks = getattr(model, 'sdc_blocks', None)
        self.network = (compiled_network(model) if self.sdre.fast or self.sdre.general_kernels
                        else None)

    @property
    def origin(self) -> np.ndarray:
        """(d,) rest tip position the model's coordinates are translated by [m]."""
        return self.io.origin

    def reset(self) -> None:
        """Forget warm starts, last valid gains and the filter state (e.g. after a clock jump)."""
        self.sdre.reset()
        self.io.reset()

    def compute(self, pos: np.ndarray, vel: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray,
                ref_acc: np.ndarray | None = None) -> LawStep:
        """Torques for every finger (the law does not use ``ref_acc``).

        Args:
            pos, vel: (n, d) estimated tip position [m] and velocity [m/s] in each base frame.
            ref_pos, ref_vel: (n, d) reference position and velocity, same frames.

        Returns:
            the SDRE step (``u`` (n, m), gains, checks, fallbacks).
        """
        frame = self.io.frame
        if self.network is not None:                 # the compiled step, network included
            z = frame.stacked(pos, vel, ref_pos, ref_vel)
            out = (self.sdre.track(self.network, frame.origin, z) if self.io.hand
                   else self.sdre.track_general(self.network, frame.origin, z))
        else:
            x, xd = frame.states(pos, vel, ref_pos, ref_vel)   # f(0) = 0 at rest
            if self._blocks is not None:             # a model in SDC form: only its lower rows
                out = self.sdre.step_sdc(*self._blocks(x), x, xd)
            else:
                out = self.sdre.step(*self.model.AG(x), x, xd)
        # keeps the loop from feeding the finger's unmodelled bending modes (README, "Noise")
        out.u = self.io.roll_off(out.u)
        return out


class AdaptiveSdreLaw:
    """The learned SDRE with a state-dependent position weight (the paper's future work):

        Q(x) = diag(q(e), q(e), q_vel, q_vel),   q(e) = q_pos · (1 + (‖e‖ / e_ref)²),  e = p_d − p,

    capped at ``gain_max`` · q_pos. A large tracking error (the fast phases, where the model's
    errors show up as lag) raises the gain; near the reference the loop stays at the default,
    noise-friendly weight. R stays fixed (only the ratio Q/R matters). All fingers share one Q per
    step: the largest finger error sets it. The gain is quantised to 1/8 octaves, one
    :class:`SdreLaw` (roll-off off) per level, so each level keeps its own warm start; the roll-off
    is applied here, once, to whichever level answered.
    """

    def __init__(self, model, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 e_ref: float = 1e-3, gain_max: float = 4.0,
                 bounds: InputBounds | None = None) -> None:
        self.io = LawIO(model.rest_tip, u_max, n_fingers, lowpass_hz, dt, shape_of(model), bounds)
        self.bounds = bounds
        if not (np.isfinite(e_ref) and e_ref > 0 and np.isfinite(gain_max) and gain_max >= 1):
            raise ValueError(f'e_ref must be > 0 and gain_max >= 1, got {e_ref!r}, {gain_max!r}')
        self.model, self.weights, self.method = model, weights, method
        self.e_ref, self.gain_max = float(e_ref), float(gain_max)
        self._levels: dict[float, SdreLaw] = {}
        self.gain = 1.0

    def _controller(self, gain: float) -> SdreLaw:
        level = round(float(np.log2(gain)) * 8) / 8
        if level not in self._levels:
            w = Weights(self.weights.q_pos * 2 ** level, self.weights.q_vel, self.weights.r)
            self._levels[level] = SdreLaw(self.model, w, self.io.u_max,
                                          n_fingers=self.io.n_fingers, method=self.method,
                                          lowpass_hz=0.0, bounds=self.bounds)
        return self._levels[level]

    def reset(self) -> None:
        self.io.reset()
        for c in self._levels.values():
            c.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        """Torques for every finger (the law does not use ``ref_acc``)."""
        e = np.linalg.norm(np.asarray(ref_pos, float) - np.asarray(pos, float), axis=1)
        e_max = float(np.max(np.where(np.isfinite(e), e, 0.0)))
        self.gain = min(1.0 + (e_max / self.e_ref) ** 2, self.gain_max)     # q(e) / q_pos
        out = self._controller(self.gain).compute(pos, vel, ref_pos, ref_vel)
        out.u = self.io.roll_off(out.u)
        return out


#: ``state_weights``: the ``sdre`` law's ``adaptive`` option
STATE_WEIGHTS = LawParam('state_weights', False, 'state-dependent Q(x) that rises with the '
                         'tracking error', option='adaptive', strict=True)


def _sdre(s: LawSettings, adaptive: bool = False):
    law = AdaptiveSdreLaw if adaptive else SdreLaw
    return law(s.model, s.weights, s.u_max, n_fingers=s.n_fingers, method=s.method,
               lowpass_hz=s.lowpass_hz, dt=s.dt, bounds=s.bounds)


register_law('sdre', _sdre, params=(*WEIGHT_PARAMS, STATE_WEIGHTS), graph=True,
             summary="the paper's learned SDRE", meanings={'adaptive': 'state-dependent weights '
                                                           'Q(x)'})
