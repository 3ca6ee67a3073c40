"""The grasp closed in one process, without ROS: simulator → KF → SDRE → simulator.

This is the node graph's loop with the topics replaced by function calls, in the same order and
with the same rules, so a lockstep run of the graph reproduces it:

1. the simulator measures the tips at t_k (:meth:`GripperSim.measure`); with a ``sensor_delay`` of
   d control periods the estimator gets the measurement of t_(k−d) instead (a FIFO of
   measurements, filled with the first one until d have been taken);
2. the estimator's constant-velocity KF turns them into x̂_k under the estimator node's rules
   (:class:`~soft_gripper_sdre.control.tip_filter.TipFilter`, stamped t_k: the first measurement
   initialises it with zero velocity); the trajectory's rest pose is that first measurement;
3. the controller takes the reference at t_k (sampled for the whole run at once) and computes u_k
   from x̂_k;
4. the simulator holds u_k over [t_k, t_k + Δt).

The loop runs in the law's task dimension d and its m inputs (its ``io.shape``; a law without
one is the hand's, d = 2, m = 2): the tips' first d coordinates, a reference in d coordinates,
commands of m inputs. The simulator is the hand (:class:`~soft_gripper_sdre.sim.hand.GripperSim`,
d = 2, m = 2), so a law of another shape is refused before anything runs.

It is used by the tests, the tuning sweeps and the benchmarks; the demo runs the real node graph.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math
import time

import numpy as np

from soft_gripper_sdre.analysis.metrics import TrackingMetrics, tracking_metrics
from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.tip_filter import MAX_BRIDGE, NS, RESET_ON_JUMP, TipFilter
from soft_gripper_sdre.control.tracking import Law, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, ShapeError

#: the shape of the fingers the in-process simulator has
SIM_SHAPE = HAND_SHAPE


@dataclass(frozen=True)
class EstimatorSettings:
    """Constant-velocity KF settings (SI): white-acceleration intensity and measurement σ."""

    accel_psd: float = 1.0
    meas_std: float = 5e-5
    process_noise: str = 'independent'


@dataclass
class LoopResult:
    """Time series of one closed-loop run, sampled at every control period (T samples)."""

    t: np.ndarray                 # (T,) s
    pos: np.ndarray               # (T, n, d) true tip position [m]
    vel: np.ndarray               # (T, n, d) true tip velocity [m/s]
    meas: np.ndarray              # (T, n, d) measured tip position the estimator got (delayed by
                                  # sensor_delay) [m]
    est: np.ndarray               # (T, n, 2d) KF estimate [m, m/s]
    ref_pos: np.ndarray           # (T, n, d)
    ref_vel: np.ndarray           # (T, n, d)
    u: np.ndarray                 # (T, n, m) applied input [N·m, or the input's SI unit]
    ok: np.ndarray                # (T, n) all Riccati checks passed
    fallback: np.ndarray          # (T, n) fallback gains used
    saturated: np.ndarray         # (T, n, m)
    residual: np.ndarray          # (T, n) relative CARE residual
    contact: np.ndarray           # (T, n) finger touches the cube (hand scene), else False
    cube: np.ndarray              # (T, 7) cube pose, NaN without a cube
    free_space: np.ndarray        # (T, n) scored samples
    excursion: np.ndarray         # (n,) peak reference excursion [m]
    metrics: list[TrackingMetrics] = field(default_factory=list)
    step_seconds: float = 0.0     # wall time of the loop itself (after the simulator's settle) [s]
    period_seconds: np.ndarray | None = None   # (T,) wall time of each period of the loop [s]
    law_seconds: np.ndarray | None = None      # (T,) wall time of the law each period (observe +
                                               # compute) [s]


def run_closed_loop(law: Law, *, duration: float, sim_config: SimConfig | None = None,
                    profile: GraspProfile | None = None, estimator: EstimatorSettings | None = None,
                    progress: bool = False, sensor_delay: float = 0.0) -> LoopResult:
    """Run the grasp under ``law`` for ``duration`` seconds of sim time and return everything
    recorded.

    ``law``: a :class:`~soft_gripper_sdre.control.tracking.Law` for as many fingers as the scene
    has, at its control period (:func:`~soft_gripper_sdre.control.laws.make_law`); every law gets
    the reference acceleration, and one with an ``observe(truth)`` method gets the plant's ground
    truth before each step (the oracles, :mod:`soft_gripper_sdre.analysis.oracle`).

    ``sensor_delay`` [s]: age of the measurement the estimator gets, a whole number of control
    periods (0: the measurement of the same period, as on the node graph in lockstep).

    Raises:
        ValueError: ``sensor_delay`` is negative, not finite or not a whole number of periods;
            the law controls another number of fingers than the scene has.
        ShapeError: the law controls fingers of another shape than the simulator's
            (:data:`SIM_SHAPE`).
    """
    shape = law_shape(law)
    if shape != SIM_SHAPE:
        raise ShapeError(f'the law controls fingers of shape ({shape}); the in-process simulator '
                         f'has the hand\'s ({SIM_SHAPE}): run it on the node graph with its '
                         'driver')
    sim_config = sim_config or SimConfig(scene='hand')
    profile = profile or GraspProfile()
    estimator = estimator or EstimatorSettings()
    dt = sim_config.control_period
    steps = int(round(duration / dt))
    delay_steps = delay_in_periods(sensor_delay, dt)
    with GripperSim(sim_config) as sim:
        n = sim.n_fingers
        kf = ConstantVelocityKF(dt, estimator.accel_psd, estimator.meas_std, n=n,
                                process_noise=estimator.process_noise)
        period_ns = int(round(dt * NS))
        tips = TipFilter(kf, period_ns, int(round(RESET_ON_JUMP * NS)), int(round(MAX_BRIDGE * NS)))
        io = getattr(law, 'io', None)          # every law of control/laws has one
        if io is not None and io.n_fingers != n:
            raise ValueError(f'the law controls {io.n_fingers} fingers, the '
                             f'{sim_config.scene!r} scene has {n}')
        iterator = range(steps)
        if progress:
            from tqdm import tqdm
            iterator = tqdm(iterator, desc='closed loop', unit='step', mininterval=0.5)
        loop = _GraspLoop(sim, law, tips, delay_steps, profile, steps, dt, shape.d)
        for k in iterator:
            loop.period(k)
    return loop.result()


#: the series a run records each period: the LoopResult fields of the same names
_RECORDED = ('t', 'pos', 'vel', 'meas', 'est', 'u', 'ok', 'fallback', 'saturated', 'residual',
             'contact', 'cube')


class _GraspLoop:
    """One run between its periods: the sensor's FIFO of measurements, the reference (sampled
    once the first measurement gives the rest pose), what is recorded and the wall-clock stamps
    of the periods and the law."""

    def __init__(self, sim: GripperSim, law: Law, tips: TipFilter, delay_steps: int,
                 profile: GraspProfile, steps: int, dt: float, d: int = 2) -> None:
        self.sim, self.law, self.tips, self.profile, self.steps = sim, law, tips, profile, steps
        self.d = d
        self.observe = getattr(law, 'observe', None)
        self.dt, self.period_ns, self.delay_steps = dt, tips.period_ns, delay_steps
        self.fifo = deque(maxlen=delay_steps + 1)     # the last d + 1 measurements, oldest first
        self.traj, self.refs = None, None
        self.rec = {k: [] for k in _RECORDED}
        self.clock = time.perf_counter
        self.stamps = np.empty(steps + 1)
        self.law_seconds = np.empty(steps)
        self.stamps[0] = self.clock()

    def period(self, k: int) -> None:
        """Steps 1–4 of the module doc at t_k = k Δt, recorded."""
        z = self._measure()
        if self.traj is None:
            self.traj = (GraspTrajectory(z, self.profile) if self.d == 2
                         else GraspTrajectory(z, self.profile, dim=self.d))
            # the whole reference at once (t_k = k Δt)
            self.refs = self.traj.sample(np.arange(self.steps) * self.dt)
        x_hat = self.tips.on_tips(k * self.period_ns, z).estimate
        if x_hat is None:
            raise RuntimeError(f'the simulator measured tips the estimator refuses at '
                               f't = {k * self.dt:g} s: {z.tolist()}')
        truth = self.sim.truth()
        t_law = self.clock()
        if self.observe is not None:
            self.observe(truth)
        refs = self.refs
        d = self.d
        out = self.law.compute(x_hat[:, :d], x_hat[:, d:], refs.pos[k], refs.vel[k],
                               ref_acc=refs.acc[k])
        self.law_seconds[k] = self.clock() - t_law
        self.sim.step(out.u)
        self._record(truth, z, x_hat, out)
        self.stamps[k + 1] = self.clock()

    def _measure(self) -> np.ndarray:
        """The tips the estimator gets this period: those measured d periods ago."""
        first = not self.fifo
        self.fifo.append(self.sim.measure()[:, :self.d])
        if first:
            # before d measurements exist, the sensor repeats the first
            self.fifo.extend([self.fifo[0]] * self.delay_steps)
        return self.fifo[0]

    def _record(self, truth, z: np.ndarray, x_hat: np.ndarray, out) -> None:
        """The period's truth, measurement, estimate and law outputs (no cube: no contact, and
        a NaN pose)."""
        rec, n = self.rec, len(z)
        rec['t'].append(truth.t)
        rec['pos'].append(truth.tip_pos[:, :self.d])
        rec['vel'].append(truth.tip_vel[:, :self.d])
        rec['meas'].append(z)
        rec['est'].append(x_hat)
        rec['u'].append(out.u)
        rec['ok'].append(out.ok)
        rec['fallback'].append(out.fallback)
        rec['saturated'].append(out.saturated)
        rec['residual'].append(out.residual)
        rec['contact'].append(truth.finger_cube_contact if truth.finger_cube_contact is not None
                              else np.zeros(n, dtype=bool))
        rec['cube'].append(truth.cube_pose if truth.cube_pose is not None
                           else np.full(7, np.nan))

    def result(self) -> LoopResult:
        """Everything recorded, with the free-space samples and the tracking metrics."""
        arrays = {k: np.asarray(v) for k, v in self.rec.items()}
        steps = self.steps
        arrays['ref_pos'], arrays['ref_vel'] = self.refs.pos[:steps], self.refs.vel[:steps]
        free = self.traj.free_space(arrays['t']) & ~arrays['contact']
        excursion = self.traj.peak_excursion()
        periods = np.diff(self.stamps)
        result = LoopResult(**arrays, free_space=free, excursion=excursion,
                            step_seconds=float(periods.sum()), period_seconds=periods,
                            law_seconds=self.law_seconds)
        result.metrics = tracking_metrics(result.pos, result.ref_pos, free, excursion)
        return result


def law_shape(law: Law) -> FingerShape:
    """The finger shape ``law`` controls: its ``io.shape``, else the hand's."""
    shape = getattr(getattr(law, 'io', None), 'shape', None)
    return shape if isinstance(shape, FingerShape) else HAND_SHAPE


def delay_in_periods(delay: float, period: float) -> int:
    """A sensor delay [s] as a whole number of control periods.

    Raises:
        ValueError: the delay is negative, not finite or not a whole number of periods (within
            1e-9).
    """
    if not (isinstance(delay, (int, float)) and math.isfinite(delay) and delay >= 0):
        raise ValueError(f'sensor_delay must be a finite number >= 0 s, got {delay!r}')
    steps = round(delay / period)
    if abs(steps * period - delay) > 1e-9:
        raise ValueError(f'sensor_delay must be a whole number of control periods ({period:g} s), '
                         f'got {delay!r} s')
    return int(steps)


def default_grasp(seconds: float, noise_std: float) -> LoopResult:
    """The grasp closed in-process on the default settings (hand, KF, fast SDRE, roll-off): the
    loop the benchmarks time and replay."""
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS
    from soft_gripper_sdre.learning.model import SDCModel
    law = make_law('sdre', SDCModel(), Weights(**DEFAULT_WEIGHTS), 0.0625)
    return run_closed_loop(law, duration=seconds, profile=GraspProfile(others='open'),
                           sim_config=SimConfig(scene='hand', noise_std=noise_std))
