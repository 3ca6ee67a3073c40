"""The simulator node: the PyBullet gripper on topics.

Publishes ``/clock``, ``tip_positions`` (each control period), ``joint_states``, ``cube_pose``,
``cube_contacts`` (~100 Hz of sim time) and ``/diagnostics``; subscribes ``torque_commands``.

*Lockstep* (default, deterministic): publish /clock and tip_positions stamped t_k, then step only
when a torque command stamped t_k arrives — event-driven, nothing blocks inside a callback. If
none arrives within ``lockstep_timeout`` seconds of wall time, hold the last good command (or zero,
by ``on_timeout``), count it, warn in diagnostics and go on: the loop never deadlocks.
*Realtime*: a wall timer steps at the control period with the latest command (zero-order hold),
counting periods whose command was late.

/diagnostics also carries the real-time factor of the stepping, this process's CPU time per step
(``cpu_per_step_us``) and the loop latency: the wall time from publishing ``tip_positions`` for
t_k to receiving the first command stamped t_k, as p50 / p99 / max [µs] over the last 10 000
answered periods (``loop_latency_us_*``).

Bad commands (NaN/Inf, wrong sizes, unknown/duplicate/missing names, stamps older than the last
applied one or ahead of the current period) are rejected with a throttled warning and counted;
the simulator never steps with a non-finite torque.
"""
from __future__ import annotations

import time

from geometry_msgs.msg import PoseArray, PoseStamped
import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import cdr, conversions as cv
from soft_gripper_sdre.nodes.common import OK, WARN, Diagnostics, LatencyWindow, ThrottledLogger, run
from soft_gripper_sdre.nodes.params import Param, ParameterError, declare_all, on_runtime_change
from soft_gripper_sdre.nodes.topics import (CLOCK, CLOCK_QOS, CUBE_CONTACTS, CUBE_POSE, JOINT_STATES,
                                            LOOP_QOS, STREAM_QOS, TIP_POSITIONS, TORQUE_COMMANDS)
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig

#: periods back a command may answer and still count in the loop latency (realtime: late answers)
LATENCY_PERIODS = 64
_NO_VALUES = np.empty(0)       # /clock carries only its stamp

PARAMS = (
    Param('mode', 'lockstep', 'stepping mode', choices=('lockstep', 'realtime'), read_only=True),
    Param('scene', 'hand', 'what to simulate', choices=('hand', 'finger'), read_only=True),
    Param('control_period', 0.001, 'sim time per step; commands are held over it', 's',
          1e-4, 0.05, read_only=True),
    Param('physics_substeps', 2, 'physics steps per control period (0.5 ms keeps |u| <= 25 sim units stable)',
          '', 1, 50, read_only=True),
    Param('torque_limit', 0.1, 'actuator limit; commands are clipped to ±limit', 'N·m', 1e-4, 1.0,
          read_only=True),
    Param('noise_std', 5e-5, 'Gaussian noise on measured tip positions (0.05 mm: a fingertip tracker)',
          'm', 0.0, 0.01, read_only=True),
    Param('seed', 0, 'seed of the measurement noise', '', 0, 2**31 - 1, read_only=True),
    Param('settle_time', 0.5, 'time at u = 0 before t = 0 (defines the rest pose)', 's', 0.0, 10.0,
          read_only=True),
    Param('with_cube', True, 'hand scene: put the cube on the palm', read_only=True),
    Param('lockstep_timeout', 0.5, 'lockstep: wall time to wait for a command before stepping anyway',
          's', 1e-3, 60.0),
    Param('on_timeout', 'hold', 'lockstep: command used when none arrived in time',
          choices=('hold', 'zero')),
    Param('on_bad_command', 'hold', 'what replaces a rejected command', choices=('hold', 'zero')),
    Param('duration', 0.0, 'stop after this much sim time and exit (0 = run until shut down)', 's',
          0.0, 1e6, read_only=True),
    Param('startup_timeout', 30.0, 'wall time to wait for a command publisher and a tip subscriber '
          'before the first step', 's', 0.0, 600.0, read_only=True),
    Param('min_tip_subscribers', 1, 'start-up: tip_positions subscribers to wait for (the demo waits '
          'for the estimator, the trajectory node and the recorder)', '', 0, 100, read_only=True),
    Param('min_diagnostics_subscribers', 0, 'start-up: /diagnostics subscribers to wait for (a '
          'monitor that reads the final counters of a short run must be matched before it begins)',
          '', 0, 100, read_only=True),
    Param('state_rate', 100.0, 'rate of joint_states, cube_pose and cube_contacts in sim time', 'Hz',
          1.0, 1000.0, read_only=True),
)


