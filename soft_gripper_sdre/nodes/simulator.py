"""The simulator node: the PyBullet gripper on topics.

It exposes the fingers ``finger_names``, each one of the scene's fingers (``hand_fingers``: a
2-finger gripper is the hand's opposite fingers 0 and 2); the others stay at zero torque.
Publishes ``tip_positions`` (each control period), ``/clock`` (``clock_rate``, 100 Hz of sim time
by default), ``joint_states``, ``cube_pose``, ``cube_contacts`` (``state_rate``; these are the
plant's topics, :class:`~soft_gripper_sdre.nodes.state_publisher.StatePublisher`) and
``/diagnostics``; subscribes ``torque_commands`` (keeping only the newest). Per period it sends
one loop message and receives one. The hand scene also publishes the live 3-D view
(docs/visualization.md): its URDF on ``robot_description`` once, and the hand as ``markers`` on a
wall timer at ``marker_rate`` while someone subscribes.

When it steps and with which torque is decided by :class:`~soft_gripper_sdre.sim.lockstep.Stepping`
(docs/design/loop_rules.md): in *lockstep* (default, deterministic) one step per command stamped
with the current period, and after ``lockstep_timeout`` of wall time (at the watchdog's second
look past it, at most 20 ms later) a step with the held or zero command so the loop never
deadlocks; commands are then lost, and each following period waits only ``lost_command_wait``
before it steps with zero torque (ERROR), until a command arrives again. *Pipelined* keeps
lockstep's rules but publishes the tips of t_k before it steps the physics from t_k to t_(k+1)
with the command that answered t_(k−1), so the physics runs while the estimator and the
controller work (one period of sensing-to-actuation delay; the first step goes with zero torque
at the start, and the run's last command is not applied). In *realtime* a wall
timer steps at the control period with the newest command, holding it while it is at most
``hold_limit`` old and stepping with zero torque after that. Bad commands (NaN/Inf,
wrong sizes, unknown/duplicate/missing names, stamps older than the last applied one or ahead of
the current period) are rejected with a throttled warning and counted; the simulator never steps
with a non-finite torque.

The first step waits until the graph is wired and ready: a command publisher,
``min_tip_subscribers`` tip readers and ``min_diagnostics_subscribers`` /diagnostics readers,
and, given ``wait_for_nodes`` (the graph's other nodes, as
:func:`~soft_gripper_sdre.nodes.graph.grasp_graph` names them), the start rule
:func:`~soft_gripper_sdre.nodes.graph.readiness_problem` over their /diagnostics: each of them
has reported, and every writer and reader of the graph has matched its peers. Without
``wait_for_nodes`` it starts after ``startup_timeout`` with what is there (a warning); with it,
it gives up instead, naming what is missing, with exit status 1
(:class:`~soft_gripper_sdre.nodes.start_gate.StartGate`).

/diagnostics also carries the real-time factor of the stepping, this process's CPU time per
step (``cpu_per_step_us``) and the loop latency: the wall time from publishing ``tip_positions``
for t_k to receiving the first command stamped t_k, as p50 / p99 / max [µs] over the last
10 000 answered periods (``loop_latency_us_*``) and over those since the previous /diagnostics
(``recent_latency_us_*``);
when the first command was accepted (``first_command_monotonic_s``, this machine's monotonic
clock, and ``first_command_after_tips_ms``, from the first tips); and the mean wall time of a step
from that command on (``step_period_us``: the loop's pace without the start-up wait, which the
real-time factor counts). Like a driver, it reports the
interval its commands are clipped to as ``bounds``: ``ax0 [-limit, limit], ax1 [-limit, limit]``
per exposed finger (``torque_limit``), joined by ``;``, which the excitation node takes as its
limit when none is given (:mod:`soft_gripper_sdre.nodes.driver_limits`).
"""
from __future__ import annotations

import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState

