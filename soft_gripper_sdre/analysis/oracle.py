"""The oracle laws: the SDRE on the simulator's true dynamics, an evaluation yardstick.

A(x), G(x) come from :func:`soft_gripper_sdre.sim.dynamics.oracle_sdc` at the plant's joint state
(projected onto the chain's static shapes; ``oracle_exact``: the paper's eq. 10–13 with the
instantaneous G₂ = J M⁻¹ B), which the caller hands over each step with ``observe(truth)`` (the
in-process loop, :func:`~soft_gripper_sdre.analysis.closed_loop.run_closed_loop`, does; the node
graph does not carry the 10-joint state at the loop rate). The state fed back is the same estimate
the other laws get.

Importing this module registers ``oracle``, ``oracle_exact`` and ``oracle_ff`` with
:func:`soft_gripper_sdre.control.laws.make_law`.
"""
from __future__ import annotations

import numpy as np

from soft_gripper_sdre.control.laws import LawSettings, register_law
from soft_gripper_sdre.control.laws.feedforward import combine_feedforward
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    LawIO,
    LawStep,
    Weights,
    hand_path,
)
from soft_gripper_sdre.sim.dynamics import FingerDynamics, oracle_sdc
from soft_gripper_sdre.sim.shape import HAND_SHAPE, ShapeError

#: the law names this module registers
ORACLE_LAWS = ('oracle', 'oracle_exact', 'oracle_ff')


class OracleSdreLaw:
    """The SDRE tracking law (eq. 22) with A(x), G(x) from the simulator's exact dynamics.

    Call :meth:`observe` with the plant's joint state (``SimTruth``: q, q̇ (n, 10)) before each
    :meth:`compute`. ``reduced``: the SDC pair projected on the static shapes (else the exact
    eq. 10–13). Holds a PyBullet client: :meth:`close` it.
    """

    def __init__(self, rest_tip, weights: Weights, u_max: float, n_fingers: int = 4,
                 method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
                 reduced: bool = True) -> None:
        self.io = LawIO(rest_tip, u_max, n_fingers, lowpass_hz, dt)
        self.n_fingers = self.io.n_fingers
        self.reduced = bool(reduced)
        self.dynamics = FingerDynamics()
        self.sdre = SdreController(weights.Q, weights.R, u_max, n=self.n_fingers, method=method)
        self._AG = None

    def reset(self) -> None:
        self.io.reset()
        self.sdre.reset()
        self._AG = None

    def observe(self, truth) -> None:
        """Evaluate the true SDC pair at the plant's joint state (``truth.q``, ``truth.qd``)."""
        A = np.zeros((self.n_fingers, 4, 4))
        G = np.zeros((self.n_fingers, 4, 2))
        for i in range(self.n_fingers):
            A[i], G[i] = oracle_sdc(self.dynamics.evaluate(truth.q[i], truth.qd[i]), self.io.origin,
                                    reduced=self.reduced)
        self._AG = (A, G)

    def _observed(self):
        if self._AG is None:
            raise RuntimeError(f'{type(self).__name__}.compute needs observe(truth) first '
                               '(the plant state)')
        return self._AG

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        """Torques for every finger (the law does not use ``ref_acc``)."""
        A, G = self._observed()
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        out = self.sdre.step(A, G, x, xd)
        step = self.io.finish(out.u_unsat, finite)
        step.ok, step.fallback = out.ok & finite, out.fallback | ~finite
        step.failed_checks, step.residual = out.failed_checks, out.residual
        return step

    def close(self) -> None:
        self.dynamics.close()


class OracleFeedforwardLaw(OracleSdreLaw):
    """:class:`~soft_gripper_sdre.control.laws.SdreFeedforwardLaw` on the oracle's true (projected)
    SDC pair, which exists only at the plant's state:
    u = G₂(q)⁻¹ (a_d − [A(q) x_d]₃,₄) + K(q)(x − x_d)."""

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None) -> LawStep:
        A, G = self._observed()
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        step = self.sdre.step(A, G, x - xd, np.zeros_like(xd))           # u_unsat = K(q) e
        return combine_feedforward(self.io, step, A[:, 2:, :], G[:, 2:, :], xd, finite, ref_acc)


def _oracle(s: LawSettings, law=OracleSdreLaw, reduced: bool = True) -> OracleSdreLaw:
    if s.bounds is not None and not hand_path(HAND_SHAPE, s.bounds):
        raise ShapeError(f'the oracle laws are the simulated hand\'s (±u_max on both inputs); '
                         f'got bounds {s.bounds}')
    u_max = s.u_max if s.bounds is None else s.bounds.symmetric_limit
    return law(s.model.rest_tip, s.weights, u_max, n_fingers=s.n_fingers, method=s.method,
               lowpass_hz=s.lowpass_hz, dt=s.dt, reduced=reduced)


def register_oracle_laws() -> None:
    """Make :data:`ORACLE_LAWS` known to :func:`~soft_gripper_sdre.control.laws.make_law` (a tool
    that runs them calls this first; calling it again changes nothing)."""
    register_law('oracle', _oracle)
    register_law('oracle_exact', lambda s: _oracle(s, reduced=False))
    register_law('oracle_ff', lambda s: _oracle(s, law=OracleFeedforwardLaw))
