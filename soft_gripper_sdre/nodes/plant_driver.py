"""The plant driver node: a gripper of two foreign fingers served the way a lab's driver would.

It stands in for a real robot's driver in front of the node graph (README, "Use with your own
gripper"): the fingers are the plants of :mod:`soft_gripper_sdre.sim.plants.presets`
(``plant``: ``tendon3`` or ``stiff2``, planar with two torques; ``pneumatic1``, planar with one
chamber pressure; ``trunk3``, a 3-D tip with three tendon tensions), and the loop runs on the
wall clock, not in lockstep. The gripper's shape gives the command's m inputs and the tip's d
coordinates; its bounds give each input's interval [lower, upper] in the input's unit (N·m, Pa,
N). A steady-clock timer ticks at ``rate`` (by default the plant's own: tendon3 200, stiff2 500,
pneumatic1 100, trunk3 250 Hz); each tick

1. takes the newest command (zero-order hold): the efforts ``<finger>/ax<k>`` for k < m of
   ``torque_commands``, clipped to the bounds (the preset's, narrowed by ``torque_limit`` and
   by ``input_lower`` / ``input_upper``). A command received more than ``command_timeout`` ago
   (wall time) is replaced by the rest input (zero; a one-sided input's bound nearest zero:
   a vented chamber, slack tendons) (``stale_ticks``: WARN in /diagnostics and a throttled
   warning with the command's age and the count: the finger springs back, so on a busy machine
   this is the first thing to look for), as is the absence of any command (``idle_ticks``);
2. advances both plants by the wall time elapsed since the previous tick, at most
   :data:`MAX_STEP_PERIODS` periods (a longer stall is not made up; ``late_ticks`` counts ticks
   more than 1.5 periods after the previous one, with a throttled warning giving the interval
   and the count, and WARN in /diagnostics while they grow);
3. measures the tips at wall time t_m (``time.time_ns()``) and stamps them t_m + δ, δ uniform in
   ±``stamp_jitter``: ``tip_positions`` carries the tips plus Gaussian noise of ``noise_std``
   per axis, published with the sensor-data QoS (best effort: a reliable reader does not match
   it; the estimator takes it with ``tips_reliability:=best_effort``), and ``drop_fraction`` of
   these messages are not published (``dropped``), at random; ``true_tip_positions`` carries
   the noise-free tips of every tick with the same stamps (reliable), for scoring.

Pose i is finger i's tip in its base frame (sim/plants/chain.py: X down the hanging finger, Y toward
the palm; Z = X × Y): (x, y, 0) for a planar finger, (x, y, z) for a 3-D one. Nothing publishes
/clock: every stamp is wall time.

Commands are never trusted: one that does not decode (unknown, missing or duplicate names — a
command for another number of inputs —, sizes) is counted (``bad_commands``) with a throttled
warning and the previous command stays in force; one with a NaN or Inf effort is counted
(``nonfinite_commands``) and the rest input is applied; one outside the bounds is clipped into
them, counted (``clipped_commands``) and warned of (a sender whose bounds are wider than the
driver's: its integral and feedforward act on inputs the finger does not receive).
/diagnostics (1 Hz) carries these counters and ``ticks``, ``published``, ``commands``, the
plant time, the command's age, the tick intervals, the shape and the bounds (``bounds``: ``ax0
[lower, upper], …`` per finger joined by ``;``, which the excitation node takes as its limit when
none is given: :mod:`soft_gripper_sdre.nodes.driver_limits`).
The node stops at ``duration`` of wall time (exit 0) or on SIGINT / SIGTERM.
"""
from __future__ import annotations

import math
import time

from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import (
    OK,
    WARN,
    Diagnostics,
    LatencyWindow,
    ThrottledLogger,
    run,
)
from soft_gripper_sdre.nodes.driver_limits import given_bounds
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    numbers_param,
    on_runtime_change,
)
from soft_gripper_sdre.nodes.topics import LOOP_QOS, NEWEST_QOS, TIP_POSITIONS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.plants.presets import GRIPPERS, RATES, plant_pair
from soft_gripper_sdre.sim.shape import InputBounds

#: the noise-free tips, for scoring (same type and stamps as tip_positions)
TRUE_TIP_POSITIONS = 'true_tip_positions'
#: the longest advance of the plants in one tick, in periods: a stall beyond it is not made up
MAX_STEP_PERIODS = 4
#: a tick more than this many periods after the previous one is late
LATE_PERIODS = 1.5
#: the fingers of each plant
N_FINGERS = 2