from soft_gripper_sdre.nodes import cdr
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.common import ERROR, Diagnostics, SteppingTiming, run
from soft_gripper_sdre.nodes.graph import GRASP_NODES
from soft_gripper_sdre.nodes.live_view import LiveView
from soft_gripper_sdre.nodes.loop_status import LoopStatus
from soft_gripper_sdre.nodes.params import (
    Param,
    ParameterError,
    declare_all,
    finger_names_param,
    on_runtime_change,
)
from soft_gripper_sdre.nodes.start_gate import StartGate, StartRule, waited_nodes_problem
from soft_gripper_sdre.nodes.state_publisher import StatePublisher, periods_between
from soft_gripper_sdre.nodes.topics import NEWEST_QOS, TORQUE_COMMANDS
from soft_gripper_sdre.sim.finger import FINGER_BASE_POSITIONS
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.lockstep import LATENCY_PERIODS, MODES, Stepping
from soft_gripper_sdre.sim.shape import InputBounds

PARAMS = (
    Param('mode', 'lockstep', 'stepping mode: lockstep (each period steps on its own command), '
          'pipelined (lockstep\'s rules, the physics stepped with the previous period\'s command '
          'while the current one is computed: one period of sensing-to-actuation delay) or '
          'realtime (a wall timer steps with the newest command)', choices=MODES, read_only=True),
    Param('scene', 'hand', 'what to simulate', choices=('hand', 'finger'), read_only=True),
    Param('control_period', 0.001, 'sim time per step; commands are held over it', 's',
          1e-4, 0.05, read_only=True),
    Param('physics_substeps', 0, 'physics steps per control period; 0 = the fewest of at most '
          '0.5 ms (2 at 1 ms, 20 at 10 ms: 0.5 ms keeps |u| <= 25 sim units stable)', '', 0, 100,
          read_only=True),
    Param('torque_limit', 0.1, 'actuator limit; commands are clipped to ±limit', 'N·m', 1e-4, 1.0,
          read_only=True),
    Param('noise_std', 5e-5, 'Gaussian noise on measured tip positions (0.05 mm: a fingertip '
          'tracker)', 'm', 0.0, 0.01, read_only=True),
    Param('seed', 0, 'seed of the measurement noise', '', 0, 2**31 - 1, read_only=True),
    Param('settle_time', 0.5, 'time at u = 0 before t = 0 (defines the rest pose)', 's', 0.0, 10.0,
          read_only=True),
    Param('with_cube', True, 'hand scene: put the cube on the palm', read_only=True),
    finger_names_param('the fingers the node exposes, in message order: pose i of tip_positions, '
                       'torque_commands <finger>/ax0|ax1, joint_states <finger>/joint_<j>'),
    Param('hand_fingers', [0, 1, 2, 3], "which of the scene's fingers each of finger_names is "
          "(hand: 0 to 3, 0 and 2 face each other across the cube; finger scene: 0); one per name, "
          'each once. The fingers not listed stay in the scene at zero torque', read_only=True),
    Param('lockstep_timeout', 0.5, 'lockstep, pipelined: wall time to wait for a command before '
          'stepping anyway (at the watchdog\'s second look past it, at most 20 ms later)',
          's', 1e-3, 60.0),
    Param('on_timeout', 'hold', 'lockstep, pipelined: command used when none arrived in time',
          choices=('hold', 'zero')),
    Param('lost_command_wait', 0.01, 'lockstep, pipelined: after a timeout, wall time each period '
          'waits for its command before it steps with zero torque, until commands arrive again',
          's', 1e-3, 60.0),
    Param('hold_limit', 0.005, 'realtime: how old (sim time) the newest command may be and still '
          'be held; an older one is replaced by zero torque', 's', 0.0, 60.0),
    Param('on_bad_command', 'hold', 'what replaces a rejected command', choices=('hold', 'zero')),
    Param('duration', 0.0, 'stop after this much sim time and exit (0 = run until shut down)', 's',
          0.0, 1e6, read_only=True),
    Param('startup_timeout', 30.0, 'wall time to wait for the graph to be ready before the first '
          'step: a command publisher, the tip subscribers and, with wait_for_nodes, the whole '
          'graph; after it a simulator with wait_for_nodes gives up (exit status 1), one without '
          'starts with what is there', 's', 0.0, 600.0, read_only=True),
    Param('min_tip_subscribers', 1, 'start-up: tip_positions subscribers to wait for (the demo '
          'waits for the estimator, the trajectory node and the recorder)', '', 0, 100,
          read_only=True),
    Param('wait_for_nodes', '', "start-up: the graph's other nodes, comma-separated, of "
          f"{', '.join(n for n in GRASP_NODES if n != 'simulator')} (grasp_graph and the launch "
          'file name them): the first step waits until each has reported on /diagnostics and every '
          "writer and reader of the graph has matched its peers; '' = no such wait",
          read_only=True, rule=waited_nodes_problem),
    Param('min_diagnostics_subscribers', 0, 'start-up: /diagnostics subscribers of other nodes to '
          'wait for (a monitor that reads the final counters of a short run must be matched before '
          'it begins)', '', 0, 100, read_only=True),
    Param('state_rate', 100.0, 'rate of joint_states, cube_pose and cube_contacts in sim time',
          'Hz', 1.0, 1000.0, read_only=True),
    Param('clock_rate', 100.0, 'rate of /clock in sim time (the tips carry every period\'s stamp)',
          'Hz', 1.0, 1000.0, read_only=True),
    Param('marker_rate', 10.0, "hand scene: rate of the hand's MarkerArray on markers, in wall "
          'time, sent only while someone subscribes (RViz, Foxglove; docs/visualization.md); '
          '0 = no markers', 'Hz', 0.0, 100.0, read_only=True),
    Param('marker_references', False, "hand scene: draw each finger's reference among the "
          'markers (subscribes to grasp_reference)', read_only=True),
)


