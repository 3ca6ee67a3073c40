"""Estimator and controller settings derived from a finger's own data, checked in closed loop.

The shipped parameters were tuned on the package's own finger at 1 kHz. A finger that is stiffer,
softer, slower, noisier or sampled at another rate needs others, and everything they depend on
is in the identification data and the model learned from it:

=================  ==================================================================
setting            from
=================  ==================================================================
control_period     the median tip period of the recordings
meas_std           the measurement noise σ of the settle phase
accel_psd          the estimator's white-acceleration intensity, picked in the check
                   among fractions of the value that best explains the recorded tips
torque_limit       ``data_facts.TORQUE_MARGIN`` × the largest torque of the excitation
q_pos, r           a closed-loop bandwidth f_c through the learned input map at rest:
                   for ẍ ≈ G₂u, LQR places each direction i at ω_i = (q_pos s_i² / r)^¼
                   (s_i the singular values of G₂(0)), so with r = 1/u_max² the weights
                   q_pos = r ω_c⁴ / (s₁ s₂) put their geometric mean at ω_c = 2π f_c
torque_lowpass_hz  :data:`ROLL_OFF_RATIO` · max(f_c, the model's fastest oscillating mode at rest)
                   (capped at a tenth of the rate by the law): a roll-off near a lightly
                   damped mode the loop does not dominate adds its lag there, and the loop
                   rings (the tendon finger at 2 Hz: 300 % of travel with 8 Hz, 2.5 % with 20)
integral_gain      k_i = ω_c³ / d, d in :data:`INTEGRAL_DIVISORS` (picked in the check: the
                   corner a decade under the loop's, or nearer); band :data:`BAND_TRAVEL` of
                   the travel (≥ 10 σ): the whole move, so the integral acts on the offset a
                   finger's gain difference from its pooled model leaves (half the travel and
                   more in the gain-error runs). A narrower band freezes the integral exactly
                   there (``tendon3`` in process: 31 / 14 % of travel with a tenth of it, 5.2 /
                   3.7 % with all of it). The recipe's plan has no contact; a grasp that presses
                   into an object sets ``integral_band`` below the depth it presses
pd_kp, pd_kd       ω_c² and 2 ζ ω_c with ζ = :data:`PD_DAMPING`, for ``pd``
rest_samples       the trajectory node's rest pose, the mean of :data:`REST_SECONDS` of tips
                   (one message's noise is a hold a slack finger must be pulled or bent to)
feedforward_at     ``ref``: the feedforward inverts the model on the reference. Evaluated
                   at the estimate, a model that depends on velocity (friction) turns the
                   estimate's noise into torque; on the tendon finger's model that alone
                   made every loop above 1 Hz diverge in the check
=================  ==================================================================

The bandwidth, the estimator's intensity and the integral gain are chosen by simulation
(:func:`derive`), from the slowest bandwidth up to the first at which every intensity diverges: each
candidate runs the default law on the learned model itself, with the measured noise on the
tips, the estimator in the loop and the command applied one period late (a driver that applies
the newest command at its next tick), along a move of the travel the data reached
(:func:`check_move`). At each bandwidth every intensity is then tried with the stronger
integral gains. A candidate is kept when it tracks within :data:`KEEP_NOMINAL` of the travel,
does not diverge, never saturates while the finger is held at rest, and still tracks within
:data:`KEEP_ROBUST` when the model's input gain is off by the factors in :data:`GAIN_ERRORS` (the
real finger is not the model: two fingers that share one model differ from it both ways). Its
score is the worst error of its nominal run, the runs with the input gain lowered and its runs on
the fingers' own fits (below); the bandwidths are tried an octave apart, then the best one's
neighbours half an octave either side (:data:`REFINE_STEP`); the lowest score wins, and then the
next lower bandwidth when it scores within :data:`PREFER_SLOWER` of it, for margin against what
the model does not know. No loop is tried at or above the slowest mode of the fingers' own fits
(below; any fit, with a lag or without): a loop that fast must shape a mode only the recordings
know (``trunk3``'s model puts the bending modes at 10 Hz, the fits at 4.8–5.5 Hz as the fingers
have them; a 5.66 Hz loop the model passed missed finger a's move by 115 % over DDS).

The two kinds of gain-error run measure different things. With the gain lowered the finger lags
its feedforward by the offset a gain difference leaves, which the feedback of a loop slower than
the finger's own spring barely corrects and the integral removes only as fast as its corner
along the move: that is what the fingers show (``trunk3`` in process, a 3.47 mm shortening at
4 Hz: 5.7 / 5.4 % of travel where that run gave 21 %, 4.3 / 4.1 % where it gave 16 %, about a
quarter of it at every bandwidth and integral tried). With the gain raised the loop has more
gain than it was designed for: that run tests the margin, and its error beyond the same offset
is the model's own modes ringing, which a finger need not share (26 % on that model with the
integral ω_c³, where both fingers tracked within 4.3 %). It bounds the candidate
(:data:`KEEP_ROBUST`) but does not rank it: ranked by it, the weaker integral that leaves the
offset won. Every intensity is run with every integral gain, since the smoothest estimator,
best on the model, leaves the least margin for a strong integral (``trunk3``: 99 % with the
gain doubled, against 26 % with the likelihood-best one).

A bandwidth holds only when its loop with the weakest integral diverges, on the model or with
the input gain off, neither with the likelihood-best intensity nor with the one a decade under it
(:data:`MARGIN_INTENSITIES`): the intensity is picked on a model that has neither the finger's
noise nor the modes the data did not excite, and a loop whose stability is lost with an estimator
a decade off the data's is at the edge of what the model supports. On ``trunk3`` the model puts
the bending modes at 10 Hz where the fingers have them at 4.4–5.1 Hz; at 8 Hz the two smoother
intensities diverged with the gain doubled while the likelihood-best one tracked within 7.4 %,
and that loop drove both fingers' bending modes (245 / 165 % of travel). The smoothest
intensity alone does not count: on ``tendon3`` at 4 Hz it diverged with the gain doubled where
the other two kept their margin, and that bandwidth holds both fingers within 3.2 %.

A finger whose actuator delivers its command through a lag (a pneumatic chamber filling through
its valve) has a state the SDC form has no room for: the model learns the lag as slowness and
damping, and settings that track within 1 % on it ring on the fingers (``pneumatic1``: 70 % and
56 % of travel at 2 Hz). Each finger's own linear fit with a first-order input lag
(:mod:`~soft_gripper_sdre.analysis.finger_fits`, fitted to its recordings by the training tool)
sees it: when a lag makes the fit run free closer to the finger's validation recordings, every
candidate the robustness runs try is also run on that fit, kept only within
:data:`KEEP_ROBUST` and scored by it too (``pneumatic1``: 1.41 Hz and the strongest integral are
chosen, 3.5 % / 3.1 % of travel on the fingers in process, where the model's runs alone chose a
2 Hz loop that rings on them). A fit without a lag is not used: its
linear statics are not the finger's across the move (``tendon3``'s index fit misses every
candidate's move by 75 % where the finger tracks within 5 %), and the model's gain-error runs
already stand for the fingers' differences.

A finger whose motion follows its inputs later than its model's does (a dead time the model
does not have) can ring under settings a check without that delay passed. The check therefore
applies its commands as much later again as the recordings show (:func:`unmodelled_delay`: the
lag of the peak of the cross-correlation of the recorded tip velocity with the model's free run
under the same inputs, :attr:`DataFacts.input_delay`), in whole periods. The hand's shape with
two-sided inputs keeps the one period of its rule.

The move goes along the direction the finger moved most in the identification data (the
principal axis of its tips about the rest pose, turned toward +Y:
:func:`~soft_gripper_sdre.analysis.data_facts.closing_direction`), the way it bends when driven.
Two inputs whose tip directions are close (12–13° on both foreign fingers) move the tip across
that axis only with opposing torques, far larger than the excitation's: a move along pure +Y,
35–50° off the axis on those fingers, is out of the limit's range beyond a fraction of a
millimetre, and a check along it measures saturation, not the settings. The move's travel is the
smaller of ``data_facts.TRAVEL_SHARE`` of the data's reach along the direction and the largest
displacement the learned model holds still there with ``holding.HOLD_SHARE`` of the torque limit
(:func:`~soft_gripper_sdre.analysis.holding.holdable_travel`: at rest the model needs
u = −G₂(x)⁻¹ (A(x)x)₂). When no candidate passes along it, the search is made again along
:data:`TRAVEL_SHRINK` of it: near the edge of its data a learned model can hold still yet snap
in motion (the tendon finger's model, 2 mm out along its axis, jumps 1 mm under every loop, and
the check fails at every bandwidth by 8–9 % of a 3.7 mm move; at 1.85 mm it passes). Below
:data:`MIN_TRAVEL_NOISE` σ of measurement noise no move is checked and nothing is derived
(:attr:`Derivation.reason`). The trajectory node closes along it with
``close_distance`` and ``side_distance``, the travel's Y and X parts (:meth:`DataFacts.move`).

The settings are the default law's. The paper's law weighs the torque that holds the finger
against its spring in its cost, so it stops short of a held move by a share set by the loop's
bandwidth against the finger's stiffness (:func:`paper_law_offset`); :func:`paper_law_bandwidth`
says how fast a loop it needs, and the derivation reports both (:attr:`Derivation.paper_law`).
"""
from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
import math
import multiprocessing
import os

