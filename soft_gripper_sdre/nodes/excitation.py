"""The excitation node: plays identification torques on ``torque_commands`` and exits when done.

Plays ``signals`` in order (the paper's u1..u4, the identifying x1, x2, or multisines and chirps
from the YAML ``spec_file``, :mod:`soft_gripper_sdre.sim.signal_specs`), each after ``settle_time``
of zero torque (the first one also until ``settle_samples`` tips were heard, below), on
``finger`` or on every finger, scaled by ``amplitude`` and clipped to the limit (below); a recorder
running meanwhile captures ``tip_positions`` and ``torque_commands`` for
``tools.learning.train --bag``.

Start: the run begins only once ``torque_commands`` has ``min_command_subscribers`` matched
subscribers (default 2: the driver and the recorder) and, with 2 or more and a ``recorder_node``,
once that recorder reports on /diagnostics that it has received both topics it records for
training: ``messages /tip_positions`` and ``messages /torque_commands`` at least 1 (the names as
this node resolves them). A matched command reader alone is not enough: the recorder's tips
reader may match the driver seconds later, and a bag whose first tips come after its first
commands has no settle phase. Until then each tip message is answered with zero torque (tips
timing; timer timing publishes zero on its timer once tips were heard), which is what the
recorder first hears of the commands. Plan time starts at the first tips after that, so the
recording holds the whole settle phase (the rest pose and the noise level for training). So the
driver, the recorder and this node may start in any order. Not ready within ``startup_timeout``
is a fault naming what was missing; /diagnostics shows ``signal`` 'waiting for …' meanwhile.

Settle: the first settle phase (before the first probe of ``level: auto`` or the first signal)
lasts ``settle_time`` of tip stamps and, with ``settle_time`` > 0, until the node has heard at
least ``settle_samples`` tip messages since the start: it is extended, at zero torque, when the
driver delivers fewer in ``settle_time`` (a lower rate, dropped messages, a loaded machine that
delays the driver's ticks), and the rest of the plan (and ``plan_time``) is shifted by the
extension. With tips timing every tip heard is answered with zero torque, so a recorder that hears
the same tips holds at least ``settle_samples`` of them before the first non-zero torque, which
training takes the noise level from. The tips answered with zero go to /diagnostics
(``settle_tips``) and the log at the first non-zero torque.

Level (``level``): ``fixed`` plays the signals at ``amplitude``. ``auto`` searches the
amplitude on the finger (:class:`~soft_gripper_sdre.sim.excitation.LevelSearch`): after the settle
phase, probes at amplitudes rising from ``level_start``, each ``level_probe_time`` long and
followed by ``settle_time`` at zero, until a probe moves an excited tip ``level_target`` ×
``max_excursion`` from rest (or reaches the torque limit); the signal is then played at the
amplitude that scales the response to that target, kept off the clip. With ``level_per:
signal`` (the default) each signal is levelled on its own, just before it plays: its probes are
the signal itself, its first ``level_probe_time`` seconds, each excursion scaled by the
signal's measured response (the whole signal's peak excursion over the probe's, as a linear model
fit on the probe's record predicts them:
:meth:`~soft_gripper_sdre.sim.excitation.SignalProbe.response_ratio`), the first probe at the
amplitude the signal before was played at (so usually one or two probes each), because one
amplitude for every signal leaves the weaker or faster ones short of the target. With
``level_per: plan`` one search before the first signal probes with a sine at the signals' peak
torque and every signal is played at its amplitude. The probes are published and recorded like
the signals. The amplitude, the probes and the share of the signals' samples at the clip go to
the log and /diagnostics (``amplitude``, ``probes``, ``clip_share``; ``levels``: each signal's).

Timing (``timing``):

* ``tips`` (default): each tip message is answered with the torque for its stamp, stamped with
  it, as the controller answers estimates: in lockstep with the simulator node (which steps when
  the command for its current period arrives), and at the sensor's rate with a realtime driver.
* ``timer``: a timer on the node's clock publishes the torque for the clock's time every
  ``period``, stamped with that time, for drivers that want commands at their own rate.

Limit (``limit_source`` in /diagnostics and the start-up line): given as a parameter
(``input_lower`` / ``input_upper``, else ``torque_limit`` > 0: ``parameter``), or else the
driver's (``driver``, the default: ``torque_limit`` 0 and both lists empty): the node then waits,
before it listens to the tips or sends anything, for a driver in its namespace to report its
bounds on /diagnostics (``plant_driver`` and the simulator node do;
:mod:`soft_gripper_sdre.nodes.driver_limits`) and plays within the tightest interval of each
input over the driver's fingers. Meanwhile /diagnostics shows ``signal`` 'waiting for the
driver's bounds' and a WARN every :data:`WAIT_LOG_PERIOD` says what it waits for and which
parameters to give instead; no report within ``driver_bounds_timeout`` (0: wait forever) is a
fault (exit status 1), and a parameter the run cannot be built with for the driver's inputs
(a spec file's signals for another number of inputs) ends the node with exit status 2. A
``bounds`` value that does not read is ignored with a warning.

Inputs: for the hand, two torques clipped to ±``torque_limit``. Bounds of 1 to 4 inputs (in the
input's unit: N·m, Pa, N) make the node play for that many inputs and publish
``<finger>/ax<k>`` for k < m, never outside [lower[k], upper[k]]: the built-in signals as shares
of each interval, about its middle for a two-sided input and from its rest value (the bound
nearest zero) into it for a one-sided one, a chamber or a tendon; a spec file's signals as
inputs in their units, clipped (:mod:`soft_gripper_sdre.sim.excitation`). "Zero torque" below is
then every input at rest. Symmetric bounds on two inputs are the hand's ±torque_limit.

Driver limits: a driver in the namespace whose reported bounds do not contain a limit given as a
parameter (or that takes another number of inputs) is refused: the node stops as a fault (exit
status 1, the error naming both limits and the parameter), before the run or during it, for the
driver would clip the signals into others than the ones recorded as sent. A driver wider than
the limit given is fine. A rising count of commands the driver clipped gets a WARN with the
count (``driver_clipped``).

Stops: at the end of the plan, on shutdown (SIGINT/SIGTERM) and on a fault, zero torque is
published before the node exits (status 0 at the end of the plan, 1 after a fault). Faults: no
tips for ``tips_timeout`` of wall time (or none at all within ``startup_timeout``), tip stamps
jumping back by more than ``reset_on_jump`` (a restarted driver), and an excited tip moving more
than ``max_excursion`` from where it was at the start (the distance in x, y and z: a 3-D tip's z
counts, a planar one's is 0; the level search measures its excursions the same way).
Malformed or old tip messages are counted, warned about (throttled) and not answered. Counters
and the signal being played go to /diagnostics.

The torque at each run time is :class:`~soft_gripper_sdre.sim.excitation_run.ExcitationRun`'s
(settle, probes, plan); what /diagnostics and the log show of the run is
:class:`~soft_gripper_sdre.nodes.excitation_report.RunReport`'s. This module is the ROS side:
parameters, tips and their stamps, timing, the start and the stops.
"""
from __future__ import annotations