class SimulatorNode(Node):
    """PyBullet gripper in lockstep, pipelined or realtime with the controller (see module doc)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('simulator', **kwargs)
        p = declare_all(self, PARAMS)
        self.p = p
        on_runtime_change(self, PARAMS, apply=self._apply)
        self.names = tuple(p['finger_names'])
        self.mounted = exposed_fingers(self.names, p['hand_fingers'], p['scene'])
        self.sim = settled_scene(p)
        self._u_scene = np.zeros((self.sim.n_fingers, 2))   # the fingers not exposed stay at zero
        self.timing = SteppingTiming(LATENCY_PERIODS)
        self._physics_k = 0           # the physics' period: the tips' one, or one ahead (pipelined)
        self.state_out = StatePublisher(
            self, self.sim, self.names, self.mounted, timing=self.timing,
            clock_every=periods_between(p['clock_rate'], p['control_period']),
            state_every=periods_between(p['state_rate'], p['control_period']))
        self.live = (LiveView(self, self.names, self.mounted, marker_rate=p['marker_rate'],
                              with_cube=p['with_cube'], with_references=p['marker_references'],
                              now=self._shown) if p['scene'] == 'hand' else None)
        # the commands arrive as CDR bytes read at fixed offsets (nodes/cdr.py)
        self.cdr_cmd = cdr.torques_codec(self.names)
        self.sub_cmd = self.create_subscription(JointState, TORQUE_COMMANDS, self.on_command,
                                                NEWEST_QOS, raw=True)
        self.diag = Diagnostics(self)
        self.stepping = Stepping(
            len(self.names), int(round(p['control_period'] * cv.NS)), p['mode'],
            int(round(p['duration'] / p['control_period'])) if p['duration'] > 0 else None,
            counters=self.diag.counters, **stepping_rules(p))
        self.status = LoopStatus(self, self.diag, self.stepping)
        cdr.watch(self.diag, self.cdr_cmd)
        self.diag.before_publish.append(self._refresh_diagnostics)
        self.diag.values['mode'] = p['mode']
        self.diag.values['scene'] = p['scene']
        self.diag.values['bounds'] = '; '.join(
            str(InputBounds.symmetric(p['torque_limit'], 2)) for _ in self.names)
        self.gate = StartGate(self, StartRule.from_params(p), tips=self.state_out.pub_tips,
                              commands=self.sub_cmd, diag=self.diag, start=self._start)
        self.get_logger().info(
            f'{p["scene"]} scene settled; {p["mode"]} at {1e3 * p["control_period"]:g} ms, '
            f'{self.sim.config.physics_substeps} physics substeps, '
            f'noise σ = {1e3 * p["noise_std"]:g} mm')

    @property
    def done(self) -> bool:
        """The run reached its ``duration``, or the graph never got ready (the process then
        exits)."""
        return self.stepping.done or self.gate.gave_up

    @property
    def exit_code(self) -> int:
        """1 when the graph never got ready (with ``wait_for_nodes``), else 0."""
        return int(self.gate.gave_up)

    def _apply(self, new: dict) -> None:
        self.p.update(new)
        for name, value in stepping_rules(self.p).items():
            setattr(self.stepping, name, value)

    # -- start-up ----------------------------------------------------------------------------
    def _start(self) -> None:
        """The first step may go (:class:`~soft_gripper_sdre.nodes.start_gate.StartGate`): the
        first tips go out, and the timer that steps (realtime) or watches for timeouts starts."""
        first = self.stepping.start()
        self.timing.start()
        if self.p['mode'] == 'realtime':
            self._stepper = self.create_timer(self.p['control_period'], self._on_period)
        else:
            self._watchdog = self.create_timer(
                min(0.01, self.p['lockstep_timeout'] / 4, self.p['lost_command_wait'] / 2),
                self._check_timeout)
        self.publish_state()
        if first is not None:  # pipelined: t_0 → t_1 while the tips of t_0 are answered
            self._physics(first)

    # -- commands and stepping ---------------------------------------------------------------
    def on_command(self, data: bytes) -> None:
        try:
            stamp, u = self.cdr_cmd.decode(data)
        except cv.MessageError as exc:
            self.stepping.command_refused()
            self.diag.problem('bad_command', f'rejected: {exc}')
            return
        outcome = self.stepping.on_command(stamp, u)
        if outcome.first_answer is not None:
            self.timing.answered(outcome.first_answer)
        if outcome.refused:
            self.diag.problem(outcome.refused, f'rejected: {outcome.reason}')
        else:
            self.timing.accepted(self.stepping.k)
        if outcome.resumed:
            self.status.back(stamp)
        self._step(outcome.step)

    def _check_timeout(self) -> None:
        lost = self.stepping.lost
        # the period awaited (pipelined: the physics is one ahead)
        t = self.stepping.now_ns / cv.NS
        u = self.stepping.on_wall_time(time.monotonic())
        if u is None:
            return
        if not lost:
            self.status.timed_out(t, self.p['on_timeout'] == 'hold', self.p['lockstep_timeout'])
        elif self.diag.level != ERROR:               # once per spell
            self.status.lost(f'each period waits {self.p["lost_command_wait"]:g} s')
        self._step(u)

    def _on_period(self) -> None:
        lost = self.stepping.lost
        u = self.stepping.on_period()
        if self.stepping.lost and not lost:
            self.status.lost(f'the newest is older than hold_limit ({self.p["hold_limit"]:g} s)')
        self._step(u)

    def _physics(self, u: np.ndarray) -> None:
        """One control period of the physics with the exposed fingers' torques ``u``."""
        self._u_scene[self.mounted] = u
        self.sim.step(self._u_scene)
        self._physics_k += 1

    def _step(self, u: np.ndarray | None) -> None:
        """The period moved on with ``u`` (finite: validated on receipt, or held or zero), if any:
        step the physics with it and publish the new period's tips. Pipelined: publish the tips
        first (the physics is there already) and step after them, from t_k to t_(k+1), while they
        are answered; once the run is done the physics stays at its end."""
        if u is None:
            return
        if self.stepping.pipelined:
            if self.done:
                self.timing.finish()
            self.publish_state()
            if not self.done:
                self._physics(u)
        else:
            self._physics(u)
            if self.done:
                self.timing.finish()
            self.publish_state()
        if self.done:
            self.status.finished(self.stepping.k)

    # -- publishing --------------------------------------------------------------------------
    def publish_state(self) -> None:
        """The current period's tips, then (the command wait armed) /clock and the state."""
        k, ns = self.stepping.k, self.stepping.now_ns
        self.state_out.tips(k, ns)          # first: the loop's critical path starts here
        self.stepping.await_command(time.monotonic())
        self.state_out.streams(k, ns)
        self.status.stepped(k)

    def _refresh_diagnostics(self) -> None:
        """Sim time and the stepping's timing (real-time factor, loop latency, the first command),
        before each /diagnostics."""
        t = self.stepping.now_ns / cv.NS
        kept = {k: v for k, v in self.diag.values.items() if not k.startswith('recent_')}
        self.diag.values = kept | {'sim_time': f'{t:.3f}'} | self.timing.report(t, self.stepping.k)

    def _shown(self) -> tuple[int, object]:
        """What the live view draws: the sim time [ns] the physics is at, and its truth."""
        return self._physics_k * self.stepping.period_ns, self.sim.truth()

    def close(self) -> None:
        self.sim.close()