import numpy as np

from soft_gripper_sdre.analysis import model_fitness
from soft_gripper_sdre.analysis.data_facts import DataFacts
from soft_gripper_sdre.analysis.finger_fits import LinearFinger, LinearFingerPlant
from soft_gripper_sdre.analysis.holding import (
    HOLD_SHARE,
    EquilibriumCurve,
    actuator_bounds,
    equilibrium_curve,
    hold_bounds,
    hold_torques,
    holdable_travel,
    loop_bounds,
)
from soft_gripper_sdre.analysis.model_fitness import model_shape, rk4_step
from soft_gripper_sdre.control.kernels import warm_up_check_loop
from soft_gripper_sdre.control.kernels.check_loop import (
    LINEAR_PLANT,
    NETWORK_PLANT,
    feedforward_check_steps,
)
from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.laws.feedforward import HandKernelParts
from soft_gripper_sdre.control.riccati import sdre_gains
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory
from soft_gripper_sdre.sim.shape import HAND_SHAPE, InputBounds, ShapeError

#: closed-loop bandwidths tried [Hz], kept below a :data:`RATE_FRACTION` of the sampling rate
BANDWIDTHS_HZ = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
RATE_FRACTION = 1 / 20
#: the search then tries the best bandwidth's neighbours this factor either side (half an octave)
REFINE_STEP = math.sqrt(2.0)
#: estimator intensities tried, as fractions of the likelihood-best one
ACCEL_PSD_FRACTIONS = (1.0, 0.1, 0.01)
#: a bandwidth holds when its loop with the weakest integral diverges with none of these first
#: intensities: the likelihood-best one and a decade under it (module doc)
MARGIN_INTENSITIES = 2
ROLL_OFF_RATIO = 4.0
#: integral gains tried, k_i = ω_c³ / divisor: the corner a decade under the loop's first, then
#: nearer it (a stronger integral absorbs more of the model's gain error while a move goes on).
#: Along a move where the finger's own spring κ is stiffer than the loop (ω_c² < κ) the corner
#: is k_i / (ω_c² + κ): at the last divisor ``trunk3``'s shortening ω_c / 4, ``flexor2``'s
#: 0.7 Hz loop on its 2.3 Hz model 0.7 ω_c. The divisors under 0.5 are for such stiff fingers:
#: with them the check keeps the loop that takes the offset out within the move where the
#: margin rule leaves only slow loops (docs/own_gripper.md, "Two antagonistic tendons"); on a
#: finger softer than its loop the corner passes ω_c and the check's runs refuse it
INTEGRAL_DIVISORS = (10.0, 4.0, 2.0, 1.0, 0.5, 0.25, 0.125)
#: the integral's band as a share of the travel (module doc's table)
BAND_TRAVEL = 1.0
PD_DAMPING = 0.7
#: the model's input gain off by these factors in the robustness runs; those below 1 also score
#: the candidate (module doc)
GAIN_ERRORS = (0.5, 2.0)
#: a candidate is kept when its error (share of the travel) is at most this on the model, and at
#: most the second with the input gain off (stability with margin: the feedforward is then off
#: by as much, which the feedback corrects only over the move)
KEEP_NOMINAL = 0.05
KEEP_ROBUST = 0.5
#: the tips the deployed plan's rest pose averages [s] (the trajectory node's ``rest_samples`` at
#: the control period): one message's noise off a slack finger's rest is a hold the law must
#: pull or bend it to (nodes/trajectory.py)
REST_SECONDS = 0.25
PREFER_SLOWER = 1.5
#: the controller node's ``torque_limit`` range [N·m] (nodes/controller.py): a symmetric limit
#: outside it goes to the node as input_lower / input_upper (:meth:`Derivation.params`)
TORQUE_LIMIT_RANGE = (1e-6, 1.0)
#: the check's move is at least this many σ of measurement noise
MIN_TRAVEL_NOISE = 10.0
#: when no candidate passes along the move, the check is made again along this share of it (a
#: learned model is least known near the edge of its data), down to MIN_TRAVEL_NOISE σ
TRAVEL_SHRINK = 0.5
CHECK_PROFILE = dict(t_start=0.5, t_close=2.0, t_hold=1.0, t_open=2.0)
#: where the derived sdre_ff evaluates the model for its feedforward (module doc)
FEEDFORWARD_AT = 'ref'
#: the model is integrated in RK4 steps of at most this [s]
MAX_STEP = 2.5e-3
#: the share of the travel the paper's law is asked to reach (:func:`paper_law_bandwidth`)
PAPER_LAW_SHARE = 0.1
#: waypoints of a curved move (the trajectory node's ``close_path``)
PATH_POINTS = 16
#: an input within this share of its range of a bound counts as at the bound [-]
AT_BOUND = 1e-9
#: the longest input-to-motion delay the model can lack that :func:`unmodelled_delay` looks for [s]
MAX_DELAY = 0.25
#: :func:`unmodelled_delay` needs at least this many periods of excitation
MIN_DELAY_SAMPLES = 100
#: processes that run the candidates' closed-loop checks side by side (:class:`CheckRunner`;
#: capped by the machine's CPUs, 1 = in this process)
CHECK_WORKERS = 2


@dataclass(frozen=True)
class LoopSettings:
    """The estimator's and the controller's parameters (the nodes' names and units)."""

    control_period: float
    meas_std: float
    accel_psd: float
    q_pos: float
    q_vel: float
    r: float
    torque_limit: float
    torque_lowpass_hz: float
    integral_gain: float
    integral_band: float
    pd_kp: float
    pd_kd: float
    bandwidth_hz: float
    feedforward_at: str = FEEDFORWARD_AT

    def weights(self) -> Weights:
        return Weights(self.q_pos, self.q_vel, self.r)


@dataclass
class CheckResult:
    """One closed-loop run on the learned model."""

    law: str
    rmse_rel: float               # RMSE of the true tip / travel (inf when it diverged)
    rest_saturated: float         # share of periods at a bound while held at rest (a one-sided
                                  # input's rest bound, where it rests, does not count)
    rest_torque: float            # largest |u − rest| / its range while held at rest
    saturated: float              # share of periods at a bound over the whole run
    diverged: bool
    outside: int = 0              # commands outside the bounds (a law must never give one)
    unreachable: float = 0.0      # largest demand no input could reach [m/s²] (LawStep)

    @property
    def ok(self) -> bool:
        return (not self.diverged and self.rest_saturated == 0.0 and self.rest_torque < 0.5
                and self.outside == 0)