import re
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, OK, Diagnostics, run
from soft_gripper_sdre.nodes.driver_limits import DriverLimits, given_bounds
from soft_gripper_sdre.nodes.excitation_report import ACTIVITY, RunReport
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    numbers_param,
    tips_reliability_param,
    with_reliability,
)
from soft_gripper_sdre.nodes.topics import (
    DIAGNOSTICS,
    LOOP_QOS,
    NEWEST_QOS,
    STREAM_QOS,
    TIP_POSITIONS,
    TORQUE_COMMANDS,
)
from soft_gripper_sdre.sim.excitation import ExcitationPlan, LevelSearch, LevelSettings
from soft_gripper_sdre.sim.excitation_run import ExcitationRun, Phase
from soft_gripper_sdre.sim.settle import SettlePhase
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.sim.signal_specs import MAX_TORQUE, SignalSpecError, resolve_signals
from soft_gripper_sdre.sim.signals import SIGNALS

#: the plan's torque limit where it goes unused (with bounds of the inputs) and none was given
PLAN_TORQUE_LIMIT = 0.1
#: the bounds of any input for the checks before the driver's are known [the input's unit]
ANY_BOUND = 1e12
#: while waiting for the driver's bounds, a line in the log this often [s of wall time]
WAIT_LOG_PERIOD = 5.0