class SimulatorNode(Node):
    """PyBullet gripper in lockstep or realtime with the controller (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('simulator', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        on_runtime_change(self, PARAMS, apply=self.p.update)
        try:
            self.sim = GripperSim(SimConfig(
                scene=p['scene'], control_period=p['control_period'],
                physics_substeps=p['physics_substeps'], torque_limit=p['torque_limit'],
                noise_std=p['noise_std'], seed=p['seed'], settle_time=p['settle_time'],
                with_cube=p['with_cube']))
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        self.n = self.sim.n_fingers
        self.period_ns = int(round(p['control_period'] * cv.NS))
        self.total_steps = int(round(p['duration'] / p['control_period'])) if p['duration'] > 0 else None
        self.state_every = max(1, int(round(1.0 / (p['state_rate'] * p['control_period']))))
        self.done = False
        self.exit_code = 0

        self.u_last = np.zeros((self.n, 2))      # last good command
        self.u_next = None                       # command received for the current period
        self.last_cmd_ns = -1                    # stamp of the last applied command
        self.k = 0                               # current period index; t_k = k · Δt
        self.started = False
        self.deadline = None
        self._wall_start = self._wall_end = None   # monotonic time of the first and last step
        self._cpu_start = self._cpu_end = None     # this process's CPU time then
        # loop latency: tip_positions for t_k published → the torque command stamped t_k received
        self.latency = LatencyWindow()
        self._tips_sent = np.zeros(LATENCY_PERIODS)   # perf_counter() at tips k, at k % LATENCY_PERIODS
        self._answered_ns = -1                   # newest period whose latency is counted

        # the per-period messages travel as CDR bytes written / read at fixed offsets (nodes/cdr.py)
        self.cdr_clock = cdr.clock_codec()
        self.cdr_tips = cdr.tips_codec(self.n)
        self.cdr_cmd = cdr.torques_codec(self.n)
        self.pub_clock = self.create_publisher(Clock, CLOCK, CLOCK_QOS)
        self.pub_tips = self.create_publisher(PoseArray, TIP_POSITIONS, LOOP_QOS)
        self.pub_joints = self.create_publisher(JointState, JOINT_STATES, STREAM_QOS)
        self.pub_cube = self.create_publisher(PoseStamped, CUBE_POSE, STREAM_QOS)
        self.pub_contacts = self.create_publisher(JointState, CUBE_CONTACTS, STREAM_QOS)
        self.sub_cmd = self.create_subscription(JointState, TORQUE_COMMANDS, self.on_command, LOOP_QOS,
                                                raw=True)
        self.log = ThrottledLogger(self.get_logger())
        self.diag = Diagnostics(self)
        cdr.watch(self.diag, self.cdr_cmd)
        self.diag.before_publish.append(self._refresh_diagnostics)
        self.diag.values['mode'] = p['mode']
        self.diag.values['scene'] = p['scene']
        self._startup_deadline = time.monotonic() + p['startup_timeout']
        self._startup_timer = self.create_timer(0.01, self._try_start)
        self.get_logger().info(
            f'{p["scene"]} scene settled; {p["mode"]} at {1e3 * p["control_period"]:g} ms, '
            f'{p["physics_substeps"]} physics substeps, noise σ = {1e3 * p["noise_std"]:g} mm')

    # -- start-up ----------------------------------------------------------------------------
    def _try_start(self) -> None:
        ready = (self.pub_tips.get_subscription_count() >= self.p['min_tip_subscribers']
                 and self.sub_cmd.get_publisher_count() > 0
                 and self.diag.subscription_count() >= self.p['min_diagnostics_subscribers'])
        if not ready and time.monotonic() < self._startup_deadline:
            return
        if not ready:
            self.get_logger().warning(
                f'starting with an incomplete graph: {self.sub_cmd.get_publisher_count()} torque_commands '
                f'publishers and {self.pub_tips.get_subscription_count()} tip_positions subscribers '
                'after startup_timeout')
        self._startup_timer.cancel()
        self.started = True
        self._wall_start, self._cpu_start = time.monotonic(), time.process_time()
        if self.p['mode'] == 'lockstep':
            self._watchdog = self.create_timer(min(0.01, self.p['lockstep_timeout'] / 4), self._check_timeout)
        else:
            self._stepper = self.create_timer(self.p['control_period'], self._realtime_step)
        self.publish_state()

    # -- commands ----------------------------------------------------------------------------
    def on_command(self, data: bytes) -> None:
        try:
            stamp, u = self.cdr_cmd.decode(data)
        except cv.MessageError as exc:
            self._reject('bad_command', str(exc))
            return
        now_ns = self.k * self.period_ns
        if self._answered_ns < stamp <= now_ns and self.started and stamp % self.period_ns == 0:
            j = stamp // self.period_ns          # answers the tips of period j (realtime: maybe late)
            if self.k - j < LATENCY_PERIODS:
                self.latency.add(time.perf_counter() - self._tips_sent[j % LATENCY_PERIODS])
                self._answered_ns = stamp
        if stamp <= self.last_cmd_ns:
            self._reject('stale_command', f'torque_commands: stamp {stamp} ns is not newer than '
                         f'the last applied {self.last_cmd_ns} ns')
            return
        if stamp > now_ns:
            self._reject('future_command', f'torque_commands: stamp {stamp} ns is ahead of sim time {now_ns} ns')
            return
        self.diag.count('commands')
        if self.p['mode'] == 'lockstep':
            if stamp == now_ns and self.started and not self.done:
                self.last_cmd_ns = stamp
                self.u_last = u
                self._step(u)
            else:
                self.diag.count('late_command')     # for an earlier period we already stepped past
        else:
            self.last_cmd_ns = stamp
            self.u_last = u
            self.u_next = u

    def _reject(self, key: str, why: str) -> None:
        self.diag.problem(key, f'rejected: {why}')
        if self.p['on_bad_command'] == 'zero':
            self.u_last = np.zeros((self.n, 2))

    # -- stepping ----------------------------------------------------------------------------
    def _step(self, u: np.ndarray) -> None:
        self.sim.step(u)      # u is finite here: validated on receipt or zero/held
        self.k += 1
        self.diag.count('steps')
        if self.total_steps is not None and self.k >= self.total_steps:
            self.done = True
            self._wall_end, self._cpu_end = time.monotonic(), time.process_time()
            self.publish_state()
            self.diag.set_status(OK, f'finished {self.k} steps')
            self.diag.publish()
            self.get_logger().info(f'duration reached after {self.k} steps; stopping')
            return
        self.publish_state()

    def _check_timeout(self) -> None:
        if self.done or self.deadline is None or time.monotonic() < self.deadline:
            return
        hold = self.p['on_timeout'] == 'hold'
        self.diag.count('timeouts')
        self.diag.set_status(WARN, f'command timeout at t = {self.sim.t:.3f} s; '
                             f'{"holding the last command" if hold else "zero torque"}')
        self.log.warn('timeout', f'no torque_commands for t = {self.sim.t:.3f} s within '
                      f'{self.p["lockstep_timeout"]} s; {"holding last" if hold else "applying zero"}')
        self._step(self.u_last if hold else np.zeros((self.n, 2)))

    def _realtime_step(self) -> None:
        if self.done:
            return
        if self.u_next is None:
            self.diag.count('late_periods')
        self.u_next = None
        self._step(self.u_last)

    # -- publishing --------------------------------------------------------------------------
    def publish_state(self) -> None:
        ns = self.k * self.period_ns
        tips = self.cdr_tips.encode(ns, self.sim.measure())
        self._tips_sent[self.k % LATENCY_PERIODS] = time.perf_counter()
        self.pub_tips.publish(tips)         # first: the loop's critical path starts here
        self.pub_clock.publish(self.cdr_clock.encode(ns, _NO_VALUES))
        self.deadline = time.monotonic() + self.p['lockstep_timeout']
        if self.k % self.state_every == 0:
            truth = self.sim.truth()
            self.pub_joints.publish(cv.joint_states_msg(ns, self.sim.joint_names, truth.q, truth.qd))
            if truth.cube_pose is not None:
                pose = PoseStamped()
                pose.header.stamp = cv.to_time(ns)
                pose.header.frame_id = 'hand'
                c = truth.cube_pose.tolist()
                pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = c[:3]
                (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
                 pose.pose.orientation.w) = c[3:]
                self.pub_cube.publish(pose)
                self.pub_contacts.publish(cv.contacts_msg(ns, truth.contact_force))
        if self.diag.level == WARN and self.k % 1000 == 0 and self.deadline is not None:
            self.diag.set_status(OK, 'stepping')

    def _refresh_diagnostics(self) -> None:
        """Sim time, real-time factor of the stepping and loop latency, before each /diagnostics."""
        t = self.k * self.period_ns / cv.NS
        self.diag.values['sim_time'] = f'{t:.3f}'
        if self._wall_start is not None:
            wall = (self._wall_end or time.monotonic()) - self._wall_start
            if wall > 0:
                self.diag.values['real_time_factor'] = f'{t / wall:.4f}'
            if self.k:
                cpu = (self._cpu_end or time.process_time()) - self._cpu_start
                self.diag.values['cpu_per_step_us'] = f'{1e6 * cpu / self.k:.0f}'
        self.diag.values.update(self.latency.summary('loop_latency_us'))

    def close(self) -> None:
        self.sim.close()


def main(args=None) -> int:
    return run(SimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