def fastest_mode_hz(model) -> float:
    """The natural frequency |λ| / 2π [Hz] of the learned A(0)'s fastest oscillating mode (an
    eigenvalue with an imaginary part); 0 when none oscillates."""
    lam = np.linalg.eigvals(model.AG(np.zeros(model_shape(model).n_state))[0][0])
    lam = lam[lam.imag > 0]
    return float(np.abs(lam).max() / (2 * math.pi)) if lam.size else 0.0


def input_gain_squared(model) -> float:
    """g² for the weights: the squared geometric mean of G₂(0)'s singular values (s₁ s₂ for two
    inputs on a planar tip; s₁² for one input)."""
    shape = model_shape(model)
    s = np.linalg.svd(model.AG(np.zeros(shape.n_state))[1][0, shape.d:, :], compute_uv=False)
    if len(s) == 2:
        return float(s[0] * s[1])
    return float(np.prod(s)) ** (2.0 / len(s))


def settings_for(model, facts: DataFacts, bandwidth_hz: float, accel_psd: float) -> LoopSettings:
    """The settings of one candidate (module doc's table)."""
    w = 2 * math.pi * bandwidth_hz
    r = 1.0 / facts.torque_limit ** 2
    q_pos = r * w ** 4 / max(input_gain_squared(model), 1e-12)
    band = max(BAND_TRAVEL * abs(facts.travel), 10 * facts.noise_std)
    return LoopSettings(
        control_period=facts.period, meas_std=max(facts.noise_std, 1e-7), accel_psd=accel_psd,
        q_pos=q_pos, q_vel=0.0, r=r, torque_limit=facts.torque_limit,
        torque_lowpass_hz=ROLL_OFF_RATIO * max(bandwidth_hz, fastest_mode_hz(model)),
        integral_gain=w ** 3 / INTEGRAL_DIVISORS[0],
        integral_band=band, pd_kp=w ** 2, pd_kd=2 * PD_DAMPING * w, bandwidth_hz=bandwidth_hz)


class ModelPlant:
    """The learned model as the check's plant, for one finger: ẋ = A(x)x + k G(x)u with the
    input map scaled by ``gain_error`` k (1: the model itself; else a robustness plant), in RK4
    steps of at most :data:`MAX_STEP` (compiled for a learned model). ``tip()`` is the tip in the
    model's frame: ``model.rest_tip`` plus the state's position."""

    def __init__(self, model, gain_error: float = 1.0, compiled: bool = True) -> None:
        shape = model_shape(model)
        self.model, self.k, self.d = model, float(gain_error), shape.d
        self.rest = np.asarray(model.rest_tip, dtype=float)[:shape.d]
        self.x = np.zeros((1, shape.n_state))
        #: a learned model's steps run compiled (:class:`~soft_gripper_sdre.analysis.model_fitness.
        #: CompiledRK4`; ``compiled`` False, or a model with its own ``AG``: numpy's RK4)
        self.rk4 = (model_fitness.CompiledRK4(model)
                    if compiled and model_fitness.CompiledRK4.fits(model) else None)

    def xdot(self, x, u):
        return model_fitness.xdot(self.model, x, self.k * np.asarray(u) if self.k != 1.0 else u)

    def tip(self) -> np.ndarray:
        return self.rest + self.x[0, :self.d]

    def step(self, u: np.ndarray, dt: float) -> None:
        """Hold ``u`` (1, m) over ``dt`` [s]."""
        substeps = math.ceil(dt / MAX_STEP - 1e-9)
        if self.rk4 is not None:
            u = np.asarray(u, dtype=float).reshape(-1)
            self.rk4.step(self.x[0], self.k * u if self.k != 1.0 else u, dt, substeps)
            return
        for _ in range(substeps):
            self.x = rk4_step(self, self.x, u, dt / substeps)


def check_move(facts: DataFacts) -> GraspTrajectory:
    """The check's reference for one finger at the model's rest: the trajectory node's
    raised-cosine move of ``facts.travel`` along ``facts.direction`` (planar:
    ``close_distance`` and ``side_distance``), along ``facts.axis`` (3-D: ``direction``), or
    through ``facts.path`` (``close_path``), held, and back (:data:`CHECK_PROFILE`)."""
    if facts.d == 2 and facts.path is None:
        close, side = facts.move()
        profile = GraspProfile(close_distance=close, side_distance=side, grasp_fingers=(0,),
                               others='hold', contact_distance=close, **CHECK_PROFILE)
        return GraspTrajectory(np.zeros((1, 2)), profile)
    plan = _plan(facts)
    profile = GraspProfile(close_distance=plan['close_distance'],
                           contact_distance=plan['contact_distance'], grasp_fingers=(0,),
                           others='hold', direction=tuple(plan['direction']),
                           close_path=(tuple(plan['close_path']) if 'close_path' in plan
                                       else None), **CHECK_PROFILE)
    return GraspTrajectory(np.zeros((1, facts.d)), profile, dim=facts.d)


def _plan(facts: DataFacts) -> dict:
    """The trajectory node's parameters of a 3-D or curved move: ``direction`` (the straight
    move's unit direction, or the chord of the curve), ``close_distance`` (its length, or the
    curve's arc length) and ``close_path`` (the curve's waypoints after the rest, flat)."""
    plan = {'task_dim': facts.d, 'direction': [float(v) for v in facts.unit],
            'close_distance': float(facts.travel), 'contact_distance': float(facts.travel)}
    if facts.path is not None:
        plan['close_path'] = [float(v) for v in np.asarray(facts.path)[1:].reshape(-1)]
    return plan


class _SpatialKF:
    """The estimator's constant-velocity KF on a 3-D tip for one finger: with independent
    process noise its axes decouple, so X, Y run in one planar KF and Z in another (fed a
    constant second coordinate). ``x`` (1, 6) = [p; v]."""

    def __init__(self, dt: float, accel_psd: float, meas_std: float) -> None:
        self.xy = ConstantVelocityKF(dt, accel_psd, meas_std, n=1)
        self.z = ConstantVelocityKF(dt, accel_psd, meas_std, n=1)
        self.x = np.zeros((1, 6))

    def _join(self) -> np.ndarray:
        a, b = self.xy.x, self.z.x
        self.x = np.array([[a[0, 0], a[0, 1], b[0, 0], a[0, 2], a[0, 3], b[0, 2]]])
        return self.x.copy()

    def reset(self, z: np.ndarray) -> None:
        self.xy.reset(z[:, :2])
        self.z.reset(np.array([[z[0, 2], 0.0]]))
        self._join()

    def step(self, z: np.ndarray) -> np.ndarray:
        self.xy.step(z[:, :2])
        self.z.step(np.array([[z[0, 2], 0.0]]))
        return self._join()


def _rest_share(u: np.ndarray, bounds: InputBounds) -> np.ndarray:
    """|u − rest| as a share of the input's range away from its rest value, per input."""
    rest = bounds.rest
    room = np.maximum(bounds.upper - rest, rest - bounds.lower)
    return np.abs(u - rest) / room


def _at_bound(u: np.ndarray, bounds: InputBounds) -> np.ndarray:
    """(…,) any input at a bound that is not its rest value (a chamber resting at 0 is not
    saturated)."""
    tol = AT_BOUND * (bounds.upper - bounds.lower)
    rest = bounds.rest
    low = (u <= bounds.lower + tol) & (bounds.lower != rest)
    high = (u >= bounds.upper - tol) & (bounds.upper != rest)
    return np.any(low | high, axis=-1)