PARAMS = (
    Param('signals', ['u1'], f'signals to play in order, each after the settle phase: built-in '
          f'({", ".join(SIGNALS)}) or named in spec_file', read_only=True),
    Param('spec_file', '', 'YAML file of user-defined multisines and chirps (see '
          'soft_gripper_sdre/sim/signal_specs.py); empty = built-in signals only', read_only=True),
    Param('duration', 0.0, 'length of each signal (0 = its own: 10 s for the built-in ones)', 's',
          0.0, 3600.0, read_only=True),
    Param('settle_time', 0.5, 'zero torque before each signal (the first one also gives the rest '
          'pose and the noise level to training)', 's', 0.0, 600.0, read_only=True),
    Param('settle_samples', 100, 'the first settle phase goes on past settle_time until this many '
          'tip messages were heard since the start (with settle_time > 0; 0 = settle_time alone)',
          '', 0, 1_000_000, read_only=True),
    finger_names_param('the fingers: pose i of tip_positions is finger i; the torque_commands '
                       'names are <finger>/ax0 … <finger>/ax<m−1>'),
    Param('finger', -1, 'the finger to excite, an index into finger_names (-1 = all); the others '
          'get zero torque', '', -1, 3, read_only=True),
    Param('torque_limit', 0.0, "the hand's two torques: every torque is clipped to ±limit (the "
          "simulator's actuator limit is 0.1 N·m; the paper's signals peak at 0.0675); 0 = the "
          "driver's limit, from its bounds on /diagnostics (see driver_bounds_timeout), unless "
          'input_lower / input_upper give the bounds', 'N·m', 0.0, 1.0, read_only=True),
    numbers_param('input_lower', 'lower bound of each input in its SI unit (N·m, Pa, N), a list '
                  "[u0, u1, …] of 1 to 4 values: the finger's inputs; '' with input_upper '' = "
                  "−torque_limit on 2 inputs (the hand), or the driver's with torque_limit 0"),
    numbers_param('input_upper', 'upper bound of each input, a list [u0, u1, …], each above its '
                  "lower bound; '' with input_lower '' = torque_limit on 2 inputs (the hand), "
                  "or the driver's with torque_limit 0"),
    Param('driver_bounds_timeout', 60.0, "no limit given (torque_limit 0, input_lower / "
          "input_upper ''): wall time to wait for a driver in this node's namespace to report "
          "its bounds on /diagnostics before stopping as a fault (exit status 1); 0 = wait "
          'forever', 's', 0.0, 86400.0, read_only=True),
    Param('timing', 'tips', 'answer each tip message with the torque for its stamp, or publish on '
          'a timer of the node\'s clock', choices=('tips', 'timer'), read_only=True),
    Param('period', 0.001, 'timer timing: the command period', 's', 1e-4, 1.0, read_only=True),
    Param('tips_timeout', 1.0, 'wall time without tip_positions after which the run stops as a '
          'fault', 's', 0.01, 600.0, read_only=True),
    Param('startup_timeout', 60.0, 'wall time to wait for the first tip_positions message and for '
          'min_command_subscribers', 's', 0.1, 3600.0, read_only=True),
    Param('min_command_subscribers', 2, 'start only once torque_commands has this many matched '
          'subscribers (2: the driver and the recorder; 1 without a recorder)', '', 0, 64,
          read_only=True),
    Param('recorder_node', 'recorder', 'with min_command_subscribers >= 2: the recorder in this '
          "node's namespace whose /diagnostics must show messages of tip_positions and "
          "torque_commands received before the run starts; '' = wait for no report",
          rule=lambda name: None if re.fullmatch(r'([A-Za-z][A-Za-z0-9_]*)?', name) else
          f'{name!r} is not a node name (a letter, then letters, digits and _; or empty)',
          read_only=True),
    Param('reset_on_jump', 0.1, 'tip stamps jumping back by more than this (a restarted driver) '
          'stop the run as a fault', 's', 1e-3, 1e6, read_only=True),
    Param('stop_wait', 0.2, 'shutdown, tips timing: wall time to wait for one more tip message to '
          'answer with zero torque (then zero goes out stamped with the newest tips)',
          's', 0.0, 10.0, read_only=True),
    Param('max_excursion', 0.0, 'stop as a fault when an excited tip moves further than this from '
          'its starting position (0 = off; level auto needs it)', 'm', 0.0, 1.0, read_only=True),
    Param('amplitude', 1.0, 'level fixed: every signal (built-in or spec_file) is multiplied by '
          'this before the torque_limit clip', '', 1e-6, 100.0, read_only=True),
    Param('level', 'fixed', 'fixed: play the signals at amplitude; auto: choose the amplitude by '
          'probes on the finger first (needs max_excursion > 0 and settle_time > 0)',
          choices=('fixed', 'auto'), read_only=True),
    Param('level_target', 0.5, 'level auto: the peak excursion aimed at, as a fraction of '
          'max_excursion', '', 0.05, 1.0, read_only=True),
    Param('level_start', 0.05, 'level auto: the amplitude of the first probe (then up to twice the '
          'last per probe)', '', 1e-6, 100.0, read_only=True),
    Param('level_probe_time', 2.0, 'level auto: the length of each probe (level_per signal: '
          "the signal's first seconds; plan: two periods of a "
          "sine at the signals' peak torque; settle_time at zero after each)", 's', 0.1, 60.0,
          read_only=True),
    Param('level_per', 'signal', 'level auto: signal = each signal its own amplitude, probed '
          'with its own first seconds (the first probe of each at the level of the one '
          'before); plan = one amplitude for every signal, probed with a sine at their peak '
          'torque', choices=('signal', 'plan'), read_only=True),
    tips_reliability_param(),
)