def _rate_problem(rate) -> str | None:
    return None if rate == 0.0 or 100.0 <= rate <= 1000.0 else \
        f'{rate:g} Hz: give 0 (the plant\'s own rate) or 100 to 1000 Hz'


def _two_names(names) -> str | None:
    why = cv.finger_names_problem(names)
    if why is None and len(names) != N_FINGERS:
        why = f'the plant has {N_FINGERS} fingers: give {N_FINGERS} names, got {len(names)}'
    return why


PARAMS = (
    Param('plant', 'tendon3', 'the gripper, from sim/plants/presets.py: tendon3 (an index and a '
          'thumb, soft three-link tendon fingers), stiff2 (two fast two-link fingers), pneumatic1 '
          '(one chamber each: one input, 0..60 kPa, planar tip), trunk3 (three-tendon '
          'segments: three inputs, 0..4 N, 3-D tip) or flexor2 (the tendon fingers driven by a '
          'flexor and an extensor tendon that only pull: two inputs, 0..4 N, planar tip)',
          choices=tuple(GRIPPERS), read_only=True),
    Param('finger_names', ['index', 'thumb'], 'the fingers in message order (pose i of the tips, '
          'torque_commands <finger>/ax<k> for k < m); two names, each a ROS name token',
          rule=_two_names, read_only=True),
    Param('rate', 0.0, "ticks per second: plants advanced, tips measured and published; 0 = the "
          "plant's own rate (tendon3 200, stiff2 500, pneumatic1 100, trunk3 250, flexor2 200 "
          "Hz); else 100 to 1000", 'Hz', 0.0, 1000.0, read_only=True, rule=_rate_problem),
    Param('stamp_jitter', 4e-4, 'each tip_positions stamp is the measurement time plus a uniform '
          'offset in ±stamp_jitter; less than half a period, so stamps keep their order', 's',
          0.0, 0.005, read_only=True),
    Param('drop_fraction', 0.01, 'fraction of tip_positions messages not published, at random',
          '', 0.0, 0.5, read_only=True),
    Param('noise_std', 5e-5, 'Gaussian noise on each measured tip coordinate', 'm', 0.0, 0.01,
          read_only=True),
    Param('seed', 0, 'seed of the noise, the jitter and the drops', '', 0, 2**31 - 1,
          read_only=True),
    Param('torque_limit', 0.0, "commands are clipped to ±torque_limit; 0 = each finger's "
          'actuator limit (tendon3 0.02, stiff2 0.25 N·m), which also caps a larger value; for the '
          'symmetric presets only (pneumatic1, trunk3: input_lower / input_upper)',
          'N·m', 0.0, 1.0, read_only=True),
    numbers_param('input_lower', "lower bound of each input in its SI unit, a list [u0, u1, …] "
                  "within the preset's bounds; '' with input_upper '' = the preset's (tendon3 "
                  '−0.02 N·m, stiff2 −0.25 N·m, pneumatic1 0 Pa, trunk3 0 N)'),
    numbers_param('input_upper', "upper bound of each input, a list [u0, u1, …] within the "
                  "preset's bounds, each above its lower bound; '' with input_lower '' = the "
                  "preset's (tendon3 0.02 N·m, stiff2 0.25 N·m, pneumatic1 60000 Pa, trunk3 4 N)"),
    Param('duration', 0.0, 'stop after this much wall time and exit (0 = run until shut down)',
          's', 0.0, 1e6, read_only=True),
    Param('command_timeout', 0.05, 'a command received longer ago than this (wall time) is '
          'replaced by zero torque', 's', 1e-3, 10.0),
)