class _CompiledSteps:
    """:func:`check_on_model`'s steps in one compiled call
    (:func:`~soft_gripper_sdre.control.kernels.check_loop.feedforward_check_steps`) where the
    loop allows: the default law stepping compiled on the hand's path with its integral action
    (:meth:`~soft_gripper_sdre.control.laws.feedforward.SdreFeedforwardLaw.hand_kernel_parts`),
    a planar estimator, two-sided inputs (``facts.bounds`` None) and the learned model (compiled)
    or a finger's linear fit as the plant (those classes themselves). The kernel works on the
    law's, the estimator's, the plant's and the loop's own arrays, the plant's state taken afresh
    at each call, so a step it hands back runs in Python on the same state and the results are
    the Python loop's (test/test_compiled_check_loop.py)."""

    def __init__(self, ctrl, parts: HandKernelParts, kf: ConstantVelocityKF, plant,
                 loop: tuple, plant_args: tuple, records: tuple, pending: np.ndarray) -> None:
        self.ctrl, self.parts, self.kf, self.plant = ctrl, parts, kf, plant
        self.loop, self.plant_args, self.records, self.pending = loop, plant_args, records, pending
        self.saved = np.zeros_like(parts.state)           # the SDRE state before a step
        self.kf_matrices = (kf.F, kf.Q, kf.R)

    @classmethod
    def of(cls, ctrl, kf, plant, dt: float, rest: np.ndarray, ref, noise: np.ndarray,
           facts: DataFacts, pending: np.ndarray, bound: float, pos: np.ndarray,
           u_hist: np.ndarray, sat: np.ndarray) -> _CompiledSteps | None:
        """The compiled steps of this loop, or None where they do not apply (class doc)."""
        parts = getattr(ctrl, 'hand_kernel_parts', lambda: None)()
        if (parts is None or facts.bounds is not None or type(kf) is not ConstantVelocityKF
                or kf.d != 2):
            return None
        if type(plant) is ModelPlant and plant.rk4 is not None:
            kind, rest_tip, origin, gain = NETWORK_PLANT, plant.rest, np.zeros(2), plant.k
            matrices = (*plant.rk4.layers, np.zeros((1, 1)), np.zeros((1, 1)))
        elif type(plant) is LinearFingerPlant:
            kind, rest_tip, origin, gain = LINEAR_PLANT, plant.rest_tip, plant.origin, plant.gain
            no_layers = (np.zeros((1, 1)), np.zeros(1)) * 3
            matrices = (*no_layers, *(np.ascontiguousarray(a, dtype=float)
                                      for a in plant.matrices(dt)))
        else:
            return None
        move = tuple(np.ascontiguousarray(a[:, 0], dtype=float)
                     for a in (ref.pos, ref.vel, ref.acc))
        plant_args = (kind, np.asarray(rest_tip, dtype=float), np.asarray(origin, dtype=float),
                      float(gain), float(dt), math.ceil(dt / MAX_STEP - 1e-9), *matrices,
                      float(bound))
        return cls(ctrl, parts, kf, plant, (noise, float(facts.noise_std), rest, *move),
                   plant_args, (pos, u_hist, sat), pending)

    def run(self, k: int) -> tuple[int, bool]:
        """Steps from ``k`` on; (the first step not run here, whether the run diverged)."""
        p = self.parts
        # the plant's state as it is now: a Python step replaces a linear fit's
        state = self.plant.x[0] if type(self.plant) is ModelPlant else self.plant.z
        alpha, previous, has_previous = p.roll_off.kernel_args(np.zeros((1, 2)))
        u_prev = np.array(previous, dtype=float).reshape(1, 2)
        has_prev = np.array([has_previous], dtype=np.bool_)
        end, left = feedforward_check_steps(
            k, *self.loop, self.kf.x, self.kf.P, *self.kf_matrices, p.origin,
            p.ff_at_reference, *p.network, p.settings, p.state, p.outputs, p.feedforward,
            self.saved, p.xi, p.integral, alpha, u_prev, has_prev, self.pending, state,
            *self.plant_args, *self.records)
        if has_prev[0]:
            p.roll_off.keep(u_prev)
        self.ctrl.sdre.steps += end - k
        return end, bool(left)


def check_on_model(model, settings: LoopSettings, facts: DataFacts, law: str = 'sdre_ff',
                   gain_error: float = 1.0, seed: int = 0, delay: int = 1,
                   plant=None) -> CheckResult:
    """Run ``law`` with ``settings`` on the learned model as the plant (module doc): measured
    noise, the estimator, the command ``delay`` periods late and ``facts.input_delay`` later
    still (rounded to whole periods), along :func:`check_move`, within the loop's bounds
    (:func:`~soft_gripper_sdre.analysis.holding.loop_bounds`: ``facts.bounds``, or
    ±``facts.torque_limit``, as every finger delivers them through its input gain); a command
    outside them is counted (:attr:`CheckResult.outside`) and fails the check.

    ``plant``: another plant for the same loop, with ``tip()`` (d,) [m] and ``step(u (1, m),
    dt)``, e.g. a finger of :mod:`soft_gripper_sdre.sim.plants` behind an adapter (the recipe's
    grippers in process, docs/own_gripper.md); the move starts from its tip at rest.
    None: ``ModelPlant(model, gain_error)``."""
    shape = model_shape(model)
    d, m = shape.d, shape.m
    bounds = loop_bounds(facts, m)
    dt = settings.control_period
    delay += delay_periods(facts.input_delay, dt)
    traj = check_move(facts)
    steps = int(round(traj.profile.duration / dt)) + 1
    t = np.arange(steps) * dt
    ref = traj.sample(t)
    if plant is None:
        plant = ModelPlant(model, gain_error)
    rest = np.array(plant.tip(), dtype=float)
    # the law in the model's units, within what every finger delivers (loop_bounds)
    limit = settings.torque_limit
    if facts.bounds is None and facts.input_gains:
        limit *= min(facts.input_gains.values())
    options = {} if facts.bounds is None else {'bounds': bounds}
    if law == 'sdre_ff':
        options.update(integral_gain=settings.integral_gain,
                       integral_band=settings.integral_band, ff_at=settings.feedforward_at)
    elif law in ('pd', 'computed_torque'):
        options.update(pd_gains=dict(kp=settings.pd_kp, kd=settings.pd_kd))
    ctrl = make_law(law, model, settings.weights(), limit, n_fingers=1,
                    lowpass_hz=settings.torque_lowpass_hz, dt=dt, **options)
    kf = (ConstantVelocityKF(dt, settings.accel_psd, settings.meas_std, n=1) if d == 2
          else _SpatialKF(dt, settings.accel_psd, settings.meas_std))
    noise = np.random.default_rng(seed).standard_normal((steps, d))   # one draw per step
    first = np.asarray(bounds.rest if facts.bounds is not None else np.zeros(m), dtype=float)
    pending = np.tile(first, (delay, 1))            # the commands not yet applied, oldest first
    pos = np.empty((steps, d))
    u_hist = np.empty((steps, m))
    sat = np.zeros(steps, dtype=bool)
    outside, unreachable = 0, 0.0
    bound = 20 * abs(facts.travel) + 0.01
    compiled = None
    tip = rest
    k = 0
    while k < steps:
        if k == 1 and law == 'sdre_ff':      # the estimator set up by the first step
            compiled = _CompiledSteps.of(ctrl, kf, plant, dt, rest, ref, noise, facts, pending,
                                         bound, pos, u_hist, sat)
        if k and compiled is not None:
            k, left = compiled.run(k)
            if left:
                return CheckResult(law, math.inf, 1.0, math.inf, 1.0, True, outside, unreachable)
            if k == steps:
                break
            tip = np.array(plant.tip(), dtype=float)
        z = tip[None] + facts.noise_std * noise[k][None]
        xh = kf.step(z) if k else (kf.reset(z), kf.x.copy())[1]
        out = ctrl.compute(xh[:, :d], xh[:, d:], rest + ref.pos[k], ref.vel[k], ref_acc=ref.acc[k])
        if delay:
            applied = pending[0].copy()
            pending[:-1] = pending[1:]
            pending[-1] = out.u[0]
        else:
            applied = out.u[0]
        plant.step(applied[None], dt)
        tip = np.array(plant.tip(), dtype=float)
        pos[k], u_hist[k] = tip - rest, out.u[0]
        if facts.bounds is None:
            sat[k] = bool(np.any(out.saturated))
        else:
            sat[k] = bool(_at_bound(out.u[0], bounds))
            outside += int(not (np.all(np.isfinite(out.u)) and bounds.contains(out.u, tol=1e-12)))
            unreachable = max(unreachable, float(np.max(getattr(out, 'unreachable', 0.0))))
        if not (np.all(np.isfinite(tip)) and np.abs(pos[k]).max() < bound):
            return CheckResult(law, math.inf, 1.0, math.inf, 1.0, True, outside, unreachable)
        k += 1
    err = np.linalg.norm(pos - ref.pos[:, 0], axis=1)
    at_rest = t < traj.profile.t_start
    rest_torque = (float(np.abs(u_hist[at_rest]).max() / limit)
                   if facts.bounds is None else float(_rest_share(u_hist[at_rest], bounds).max()))
    return CheckResult(law, float(np.sqrt(np.mean(err ** 2)) / abs(facts.travel)),
                       float(sat[at_rest].mean()), rest_torque, float(sat.mean()), False,
                       outside, unreachable)