class ExcitationNode(Node):
    """Identification torques on ``torque_commands`` (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('excitation', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        self.names = tuple(p['finger_names'])
        self.n = len(self.names)
        given = given_limit(p)
        if given is None:
            check_without_limit(p, self.n)
        #: the run (None while the limit is awaited from the driver), its number of inputs,
        #: where its limit came from ('parameter' or 'driver') and the driver it came from
        self.run: ExcitationRun | None = None
        self.m: int | None = None
        self.limit_source = 'parameter' if given is not None else 'driver'
        self.limit_driver: str | None = None
        self.newest_tips: np.ndarray | None = None
        self.done = False
        self.exit_code = 0
        self.start_ns: int | None = None        # stamp of the first tips: plan time 0 (tips timing)
        self.clock_start_ns: int | None = None  # clock time of the first tick (timer timing)
        self.last_ns = -1                       # newest accepted tip stamp
        self.answered_ns = -1                   # stamp of the last command published
        self.last_heard: float | None = None    # wall time of the newest accepted tips
        self.stopping = False                   # shutdown: answer the next tips with zero
        self.stopped = False                    # the final zero went out
        self._waiting_since = time.monotonic()  # for the driver's bounds
        self._wait_logged = self._waiting_since
        self._deadline = self._waiting_since + p['startup_timeout']
        self.cdr_tips = cdr.tips_codec(self.names)
        self.cdr_cmd = None
        self.pub_cmd = self.create_publisher(JointState, TORQUE_COMMANDS, LOOP_QOS)
        self.sub_tips = None
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_tips)
        self.diag.values['limit_source'] = self.limit_source
        #: the recorder whose report the start waits for (its full name), and its newest values
        self.recorder = None
        if p['recorder_node'] and p['min_command_subscribers'] >= 2:
            self.recorder = f'{self.get_namespace().rstrip("/")}/{p["recorder_node"]}'
        self.recorder_values: dict[str, str] = {}
        self.recorded = tuple(f'messages {self.resolve_topic_name(t)}'
                              for t in (TIP_POSITIONS, TORQUE_COMMANDS))
        self.sub_diag = (self.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_report,
                                                  STREAM_QOS) if self.recorder else None)
        self.report: RunReport | None = None
        self.driver_limits = DriverLimits(self, self.diag, None, take=self._take_driver_limit,
                                          refuse=self._refuse_limit)
        self._watchdog = self.create_timer(0.05, self._check_watchdog)
        if given is not None:
            self._configure(given)
        else:
            self.diag.values.update(signal="waiting for the driver's bounds", limit='')
            self.get_logger().info(
                f"no limit given (torque_limit 0, input_lower / input_upper ''): waiting for the "
                f"driver's bounds on /diagnostics ({self._driver_text()}){self._timeout_text()}")

    def _configure(self, bounds: InputBounds) -> None:
        """Build the run within ``bounds`` and start listening to the tips (the commands' names
        follow its number of inputs).

        Raises:
            ParameterError: a parameter the run cannot be built with (the message names it).
        """
        self.run = excitation_run(self.p, self.n, bounds)
        self.m = self.run.plan.m
        self.cdr_cmd = cdr.torques_codec(self.names, self.m)
        p = self.p
        self.sub_tips = self.create_subscription(
            PoseArray, TIP_POSITIONS, self.on_tips,
            with_reliability(NEWEST_QOS, p['tips_reliability']), raw=True)
        self.report = RunReport(self.diag, self.get_logger(), self.run, p)
        self.diag.values['limit'] = str(bounds)
        self.driver_limits.use(bounds)
        self._deadline = time.monotonic() + p['startup_timeout']
        if p['timing'] == 'timer':
            self._ticker = self.create_timer(p['period'], self._on_tick, clock=self.get_clock())
        self.report.log_start(self.names, self._source_text())
        if self.recorder is not None:
            self.get_logger().info(f'... and once the recorder {self.recorder} reports on '
                                   f'/diagnostics that it received {TIP_POSITIONS} and '
                                   f"{TORQUE_COMMANDS} (recorder_node; '' waits for no report)")

    def _source_text(self) -> str:
        """Where the limit came from, for the log."""
        if self.limit_source == 'driver':
            return f'limit_source driver: the bounds of {self.limit_driver}'
        return 'limit_source parameter'

    def _driver_text(self) -> str:
        namespace = self.get_namespace()
        return (f"a node in the namespace {namespace} reporting 'bounds', as plant_driver and "
                'the simulator node do; or give torque_limit (± torques on two inputs) or '
                'input_lower / input_upper')

    def _timeout_text(self) -> str:
        timeout = self.p['driver_bounds_timeout']
        return (f'; giving up after driver_bounds_timeout ({timeout:g} s)' if timeout > 0
                else '; waiting without end (driver_bounds_timeout 0)')

    def _take_driver_limit(self, driver: str, bounds: InputBounds, text: str) -> None:
        """The driver ``driver`` reported ``bounds`` (``text``) while none were given: the
        excitation's limit is theirs (a parameter the run cannot be built with ends the node
        with exit status 2)."""
        if self.run is not None or self.done:
            return
        self.limit_driver = driver
        try:
            self._configure(bounds)
        except ParameterError as exc:
            self.get_logger().fatal(f'bad parameter: {exc} (for the bounds of the driver '
                                    f'{driver}: {text})')
            self.diag.set_status(ERROR, f'bad parameter: {exc}')
            self.exit_code, self.done, self.stopped = 2, True, True
            return
        self.get_logger().info(f'the limit is the driver {driver}\'s: {bounds} (its bounds on '
                               '/diagnostics, the tightest over its fingers; limit_source driver)')

    def _refuse_limit(self, why: str) -> None:
        """A driver does not take the whole limit: stop as a fault before (or while) sending
        what it would clip."""
        self.fault(why, max(self.last_ns, 0))

    # -- inputs ------------------------------------------------------------------------------
    def on_tips(self, data: bytes) -> None:
        if self.stopped:
            return
        try:
            stamp, tips = self.cdr_tips.decode(data)
        except cv.MessageError as exc:
            self.diag.problem('bad_tips', f'rejected: {exc}')
            return
        if stamp <= self.last_ns:
            if stamp < self.last_ns - int(self.p['reset_on_jump'] * cv.NS):
                self.fault(f'tip stamps jumped back from {self.last_ns / cv.NS:.4f} s to '
                           f'{stamp / cv.NS:.4f} s (a restarted driver?)', stamp)
            else:
                self.diag.problem('old_tips', f'rejected: stamp {stamp} ns is not newer than '
                                              f'{self.last_ns} ns')
            return
        self.last_ns, self.last_heard = stamp, time.monotonic()
        self.newest_tips = tips
        self.diag.count('tips')
        if self.stopping:
            self.stop(stamp, 'stopped on shutdown')
            return
        if self.start_ns is None and not self._start(stamp, tips):
            return
        excursion = self.run.excursion(tips) if self.p['max_excursion'] > 0 else 0.0
        if excursion > self.p['max_excursion']:
            self.fault(f'a tip moved {1e3 * excursion:.2f} mm from its start, '
                       f'more than max_excursion ({1e3 * self.p["max_excursion"]:g} mm)', stamp)
            return
        if self.p['timing'] == 'tips':
            self._advance(stamp, (stamp - self.start_ns) / cv.NS, tips)
        self.run.settle.heard_tips()            # (counted after its own answer: tips timing
                                                # answers it before it counts)

    def _on_report(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.recorder:
                self.recorder_values = {kv.key: kv.value for kv in status.values}

    def start_problem(self) -> str | None:
        """What the run still waits for (module doc, "Start"), or None."""
        subscribers = self.pub_cmd.get_subscription_count()
        self.diag.values['command_subscribers'] = str(subscribers)
        if subscribers < self.p['min_command_subscribers']:
            return (f'{self.p["min_command_subscribers"]} {TORQUE_COMMANDS} subscribers '
                    f'({subscribers} matched)')
        if self.recorder is not None:
            missing = [key.split(' ', 1)[1] for key in self.recorded
                       if _count(self.recorder_values.get(key)) < 1]
            if missing:
                heard = 'no report yet' if not self.recorder_values else 'none of ' + ', '.join(
                    missing)
                return f'the recorder {self.recorder} to receive {" and ".join(missing)} ({heard})'
        return None

    def _start(self, stamp: int, tips: np.ndarray) -> bool:
        """Start the run at these tips once nothing is missing (:meth:`start_problem`); until
        then answer them with zero (tips timing). Whether it started."""
        problem = self.start_problem()
        if problem is not None:
            self.diag.values['signal'] = f'waiting for {problem}'
            if self.p['timing'] == 'tips':
                self._publish(stamp, self.run.plan.rest_inputs())
            return False
        self.start_ns = stamp
        self.run.start(tips)
        if self.sub_diag is not None:
            self.destroy_subscription(self.sub_diag)
            self.sub_diag = None
        subscribers = self.diag.values['command_subscribers']
        recorder = (f' and the recorder {self.recorder} hearing both topics' if self.recorder
                    else '')
        self.get_logger().info(f'tip_positions at t = {stamp / cv.NS:.4f} s with {subscribers} '
                               f'{TORQUE_COMMANDS} subscriber(s){recorder}: the run starts')
        return True

    def _on_tick(self) -> None:
        if self.stopped:
            return
        now = self.get_clock().now().nanoseconds
        if self.start_ns is None:           # waiting to start: zero, once the driver is heard
            if self.newest_tips is not None and now > self.answered_ns:
                self._publish(now, self.run.plan.rest_inputs())
            return
        if self.clock_start_ns is None:
            self.clock_start_ns = now
        if now <= self.answered_ns:
            return
        self._advance(now, (now - self.clock_start_ns) / cv.NS, self.newest_tips)

    def _check_watchdog(self) -> None:
        if self.stopped:
            return
        now = time.monotonic()
        if self.run is None:
            self._check_driver_wait(now)
            return
        if self.last_heard is None and now > self._deadline:
            self.fault(f'no tip_positions within startup_timeout ({self.p["startup_timeout"]:g} s)',
                       max(self.last_ns, 0))
        elif self.start_ns is None and now > self._deadline:
            problem = self.start_problem()
            if problem is not None and problem.startswith('the recorder'):
                self.fault(f'still waiting for {problem} after startup_timeout '
                           f'({self.p["startup_timeout"]:g} s): start the recorder '
                           f'({self.recorder}), or set recorder_node to its name or to \'\'',
                           self.last_ns)
                return
            self.fault(f'{TORQUE_COMMANDS} has {self.pub_cmd.get_subscription_count()} matched '
                       f'subscriber(s) after startup_timeout ({self.p["startup_timeout"]:g} s); '
                       f'min_command_subscribers is {self.p["min_command_subscribers"]}: start the '
                       'driver and the recorder, or lower min_command_subscribers', self.last_ns)
        elif self.last_heard is not None and now - self.last_heard > self.p['tips_timeout']:
            self.fault(f'no tip_positions for {self.p["tips_timeout"]:g} s of wall time since '
                       f't = {self.last_ns / cv.NS:.4f} s', self.last_ns)

    def _check_driver_wait(self, now: float) -> None:
        """Waiting for the driver's bounds: a line every :data:`WAIT_LOG_PERIOD`, and the fault
        at ``driver_bounds_timeout``."""
        waited = now - self._waiting_since
        timeout = self.p['driver_bounds_timeout']
        if 0 < timeout < waited:
            ignored = self.diag.values.get('driver_bounds_ignored')
            heard = f' (ignored, not bounds: {ignored})' if ignored else ''
            self.fault(f"no driver reported its bounds on /diagnostics{heard} within "
                       f'driver_bounds_timeout ({timeout:g} s): give the limit as torque_limit '
                       '(± torques on two inputs) or input_lower / input_upper, start the driver, '
                       'or set driver_bounds_timeout 0 to wait without end', max(self.last_ns, 0))
        elif now - self._wait_logged >= WAIT_LOG_PERIOD:
            self._wait_logged = now
            self.get_logger().warn(f"still waiting for the driver's bounds on /diagnostics after "
                                   f'{waited:.0f} s ({self._driver_text()}){self._timeout_text()}')

    # -- outputs -----------------------------------------------------------------------------
    def _advance(self, stamp: int, t: float, tips: np.ndarray) -> None:
        """Publish the run's torque for run time ``t`` [s] stamped ``stamp`` (``tips``: the
        newest), or stop at the end of the plan."""
        step = self.run.at(t, tips)
        self.report.step(step)
        if step.phase is Phase.OVER:
            self.stop(stamp, f'finished: {self.run.whole.duration:g} s played')
            return
        self._publish(stamp, step.u)
        self.diag.good('commands', ACTIVITY[step.phase])

    def _publish(self, stamp: int, u: np.ndarray) -> None:
        self.pub_cmd.publish(self.cdr_cmd.encode(stamp, u))
        self.answered_ns = stamp

    def stop(self, stamp: int, why: str, level: int = OK) -> None:
        """Publish zero torque stamped ``stamp`` and end the run (the node exits)."""
        if self.stopped:
            return
        if self.run is not None:            # (without a run nothing was ever sent)
            self._publish(stamp, self.run.plan.rest_inputs())
        self.stopped = self.done = True
        self.diag.values['signal'] = 'stopped'
        self.diag.set_status(level, why)
        if level == OK:
            self.get_logger().info(f'{why}; zero torque sent at t = {stamp / cv.NS:.4f} s')

    def fault(self, why: str, stamp: int) -> None:
        """Stop with zero torque and exit status 1, reporting ``why`` (ERROR)."""
        self.exit_code = 1
        self.get_logger().error(f'{why}: stopping with zero torque')
        self.stop(stamp, why, ERROR)

    def close(self) -> None:
        """The shutdown stop (run() calls this on SIGINT/SIGTERM and after the end): unless the
        final zero went out, answer the next tips with zero (tips timing; waiting at most
        ``stop_wait``) or publish it on the clock now, and wait until it is delivered."""
        if self.stopped or not self.context.ok() or self.run is None:
            return
        if self.p['timing'] == 'timer' and self.start_ns is not None:
            self.stop(max(self.get_clock().now().nanoseconds, self.answered_ns + 1),
                      'stopped on shutdown')
        elif self.executor is not None and self.start_ns is not None:
            self.stopping = True
            deadline = time.monotonic() + self.p['stop_wait']
            while not self.stopped and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.02)
        if not self.stopped:          # no tips came: zero for the newest stamp heard
            self.stop(max(self.last_ns, 0), 'stopped on shutdown')
        self.pub_cmd.wait_for_all_acked(Duration(seconds=1))


def _count(value: str | None) -> int:
    """A count of a /diagnostics report (0 when absent or not a number)."""
    try:
        return int(value) if value is not None else 0
    except ValueError:
        return 0


def excitation_run(p: dict, n: int, bounds: InputBounds | None = None) -> ExcitationRun:
    """The run the node's parameters ``p`` describe for ``n`` fingers within ``bounds`` (None:
    the limit the parameters give, :func:`given_limit`): the plan of its signals, the first
    settle phase and, with ``level: auto``, the amplitude search. Symmetric bounds on two inputs
    are the hand's ±``torque_limit`` (``p['torque_limit']`` is set to theirs).

    Raises:
        ParameterError: a bad finger, signal, spec file or level setting, or no limit at all
            (the message names it).
    """
    if bounds is None:
        bounds = given_limit(p)
        if bounds is None:
            raise ParameterError("parameters 'torque_limit', 'input_lower', 'input_upper': no "
                                 "limit given (torque_limit 0, input_lower / input_upper ''), "
                                 "and none from a driver")
    _check_finger(p, n)
    finger = None if p['finger'] < 0 else p['finger']
    if bounds.m == 2 and bounds.symmetric_limit is not None:
        p['torque_limit'] = bounds.symmetric_limit
        bounds = None
    m = None if bounds is None else bounds.m
    limit = MAX_TORQUE if bounds is None else max(
        MAX_TORQUE, 10 * float(np.abs(np.concatenate([bounds.lower, bounds.upper])).max()))
    try:
        signals = resolve_signals(list(p['signals']), p['spec_file'] or None,
                                  p['duration'] or None, m, limit,
                                  bounds is not None and bool(bounds.one_sided.all()))
        plan = ExcitationPlan(signals, p['settle_time'], n, finger,
                              p['torque_limit'] or PLAN_TORQUE_LIMIT, p['amplitude'], bounds)
    except (SignalSpecError, ValueError) as exc:
        raise ParameterError(str(exc)) from None
    settle = SettlePhase(p['settle_time'], p['settle_samples'])
    if p['level'] == 'auto' and p.get('level_per', 'plan') == 'signal':
        return ExcitationRun(plan, settle, per_signal=signal_searches(p, plan, finger))
    search = level_search(p, plan, finger) if p['level'] == 'auto' else None
    return ExcitationRun(plan, settle, search)


def given_limit(p: dict) -> InputBounds | None:
    """The limit the parameters ``p`` give: ``input_lower`` / ``input_upper`` (1 to 4 inputs),
    else ±``torque_limit`` on the hand's two inputs; None when neither is given (torque_limit 0,
    both lists empty): the limit is then the driver's.

    Raises:
        ParameterError: a list that is not numbers, one list empty and the other not, different
            lengths, not 1 to 4 inputs, or an empty interval (the message names the parameters).
    """
    bounds = given_bounds(p, neither="±torque_limit on 2 inputs, or the driver's limit")
    if bounds is None and p['torque_limit'] > 0:
        return InputBounds.symmetric(p['torque_limit'], 2)
    return bounds


def check_without_limit(p: dict, n: int) -> None:
    """Check what can be checked of the parameters ``p`` for ``n`` fingers before the driver's
    bounds are known: the finger, the level settings, and the signals (each the built-in or the
    spec file's for some number of inputs from 1 to 4, whatever the bounds); the rest is
    checked when the bounds arrive.

    Raises:
        ParameterError: the first problem found (the message names it).
    """
    _check_finger(p, n)
    if p['level'] == 'auto':
        _check_level(p)
    problem = None
    for m in (2, 1, 3, 4):       # bounds wide enough for any spec file's amplitudes and offsets
        wide = InputBounds(np.full(m, -ANY_BOUND), np.full(m, 2 * ANY_BOUND))
        try:
            excitation_run(dict(p), n, wide)
            return
        except ParameterError as exc:
            problem = problem or exc
    raise problem


def _check_finger(p: dict, n: int) -> None:
    if p['finger'] >= n:
        raise ParameterError(f"parameter 'finger': {p['finger']} is not a finger of "
                             f'finger_names {list(p["finger_names"])} (indices 0 to {n - 1}, '
                             'or -1 for all)')


def _check_level(p: dict) -> None:
    """Raises ParameterError for a setting level auto cannot work with (naming it)."""
    for name, bad, why in (
            ('max_excursion', p['max_excursion'] <= 0,
             'level auto needs max_excursion > 0 (it aims at level_target × max_excursion)'),
            ('settle_time', p['settle_time'] <= 0,
             'level auto needs settle_time > 0 (the rest pose the probes are measured from)'),
            ('amplitude', p['amplitude'] != 1.0,
             f'{p["amplitude"]:g} with level auto, which chooses the amplitude itself; leave '
             'amplitude at 1.0, or use level fixed')):
        if bad:
            raise ParameterError(f'parameter {name!r}: {why}')


def _level_settings(p: dict, start: float | None = None) -> LevelSettings:
    return LevelSettings(target=p['level_target'],
                         start=p['level_start'] if start is None else start,
                         probe_time=p['level_probe_time'], settle_time=p['settle_time'])


def signal_searches(p: dict, plan: ExcitationPlan, finger: int | None):
    """The searches of ``level: auto`` with ``level_per: signal`` for ``plan``'s signals: a
    factory (the signal's plan, the amplitude to start at or None) -> its
    :class:`LevelSearch`, probing with the signal itself (cross-checks the parameters and that
    every signal can probe its own level).

    Raises:
        ParameterError: a setting level auto cannot work with, or a signal zero over its probe
            or without room within the limits (the message names it).
    """
    _check_level(p)
    for j in range(len(plan.segments)):
        try:
            plan.signal_plan(j).own_probe(p['level_probe_time'])
        except ValueError as exc:
            raise ParameterError(f"parameter 'signals': {exc}") from None

    def make(single: ExcitationPlan, start: float | None) -> LevelSearch:
        probe = single.own_probe(p['level_probe_time'])
        if start is not None:
            start = min(start, probe.largest)
        return LevelSearch(np.ones(2), 1.0, p['max_excursion'], single.n_fingers, finger,
                           _level_settings(p, start), signal=probe)
    return make


def level_search(p: dict, plan: ExcitationPlan, finger: int | None) -> LevelSearch:
    """The amplitude search of ``level: auto`` with ``level_per: plan`` for ``plan``
    (cross-checks its parameters).

    Raises:
        ParameterError: a setting level auto cannot work with (the message names it).
    """
    _check_level(p)
    peak = plan.peak_torque
    if not peak.max() > 0:
        raise ParameterError("parameter 'signals': every signal is zero; level auto has "
                             'nothing to scale')
    settings = _level_settings(p)
    inputs = None
    if plan.map is not None:
        try:
            inputs = plan.probe_inputs()
        except ValueError as exc:
            raise ParameterError(f"parameter 'signals': {exc}") from None
    return LevelSearch(peak, p['torque_limit'], p['max_excursion'], plan.n_fingers, finger,
                       settings, inputs)


def main(args=None) -> int:
    return run(ExcitationNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