class PlantDriverNode(Node):
    """Two foreign fingers on a wall-clock loop, served like a robot driver (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('plant_driver', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        if p['rate'] == 0.0:
            p['rate'] = RATES[p['plant']]
        self.period = 1.0 / p['rate']
        if p['stamp_jitter'] >= 0.5 * self.period:
            raise ParameterError(f"parameter 'stamp_jitter': {p['stamp_jitter']:g} s must be less "
                                 f"than half the period ({0.5 * self.period:g} s at rate "
                                 f"{p['rate']:g} Hz), or stamps could go back")
        on_runtime_change(self, PARAMS, apply=self.p.update)
        self.names = tuple(p['finger_names'])
        self.plants = plant_pair(p['plant'])
        self.shape = self.plants[0].shape
        self.m, self.d = self.shape.m, self.shape.d
        #: per finger and input the bounds commands are clipped to (n, m)
        self.lower, self.upper = finger_bounds(self.plants, p)
        #: per finger the input held without a command (n, m): the nearest to zero
        self.rest_input = np.clip(0.0, self.lower, self.upper)
        self.rng = np.random.default_rng(p['seed'])
        #: the command in force (n, m) and its receipt (monotonic s; None: none yet)
        self.command = self.rest_input.copy()
        self.command_received: float | None = None
        #: the input of the last tick (n, m) [input unit]
        self.applied = self.rest_input.copy()
        self.plant_time = 0.0
        self.done = False
        self._last_stamp = 0
        self._intervals = LatencyWindow(2000)
        self.log = ThrottledLogger(self.get_logger())
        self._late_reported = 0             # late_ticks at the previous /diagnostics

        self.cdr_tips = cdr.tips_codec(self.names)
        self.cdr_cmd = cdr.torques_codec(self.names, self.m)
        self.pub_tips = self.create_publisher(PoseArray, TIP_POSITIONS, qos_profile_sensor_data)
        self.pub_truth = self.create_publisher(PoseArray, TRUE_TIP_POSITIONS, LOOP_QOS)
        self.sub_cmd = self.create_subscription(JointState, TORQUE_COMMANDS, self.on_command,
                                                NEWEST_QOS, raw=True)
        self.diag = Diagnostics(self, hardware_id=f'plant_driver/{p["plant"]}')
        for key in ('ticks', 'late_ticks', 'stale_ticks'):     # reported from the start, at 0
            self.diag.counters[key] = 0
        cdr.watch(self.diag, self.cdr_cmd)
        self.diag.before_publish.append(self._refresh_diagnostics)
        self.diag.values['plant'] = p['plant']
        self.diag.values['shape'] = str(self.shape)
        self.diag.values['bounds'] = '; '.join(
            str(InputBounds(lo, hi)) for lo, hi in zip(self.lower, self.upper))
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._started = self._last_tick = time.monotonic()
        self._timer = self.create_timer(self.period, self._tick, clock=steady)
        freqs = ', '.join(f'{f.params.name} {f.natural_frequencies()[0]:.1f} Hz'
                          for f in self.plants)
        if self.m == 2 and np.array_equal(self.lower, -self.upper):
            limits = f'torque limit {", ".join(f"{x:g}" for x in self.upper[:, 0])} N·m'
        else:
            limits = f'{self.m} input(s), bounds {self.diag.values["bounds"]}'
        self.get_logger().info(
            f'driving {p["plant"]} ({freqs}) as {", ".join(self.names)} at {p["rate"]:g} Hz '
            f'on the wall clock; {limits}; tips in {self.d} dimensions')

    # -- commands ----------------------------------------------------------------------------
    def on_command(self, data: bytes) -> None:
        self.diag.count('commands')
        try:
            _stamp, u = self.cdr_cmd.decode(data)
        except cv.MessageError as exc:
            if _has_nonfinite_effort(data):
                self._take(self.rest_input.copy())
                self.diag.problem('nonfinite_commands', f'torque_commands with NaN or Inf: '
                                  f'the rest input ({exc})')
            else:
                self.diag.problem('bad_commands', f'rejected: {exc}; the previous command '
                                  'stays in force')
            return
        clipped = np.clip(u, self.lower, self.upper)
        if np.any(clipped != u):
            self.diag.problem('clipped_commands', 'a command outside the bounds '
                              f'({self.diag.values["bounds"]}) was clipped into them: the finger '
                              'receives other inputs than its sender computed; give the sender '
                              "the driver's bounds (input_lower / input_upper, torque_limit)")
        self._take(clipped)

    def _take(self, u: np.ndarray) -> None:
        self.command = u
        self.command_received = time.monotonic()

    def _torque(self, now: float) -> np.ndarray:
        """The input to hold over this tick: the command, or the rest input if none or stale."""
        if self.command_received is None:
            self.diag.count('idle_ticks')
            return self.rest_input.copy()
        age = now - self.command_received
        if age > self.p['command_timeout']:
            self.diag.count('stale_ticks')
            if self.diag.level == OK or self.diag.message.startswith('late ticks'):
                self.diag.set_status(WARN, 'torque_commands stale: zero torque')
            self.log.warn('stale', f'the newest torque_commands is {1e3 * age:.1f} ms old (more '
                          f'than command_timeout {1e3 * self.p["command_timeout"]:g} ms): '
                          'applying the rest input, the finger springs back; '
                          f'{self.diag.counters["stale_ticks"]} stale tick(s) in all')
            return self.rest_input.copy()
        if self.diag.level == WARN and self.diag.message.startswith('torque_commands stale'):
            self.diag.set_status(OK, 'driving')
        return self.command

    # -- the loop ----------------------------------------------------------------------------
    def _tick(self) -> None:
        now = time.monotonic()
        elapsed = now - self._last_tick
        self._last_tick = now
        self._intervals.add(elapsed)
        if elapsed > LATE_PERIODS * self.period:
            self.diag.count('late_ticks')
            self.log.warn('late', f'tick {1e3 * elapsed:.1f} ms after the previous one (period '
                          f'{1e3 * self.period:g} ms): the driver was starved of CPU; '
                          f'{self.diag.counters["late_ticks"]} late tick(s) in all')
        dt = min(elapsed, MAX_STEP_PERIODS * self.period)
        self.applied = self._torque(now)
        for plant, u in zip(self.plants, self.applied):
            plant.step(u, dt)
        self.plant_time += dt
        jitter = self.rng.uniform(-1.0, 1.0) * self.p['stamp_jitter']
        stamp = time.time_ns() + int(round(jitter * 1e9))      # the measurement's wall time
        stamp = max(stamp, self._last_stamp + 1)   # a tick that catches up after a stall is early
        self._last_stamp = stamp
        self.diag.count('ticks')
        d = self.d
        truth = np.zeros((N_FINGERS, 3))
        truth[:, :d] = [plant.tip() for plant in self.plants]
        self.pub_truth.publish(self.cdr_tips.encode(stamp, truth))
        measured = truth.copy()
        measured[:, :d] += self.rng.normal(0.0, self.p['noise_std'], (N_FINGERS, d))
        if self.rng.random() < self.p['drop_fraction']:
            self.diag.count('dropped')
        else:
            self.pub_tips.publish(self.cdr_tips.encode(stamp, measured))
            self.diag.count('published')
        if self.p['duration'] > 0 and now - self._started >= self.p['duration']:
            self._timer.cancel()
            self.done = True
            self.get_logger().info(f'duration reached after {self.diag.counters["ticks"]} ticks; '
                                   'stopping')

    def _refresh_diagnostics(self) -> None:
        late = self.diag.counters['late_ticks']
        if late > self._late_reported and self.diag.level == OK:
            self.diag.set_status(WARN, f'late ticks (a busy machine): {late - self._late_reported} '
                                 f'since the last report, {late} in all')
        elif late == self._late_reported and self.diag.message.startswith('late ticks'):
            self.diag.set_status(OK, 'driving')
        self._late_reported = late
        self.diag.values['plant_time'] = f'{self.plant_time:.3f}'
        if self.command_received is not None:
            age = time.monotonic() - self.command_received
            self.diag.values['command_age_ms'] = f'{1e3 * age:.1f}'
        self.diag.values.update(self._intervals.summary('tick_interval_us'))


def finger_bounds(plants, p: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per finger and input the (lower, upper) bounds (n, m) of the commands: each finger's
    actuator bounds, narrowed to ±``torque_limit`` (if > 0: symmetric presets only) and to
    ``input_lower`` / ``input_upper`` (if given).

    Raises:
        ParameterError: ``torque_limit`` for a preset with one-sided inputs, or ``input_lower``
            / ``input_upper`` not one value per input or outside the preset's bounds (the
            message names them).
    """
    m = plants[0].shape.m
    lower = np.array([f.bounds.lower for f in plants])
    upper = np.array([f.bounds.upper for f in plants])
    if p['torque_limit'] > 0:
        if any(f.bounds.symmetric_limit is None for f in plants):
            raise ParameterError(f"parameter 'torque_limit': plant {p['plant']!r} has inputs "
                                 f'that are not ±a limit ({plants[0].bounds}); narrow them with '
                                 'input_lower / input_upper')
        lower = np.maximum(lower, -p['torque_limit'])
        upper = np.minimum(upper, p['torque_limit'])
    given = given_bounds(p, m, "the preset's bounds", f" (plant {p['plant']!r})")
    if given is None:
        return lower, upper
    if np.any(given.lower < lower) or np.any(given.upper > upper):
        raise ParameterError(f"parameters 'input_lower', 'input_upper': [{given}] reaches beyond "
                             f"the plant's bounds [{plants[0].bounds}]")
    return np.broadcast_to(given.lower, lower.shape).copy(), np.broadcast_to(
        given.upper, upper.shape).copy()


def _has_nonfinite_effort(data: bytes) -> bool:
    """Whether ``data`` is a JointState whose efforts hold a NaN or Inf."""
    try:
        msg = deserialize_message(data, JointState)
    except Exception:       # rclpy's RMWError: not CDR of a JointState at all
        return False
    return not all(math.isfinite(e) for e in msg.effort)


def main(args=None) -> int:
    return run(PlantDriverNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