def delay_periods(input_delay: float, period: float) -> int:
    """The whole periods of ``period`` [s] nearest ``input_delay`` [s] (0 for no delay)."""
    return int(round(input_delay / period)) if input_delay > 0 else 0


def unmodelled_delay(model, t: np.ndarray, u: np.ndarray, tips: np.ndarray,
                     max_delay: float = MAX_DELAY) -> float:
    """The input-to-motion delay [s] the learned model lacks: how much later the finger's tip
    moves than the model's under the same inputs.

    The model runs free from its rest under the recorded inputs held
    between tips; the delay is the lag, within ``max_delay``, at which the cross-correlation of
    the recorded tip velocity with the model's peaks (refined by a parabola through the peak and
    its neighbours; 0 when the finger leads). A dead time the model does not have (a valve's, a
    driver's) shows here in full; a lag the training absorbed into slower, better damped
    dynamics does not (the one-chamber finger's 40/60 ms pressure lag: 0 ms on every bag, the
    model's velocity 0–2 periods behind the finger's; docs/own_gripper.md).

    Args:
        t: (N,) tip times [s], increasing.
        u: (N, m) the inputs held at those times [their SI unit].
        tips: (N, d) the recorded tips [m], the first at the finger's rest (the stretch
            starts at the first input off rest).

    Raises:
        ShapeError: arrays of other shapes than the model's, fewer than
            :data:`MIN_DELAY_SAMPLES` tips, times not increasing, or values not finite.
    """
    shape = model_shape(model)
    d, m = shape.d, shape.m
    t = np.asarray(t, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float)
    tips = np.asarray(tips, dtype=float)
    if u.shape != (len(t), m) or tips.shape != (len(t), d):
        raise ShapeError(f'excitation: {len(t)} times need inputs ({len(t)}, {m}) and tips '
                         f'({len(t)}, {d}) for a model of {shape}, got {u.shape} and '
                         f'{tips.shape}')
    if len(t) < MIN_DELAY_SAMPLES:
        raise ShapeError(f'excitation: at least {MIN_DELAY_SAMPLES} tips needed, got {len(t)}')
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(tips))):
        raise ShapeError('excitation: times, inputs and tips must be finite')
    if not np.all(np.diff(t) > 0):
        raise ShapeError('excitation: the times must increase')
    dt = float(np.median(np.diff(t)))
    grid = t[0] + dt * np.arange(int((t[-1] - t[0]) / dt + 1e-9) + 1)
    # the input in force at each grid time (a tip stamped a rounding error later counts as at it)
    held = u[np.clip(np.searchsorted(t, grid + 1e-6 * dt, side='right') - 1, 0, len(t) - 1)]
    pos = np.stack([np.interp(grid, t, tips[:, k]) for k in range(d)], axis=1)
    pos = pos - pos[0]
    substeps = max(1, math.ceil(dt / MAX_STEP - 1e-9))
    if model_fitness.CompiledRK4.fits(model):          # a learned model: compiled
        run = model_fitness.CompiledRK4(model).simulate(np.zeros(2 * d), held[:-1], dt,
                                                        substeps)[:, :d]
    else:
        run = model_fitness.simulate(model, np.zeros((1, 2 * d)), held[:-1, None, :], dt,
                                     substeps=substeps)[:, 0, :d]
    alive = int(np.argmin(np.all(np.isfinite(run), axis=1))) if not np.all(
        np.isfinite(run)) else len(run)
    n = alive - 1
    lags = int(max_delay / dt + 1e-9)
    if n < MIN_DELAY_SAMPLES or lags < 1:
        return 0.0
    v_data = np.diff(pos[:alive], axis=0)
    v_model = np.diff(run[:alive], axis=0)
    v_data = v_data - v_data.mean(axis=0)
    v_model = v_model - v_model.mean(axis=0)
    lags = min(lags, n // 2)
    corr = np.array([np.sum(v_data[k:] * v_model[:n - k]) / (n - k) for k in range(lags + 1)])
    k = int(np.argmax(corr))
    shift = float(k)
    if 0 < k < lags:
        lo, mid, hi = corr[k - 1], corr[k], corr[k + 1]
        bend = lo - 2 * mid + hi
        if bend < 0:
            shift += 0.5 * (lo - hi) / bend
    return max(shift, 0.0) * dt


def paper_law_offset(model, facts: DataFacts, bandwidth_hz: float) -> float:
    """Share of a held move along ``facts.direction`` that the paper's law (``sdre``, eq. 22–23)
    stops short of, on the model linearised at rest, with the weights of ``bandwidth_hz``.

    Its gains minimise eᵀQe + uᵀRu, and the torque that holds a displaced finger against its
    spring is in that cost: the steady state x = −A_cl⁻¹ G K_s x_d trades error for torque. On
    ẍ = −ω_n² p + g u with q/r = ω_c⁴/g² the share is 1 / (1 + (ω_c/ω_n)⁴) exactly, so a tenth
    needs ω_c ≥ √3 ω_n whatever Q and R. ``sdre_ff``'s feedforward and integral remove it.
    """
    shape = model_shape(model)
    d = shape.d
    A, G = (a[0] for a in model.AG(np.zeros((1, shape.n_state))))
    cost = settings_for(model, facts, bandwidth_hz, facts.accel_psd_ml).weights()
    Q = np.diag([cost.q_pos] * d + [cost.q_vel] * d)
    R = cost.r * np.eye(shape.m)
    K, Ks, _ = sdre_gains(A, G, Q, R)
    x_d = np.concatenate([facts.unit, np.zeros(d)])
    x = -np.linalg.solve(A + G @ K, G @ (Ks @ x_d))
    return float(np.linalg.norm((x_d - x)[:d]))


def paper_law_bandwidth(model, facts: DataFacts, share: float = PAPER_LAW_SHARE) -> float:
    """The lowest bandwidth [Hz] whose weights bring :func:`paper_law_offset` to ``share``
    (``inf`` beyond 1 kHz): how fast a loop the paper's law needs on this finger."""
    lo, hi = 0.01, 1000.0
    if paper_law_offset(model, facts, hi) > share:
        return math.inf
    for _ in range(40):                 # the offset falls as the bandwidth rises: bisect in log
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if paper_law_offset(model, facts, mid) > share else (lo, mid)
    return hi


@dataclass
class Derivation:
    """The chosen settings, their checks, and every candidate tried; ``reason`` says why
    nothing was derived when no candidate was run."""

    settings: LoopSettings | None
    checks: dict                  # law → CheckResult of the chosen settings (nominal)
    candidates: list[dict]
    facts: DataFacts
    reason: str = ''
    #: the paper's law on the chosen settings: the share of the move it holds short of, and the
    #: bandwidth it would need for :data:`PAPER_LAW_SHARE` (:func:`paper_law_offset`)
    paper_law: dict | None = None
    #: the chosen settings' runs on the fingers' own fits with their input lags, by finger
    #: (:func:`check_on_model` results as dicts; None: no fit with a lag took part)
    on_fingers: dict[str, dict] | None = None
    #: the model's inputs per finger (m): symmetric bounds on any other number than the hand's
    #: two go to the controller as input_lower / input_upper (:meth:`params`)
    m: int = 2
    #: the chosen settings' score (module doc: the worst error / travel of the nominal run, the
    #: runs with the input gain lowered and those on the fingers' fits); None: nothing chosen
    score: float | None = None

    def summary(self) -> dict:
        facts = asdict(replace(self.facts, bounds=None))
        facts['bounds'] = self.facts.bounds.to_record() if self.facts.bounds is not None else None
        for key in ('axis', 'path', 'bounds', 'input_gains'):
            if facts[key] is None:
                del facts[key]              # the hand's planar straight move: as it always was
        if facts['input_delay'] == 0.0:
            del facts['input_delay']
        return {'settings': asdict(self.settings) if self.settings else None,
                'reason': self.reason, 'facts': facts, 'paper_law': self.paper_law,
                'checks': {k: asdict(v) for k, v in self.checks.items()},
                'candidates': self.candidates, 'score': self.score,
                **({'on_fingers': self.on_fingers} if self.on_fingers else {}),
                'rules': {'bandwidths_hz': list(BANDWIDTHS_HZ), 'gain_errors': list(GAIN_ERRORS),
                          'keep_nominal': KEEP_NOMINAL, 'keep_robust': KEEP_ROBUST,
                          'hold_share': HOLD_SHARE, 'min_travel_noise': MIN_TRAVEL_NOISE,
                          'travel_shrink': TRAVEL_SHRINK,
                          'check_profile': CHECK_PROFILE,
                          'delay_periods': 1 + delay_periods(self.facts.input_delay,
                                                             self.facts.period)}}

    def params(self, finger_names: list[str]) -> dict:
        """The nodes' parameters for these settings as plain data: ``{'estimator': {…},
        'controller': {…}, 'trajectory': {…}}`` (the controller's ``model_path`` is the caller's).

        Two inputs with symmetric bounds within :data:`TORQUE_LIMIT_RANGE` get the controller's
        ``torque_limit``; per-input bounds, symmetric bounds on another number of inputs (:attr:`m`)
        or beyond that range (inputs in N or Pa) get ``input_lower``/``input_upper`` in its place
        (the node's ``torque_limit`` is the hand's, in N·m). The hand's planar straight move is
        ``close_distance`` and ``side_distance``; another shape adds ``task_dim`` (estimator,
        trajectory). Its move is ``direction``
        (d values, the unit direction) with ``close_distance`` its length, and for a curved move
        ``close_path`` (d values per waypoint after the rest, relative to it, flat; then
        ``direction`` is its chord), both lists of floats. The trajectory node's rest pose is the
        mean of :data:`REST_SECONDS` of tips (``rest_samples``).

        Raises:
            ValueError: no settings were derived (:attr:`reason`).
        """
        d, f = self.settings, self.facts
        if d is None:
            raise ValueError(f'no settings were derived: {self.reason or "no candidate passed"}')
        names = list(finger_names)
        est = {'finger_names': names, 'control_period': d.control_period,
               'meas_std': d.meas_std, 'accel_psd': d.accel_psd}
        ctrl = {'finger_names': names, 'control_period': d.control_period, 'q_pos': d.q_pos,
                'q_vel': d.q_vel, 'r': d.r, 'torque_limit': d.torque_limit,
                'torque_lowpass_hz': d.torque_lowpass_hz,
                'integral_gain': d.integral_gain, 'integral_band': d.integral_band,
                'feedforward_at': d.feedforward_at, 'pd_kp': d.pd_kp, 'pd_kd': d.pd_kd}
        bounds = self.input_bounds()
        if bounds is not None:
            # the bounds replace the symmetric limit (the node's torque_limit is in N·m)
            del ctrl['torque_limit']
            ctrl['input_lower'] = [float(v) for v in bounds.lower]
            ctrl['input_upper'] = [float(v) for v in bounds.upper]
        if f.input_gains:
            ctrl['input_gains'] = [f.input_gains.get(name, 1.0) for name in names]
        if f.d == 2 and f.path is None:
            close, side = f.move()
            plan = {'close_distance': close, 'side_distance': side, 'contact_distance': close}
        else:
            est['task_dim'] = f.d
            plan = _plan(f)
        plan['rest_samples'] = max(1, round(REST_SECONDS / d.control_period))
        return {'estimator': est, 'controller': ctrl, 'trajectory': plan}

    def input_bounds(self) -> InputBounds | None:
        """The controller's ``input_lower`` / ``input_upper`` for these settings, or None where
        its ``torque_limit`` gives them (two inputs, a symmetric limit within
        :data:`TORQUE_LIMIT_RANGE`: :meth:`params`)."""
        f, limit = self.facts, self.settings.torque_limit
        if f.bounds is None and (self.m != 2 or not (TORQUE_LIMIT_RANGE[0] <= limit
                                                     <= TORQUE_LIMIT_RANGE[1])):
            return InputBounds.symmetric(limit, self.m)
        return f.bounds

    def move_text(self) -> str:
        """The checked move in words: its length and where it goes."""
        f = self.facts
        if f.path is not None:
            end = 1e3 * np.asarray(f.path[-1])
            return (f'{1e3 * f.travel:.3g} mm along the curve of the model\'s equilibria under '
                    f'constant inputs, to ({", ".join(f"{v:.3g}" for v in end)}) mm from rest')
        if f.d == 3:
            return (f'{1e3 * f.travel:.3g} mm along ({", ".join(f"{v:.3f}" for v in f.unit)})')
        return f'{1e3 * f.travel:.3g} mm at {f.direction:.0f}° from +X toward +Y'

    def fingers_text(self) -> tuple[str, str | None]:
        """What the fingers' own fits (:attr:`on_fingers`) expect of the chosen settings, in
        words, and a warning when a finger misses :data:`KEEP_NOMINAL` of the travel on its fit or
        diverges there (None: none does); ('', None) without such fits."""
        if not self.on_fingers:
            return '', None

        def figure(r: dict) -> str:
            return 'diverges' if r['diverged'] else f'{100 * r["rmse_rel"]:.2f} %'
        said = ('on the fingers\' own fits, each with its input lag, error / travel: '
                + ', '.join(f'{name} {figure(r)}' for name, r in self.on_fingers.items())
                + ' (what training expects of the deployed grasp)')
        beyond = {name: r for name, r in self.on_fingers.items()
                  if r['diverged'] or not r['rmse_rel'] <= KEEP_NOMINAL}
        if not beyond:
            return said, None
        return said, (
            'WARNING: on its own fit ' + ', '.join(f'{name} {figure(r)}'
                                                   for name, r in beyond.items())
            + f', beyond the {100 * KEEP_NOMINAL:g} % of travel the check holds the model to: the '
            'deployed grasp may miss it too. Record longer or richer excitation and train again, '
            'or deploy and score the grasp (docs/own_gripper.md, "The expectation")')


def derive(model, facts: DataFacts, laws: tuple[str, ...] = ('sdre_ff', 'sdre'),
           progress=None, bandwidths: tuple[float, ...] = BANDWIDTHS_HZ,
           excitation: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
           workers: int = CHECK_WORKERS, fingers: tuple[LinearFinger, ...] = ()
           ) -> Derivation:
    """Pick the bandwidth (among ``bandwidths``), the estimator's intensity and the integral gain
    by closed-loop runs on the model (module doc); ``settings`` is None when no candidate passes
    or no move can be checked (``reason``). ``progress(text)`` hears each run.

    ``workers``: processes that run the checks side by side (:class:`CheckRunner`); every
    number gives the same runs, rows, messages (in the same order) and choice.

    ``excitation``: stretches (t [s], inputs (N, m), tips (N, d) [m]) of the recordings. For any
    finger but the hand's shape with two-sided inputs, the check's commands come
    ``facts.input_delay`` late, the longest :func:`unmodelled_delay` of these stretches (the
    hand's shape with two-sided inputs keeps the one period of its rule).

    ``fingers``: each finger's own fit (:mod:`~soft_gripper_sdre.analysis.finger_fits`). Every
    candidate the robustness runs try on the model with its input gain off is run on each fit
    that found an input lag too, and is kept and scored the same way (module doc).
    """
    shape = model_shape(model)
    _check_facts(facts, shape, fingers)
    if excitation and not (shape == HAND_SHAPE and facts.bounds is None):
        facts = replace(facts, input_delay=max(unmodelled_delay(model, *e) for e in excitation))
        if progress is not None:
            progress(f'the finger moves {1e3 * facts.input_delay:.3g} ms after the model: '
                     f'the check applies its commands '
                     f'{1 + delay_periods(facts.input_delay, facts.period)} period(s) late')
    reach = facts.travel if facts.reach_travel is None else facts.reach_travel
    curve = None
    if shape.m < shape.d:
        # the finger holds still only on its equilibria: the move follows them
        curve = equilibrium_curve(model, loop_bounds(facts, shape.m), facts.unit)
        held = min(reach, curve.holdable_length(hold_bounds(loop_bounds(facts, shape.m))))
        facts = _along_curve(replace(facts, reach_travel=reach), curve, held)
        way = 'the curve of the model\'s equilibria under constant inputs'
    else:
        facts = replace(facts, travel=holdable_travel(model, replace(facts, travel=reach)),
                        reach_travel=reach)
        way = (f'{facts.direction:.0f}° from +X toward +Y' if facts.d == 2 else
               f'({", ".join(f"{v:.3f}" for v in facts.unit)})')
    limit = (f'the torque limit {loop_bounds(facts, shape.m).upper[0]:.3g} N·m'
             if facts.bounds is None else f'the loop\'s input range {loop_bounds(facts, shape.m)}')
    if facts.input_gains:
        limit += ' (what every finger delivers through its input gain)'
    if facts.travel < MIN_TRAVEL_NOISE * facts.noise_std:
        need = np.abs(hold_torques(model,
                                   MIN_TRAVEL_NOISE * facts.noise_std * facts.unit[None])).max()
        return Derivation(None, {}, [], facts, m=shape.m, reason=(
            f'the model holds at most {1e3 * facts.travel:.3g} mm along {way} with '
            f'{HOLD_SHARE:g} of {limit}, under '
            f'{MIN_TRAVEL_NOISE:g} σ of noise ({1e3 * MIN_TRAVEL_NOISE * facts.noise_std:.3g} mm, '
            f'which needs {need:.3g} N·m): excite with larger torques'))
    say = progress if progress is not None else (lambda text: None)
    say(f'move of {1e3 * facts.travel:.3g} mm along {way} (half the reach {1e3 * reach:.3g} mm, '
        f'or what the model holds with {HOLD_SHARE:g} of {limit})')
    for fit in fingers:
        say(f'{fit.name}\'s own linear fit runs free within {100 * fit.free_run:.0f} % of its '
            f'validation motion with an input lag of {1e3 * fit.lag:.3g} ms: '
            + ('each kept candidate is checked on it too' if fit.lag > 0 else
               'no lag the model lacks, the checks run on the model'))
    modes = [hz for fit in fingers for hz in fit.modes_hz]
    if modes:
        # a loop at a finger's own mode must shape it, and only its recordings know it (module doc)
        bandwidths = tuple(b for b in bandwidths if b < min(modes))
        say(f'the fingers\' own fits put their slowest mode at {min(modes):.3g} Hz: the loops '
            'tried stay under it')
    fingers = tuple(fit for fit in fingers if fit.lag > 0)
    rows: list[dict] = []
    warm_up_check_loop()                # compiled once here: the forked workers inherit it
    with CheckRunner(model, workers) as runner:
        while True:
            kept = _search(runner, facts, bandwidths, rows, say, tuple(fingers))
            shorter = TRAVEL_SHRINK * facts.travel
            if kept or shorter < MIN_TRAVEL_NOISE * facts.noise_std:
                break
            facts = (replace(facts, travel=shorter) if curve is None
                     else _along_curve(facts, curve, shorter))
            say(f'no setting passed: a move of {1e3 * shorter:.3g} mm')
        if not kept:
            return Derivation(None, {}, rows, facts, m=shape.m)
        # the best bandwidth's neighbours half an octave either side (module doc)
        best_hz = min(kept, key=lambda c: (c[0], c[1]))[1]
        between = tuple(hz for hz in (best_hz / REFINE_STEP, best_hz * REFINE_STEP)
                        if all(not math.isclose(hz, b, rel_tol=1e-6) for b in bandwidths)
                        and (not modes or hz < min(modes)))
        if between:
            say(f'half an octave either side of {best_hz:g} Hz: '
                + ', '.join(f'{hz:.3g} Hz' for hz in between))
            kept += _search(runner, facts, between, rows, say, tuple(fingers))
        kept.sort(key=lambda c: (c[0], c[1]))
        best = kept[0]
        slower = [c for c in kept if c[1] < best[1] and c[0] <= PREFER_SLOWER * best[0]]
        chosen, nominal, row = (max(slower, key=lambda c: (c[1], -c[0])) if slower else best)[2:]
        # the default law's nominal check of the chosen settings is the one the search ran
        runs = {law: (None if law == 'sdre_ff' else runner.submit(chosen, facts, law=law))
                for law in laws}
        needs = paper_law_bandwidth(model, facts)
        checks = {law: nominal if run is None else run.result() for law, run in runs.items()}
    paper = {'hold_offset': paper_law_offset(model, facts, chosen.bandwidth_hz),
             'share': PAPER_LAW_SHARE,
             'needs_bandwidth_hz': needs if math.isfinite(needs) else None}     # None: over 1 kHz
    return Derivation(chosen, checks, rows, facts, paper_law=paper, m=shape.m,
                      on_fingers=row.get('fingers'), score=row['score'])


def _check_facts(facts: DataFacts, shape, fingers: tuple[LinearFinger, ...] = ()) -> None:
    """``facts`` and the fingers' own fits fit a model of ``shape``: the move's dimension, the
    bounds' inputs and each fit's (d, m).

    Raises:
        ShapeError: the move has another dimension than the model's tip, the bounds another
            number of inputs than the model, or a fit another shape.
    """
    for fit in fingers:
        if (fit.d, fit.m) != (shape.d, shape.m):
            raise ShapeError(f'finger fit {fit.name!r} is of shape (d={fit.d}, m={fit.m}), the '
                             f'model ({shape})')
    if facts.d != shape.d:
        raise ShapeError(f'the move is {facts.d}-D (DataFacts.axis), the model\'s tip '
                         f'{shape.d}-D ({shape})')
    if facts.bounds is not None and facts.bounds.m != shape.m:
        raise ShapeError(f'input bounds: {facts.bounds.m} input(s) (DataFacts.bounds) for a '
                         f'model of {shape.m} ({shape})')
    for name in ('period', 'noise_std', 'torque_limit', 'accel_psd_ml'):
        value = getattr(facts, name)
        least = 0.0 if name == 'noise_std' else math.nextafter(0.0, 1.0)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= least):
            raise ShapeError(f'DataFacts.{name} must be finite and '
                             f'{">= 0" if name == "noise_std" else "> 0"}, got {value!r}')