def settled_scene(p: dict) -> GripperSim:
    """The scene the parameters ``p`` describe, settled.

    Raises:
        ParameterError: the scene refused a value.
    """
    try:
        return GripperSim(SimConfig(
            scene=p['scene'], control_period=p['control_period'],
            physics_substeps=p['physics_substeps'] or None, torque_limit=p['torque_limit'],
            noise_std=p['noise_std'], seed=p['seed'], settle_time=p['settle_time'],
            with_cube=p['with_cube']))
    except ValueError as exc:
        raise ParameterError(str(exc)) from None


def stepping_rules(p: dict) -> dict:
    """The :class:`~soft_gripper_sdre.sim.lockstep.Stepping` attributes that the parameters
    ``p`` set and that may change at runtime, by name."""
    return dict(timeout=p['lockstep_timeout'], on_timeout=p['on_timeout'],
                on_bad_command=p['on_bad_command'], lost_command_wait=p['lost_command_wait'],
                hold_periods=int(round(p['hold_limit'] / p['control_period'])))


def exposed_fingers(names, hand_fingers, scene: str) -> np.ndarray:
    """The ``scene``'s finger index of each of ``names`` (the ``hand_fingers`` parameter), checked.

    Raises:
        ParameterError: not one index per name, an index twice, or one the scene does not have.
    """
    hand_fingers = [int(i) for i in hand_fingers]
    scene_fingers = 1 if scene == 'finger' else len(FINGER_BASE_POSITIONS)
    if len(hand_fingers) != len(names):
        raise ParameterError(f"parameter 'hand_fingers': {hand_fingers} has {len(hand_fingers)} "
                             f'entries but finger_names {list(names)} has {len(names)}: give one '
                             f"scene finger per name (the {scene} scene has {scene_fingers}: "
                             f'0 to {scene_fingers - 1})')
    if len(set(hand_fingers)) != len(hand_fingers):
        raise ParameterError(f"parameter 'hand_fingers': {hand_fingers} names a finger twice")
    if any(not 0 <= i < scene_fingers for i in hand_fingers):
        raise ParameterError(f"parameter 'hand_fingers': {hand_fingers} out of range: the {scene} "
                             f'scene has {scene_fingers} finger(s), 0 to {scene_fingers - 1}')
    return np.array(hand_fingers, dtype=np.intp)


def main(args=None) -> int:
    return run(SimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