def _along_curve(facts: DataFacts, curve: EquilibriumCurve, length: float) -> DataFacts:
    """``facts`` with the move ``length`` [m] along ``curve`` from rest (:data:`PATH_POINTS`
    waypoints; no path when the curve is shorter than a micrometre)."""
    length = min(float(length), float(curve.arc[-1]))
    if length < 1e-6:
        return replace(facts, travel=max(length, 0.0), path=None)
    return replace(facts, travel=length, path=curve.cut(length, PATH_POINTS))


#: the model a :class:`CheckRunner`'s worker process checks on (set when the worker starts)
_WORKER_MODEL = None


def _start_worker(model) -> None:
    global _WORKER_MODEL
    _WORKER_MODEL = model


def _worker_check(settings: LoopSettings, facts: DataFacts, law: str,
                  gain_error: float, finger: LinearFinger | None = None) -> CheckResult:
    return _check(_WORKER_MODEL, settings, facts, law, gain_error, finger)


def _check(model, settings: LoopSettings, facts: DataFacts, law: str, gain_error: float,
           finger: LinearFinger | None) -> CheckResult:
    """:func:`check_on_model` on the model (``finger`` None) or on ``finger``'s own fit as the
    plant, from its equilibrium under the inputs' rest value at the model's rest tip, receiving
    the law's commands through its input gain (``facts.input_gains``)."""
    if finger is None:
        return check_on_model(model, settings, facts, law=law, gain_error=gain_error)
    rest_input = actuator_bounds(facts, finger.m).rest
    gain = (facts.input_gains or {}).get(finger.name, 1.0)
    return check_on_model(model, settings, facts, law=law, plant=finger.plant(
        np.asarray(model.rest_tip, dtype=float), rest_input, input_gain=gain))


class CheckRunner:
    """Runs :func:`check_on_model` of one model for the search, in this process or in
    ``workers`` forked processes side by side (each check is seeded and independent of the
    others, so where it runs does not change its result).

    The workers inherit the model when they are forked (it is not pickled); the checks' settings,
    facts and results travel by pickle. One worker, one CPU, or a platform that cannot fork runs
    every check here, when it is submitted. Use as a context manager: the workers end with it.
    """

    def __init__(self, model, workers: int = CHECK_WORKERS) -> None:
        if not (isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1):
            raise ValueError(f'workers must be an int >= 1, got {workers!r}')
        self.model = model
        self.workers = min(workers, os.cpu_count() or 1)
        if 'fork' not in multiprocessing.get_all_start_methods():
            self.workers = 1
        self._pool = (ProcessPoolExecutor(self.workers, multiprocessing.get_context('fork'),
                                          initializer=_start_worker, initargs=(model,))
                      if self.workers > 1 else None)

    def submit(self, settings: LoopSettings, facts: DataFacts, law: str = 'sdre_ff',
               gain_error: float = 1.0, finger: LinearFinger | None = None) -> Future:
        """The check's future :class:`CheckResult` (already done when run here); on the model
        with its input gain off by ``gain_error``, or on ``finger``'s own fit."""
        if self._pool is not None:
            return self._pool.submit(_worker_check, settings, facts, law, gain_error, finger)
        done: Future = Future()
        done.set_result(_check(self.model, settings, facts, law, gain_error, finger))
        return done

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> CheckRunner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _search(runner: CheckRunner, facts: DataFacts, bandwidths: tuple[float, ...],
            rows: list[dict], say, fingers: tuple[LinearFinger, ...] = ()
            ) -> list[tuple[float, float, LoopSettings, CheckResult, dict]]:
    """The candidates along ``facts``' move (module doc), each run appended to ``rows``; returns
    the kept ones as (score, bandwidth, settings, nominal check, row).

    The checks are submitted to ``runner`` as soon as the rule knows they will run (the next
    bandwidth's intensities beside this one's integral gains and robustness runs) and their
    results are taken in the rule's order, so rows, messages and choice are those of one check
    after another."""
    model = runner.model
    kept = []

    def record(cand: LoopSettings, nominal: CheckResult) -> tuple[CheckResult, LoopSettings,
                                                                  dict]:
        """The nominal check of ``cand``, recorded as a new row of ``rows``."""
        rows.append({'travel': facts.travel, 'bandwidth_hz': cand.bandwidth_hz,
                     'accel_psd': cand.accel_psd, 'integral_gain': cand.integral_gain,
                     'nominal': asdict(nominal)})
        say(f'{cand.bandwidth_hz:g} Hz, accel_psd {cand.accel_psd:.3g}, integral '
            f'{cand.integral_gain:.3g}: ' + ('diverged' if nominal.diverged else
                                            f'{100 * nominal.rmse_rel:.2f} % of travel'))
        return nominal, cand, rows[-1]

    def passes(nominal: CheckResult) -> bool:
        return nominal.ok and nominal.rmse_rel <= KEEP_NOMINAL

    def robust(cand: LoopSettings) -> list[Future]:
        return ([runner.submit(cand, facts, gain_error=g) for g in GAIN_ERRORS]
                + [runner.submit(cand, facts, finger=fit) for fit in fingers])

    def intensities(hz: float) -> list[tuple[LoopSettings, Future]]:
        cands = [settings_for(model, facts, hz, frac * facts.accel_psd_ml)
                 for frac in ACCEL_PSD_FRACTIONS]
        return [(c, runner.submit(c, facts)) for c in cands]

    todo = [b for b in bandwidths if b <= RATE_FRACTION / facts.period]
    ahead = intensities(todo[0]) if todo else []
    for i, hz in enumerate(todo):
        tried = [record(cand, run.result()) for cand, run in ahead]
        if all(nominal.diverged for nominal, _, _ in tried):
            break                  # every estimator diverged: a faster loop has less margin still
        w = 2 * math.pi * hz
        # every intensity with the stronger integral gains
        stronger = [replace(cand, integral_gain=w ** 3 / divisor)
                    for _, cand, _ in tried for divisor in INTEGRAL_DIVISORS[1:]]
        runs = [runner.submit(cand, facts) for cand in stronger]
        checks = {k: robust(cand) for k, (nominal, cand, _) in enumerate(tried)
                  if passes(nominal)}
        ahead = intensities(todo[i + 1]) if i + 1 < len(todo) else []
        first = len(tried)
        tried += [record(cand, run.result()) for cand, run in zip(stronger, runs)]
        for k, (nominal, cand, _) in enumerate(tried[first:], first):
            if passes(nominal):
                checks[k] = robust(cand)
        for k, (nominal, cand, row) in enumerate(tried):
            if k not in checks:
                continue
            results = [run.result() for run in checks[k]]
            row['robust'] = [asdict(r) for r in results[:len(GAIN_ERRORS)]]
            if fingers:
                row['fingers'] = {fit.name: asdict(r)
                                  for fit, r in zip(fingers, results[len(GAIN_ERRORS):])}
                say(f'  {cand.bandwidth_hz:g} Hz, accel_psd {cand.accel_psd:.3g}, integral '
                    f'{cand.integral_gain:.3g} on the fingers\' own fits: ' + ', '.join(
                        f'{fit.name} ' + ('diverged' if r.diverged else
                                          f'{100 * r.rmse_rel:.2f} %')
                        for fit, r in zip(fingers, results[len(GAIN_ERRORS):])))
            row['robust_ok'] = all(r.ok and r.rmse_rel <= KEEP_ROBUST for r in results)
            row['score'] = max([nominal.rmse_rel]
                               + [r.rmse_rel for g, r in zip(GAIN_ERRORS, results) if g < 1]
                               + [r.rmse_rel for r in results[len(GAIN_ERRORS):]])
        # the bandwidth holds only when its loop with the weakest integral diverges with none of
        # the first MARGIN_INTENSITIES, on the model or with its input gain off (module doc)
        holds = not any(nominal.diverged or any(r['diverged'] for r in row.get('robust', ()))
                        for nominal, _, row in tried[:min(first, MARGIN_INTENSITIES)])
        for nominal, cand, row in tried:
            if holds and row.get('robust_ok', False):
                kept.append((row['score'], hz, cand, nominal, row))
    for _, run in ahead:
        run.cancel()
    return kept
