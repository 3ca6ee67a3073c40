"""The grasp's node graph as data: its nodes, their executables, parameter files, parameter
overrides, remappings and namespace.

One description serves every way the graph is started:

* :class:`soft_gripper_sdre.tools.graph.procs.Graph` starts each node as the process
  ``python -m soft_gripper_sdre.nodes.<executable> --ros-args ...`` (:meth:`NodeSpec.command`): the
  demo, the graph benchmarks, the multi-hand and multi-host runs and the tests;
* ``launch/grasp.launch.py`` turns the same specs into ``launch_ros`` nodes for ``ros2 launch``.

Pure data: no rclpy import, so a launch file, a supervisor in another network namespace or a
test can read it without a ROS context.

**Time with several hands.** The simulator publishes sim time on ``/clock``, the absolute name every
ROS tool expects. Two simulators on one domain would both publish there, and a node of one hand
would step its clock back and forth between the two. So a graph in a namespace remaps ``/clock``
to the relative ``clock`` for all its nodes: the hand ``/left_hand`` keeps its own time on
``/left_hand/clock`` (``clock=`` of :func:`grasp_graph` names another topic). Every other topic of
the graph is relative already and lands under the namespace; ``/diagnostics`` stays shared, its
statuses named by each node's fully qualified name (``/left_hand/simulator``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import os
from pathlib import Path
import re
import shutil
import sys
from typing import Any, Callable, Mapping, Sequence

PACKAGE = 'soft_gripper_sdre'
#: the source tree's parameter files (a colcon install has them under share/, see
#: default_params_file)
CONFIG_DIR = Path(__file__).resolve().parents[2] / 'config'
#: sim time, as the simulator publishes it (nodes/topics.py CLOCK)
CLOCK = '/clock'
#: start order: listeners first, the simulator (which waits for them) last. A run stops in reverse,
#: so the controller goes right after the simulator, before its estimate_watchdog (wall time, once
#: the estimates stop) would report a run cut short before the plan's end as an ERROR
GRASP_NODES = ('recorder', 'estimator', 'trajectory', 'controller', 'simulator')
#: the nodes that declare ``control_period``: :func:`grasp_graph` gives them all one value
PERIOD_NODES = ('estimator', 'controller', 'simulator')
#: the loop's processes, which :func:`grasp_graph` runs at real-time priority when asked
REALTIME_NODES = ('simulator', 'estimator', 'controller')
#: with ``pin``: the plant on one core and the loop's other processes on another (positions in
#: the list of CPUs the process may use), so each finds its caches as it left them from one period
#: to the next (docs/performance.md, "Cores"). The trajectory node and the recorder are left to
#: the scheduler: the trajectory node is idle once it has planned, and beside the estimator and
#: the controller it would start up on the core where they load their models at real-time priority
PIN_SLOTS = {'simulator': 0, 'estimator': 1, 'controller': 1}
#: the control periods the grasp graph is run and measured at [s] (docs/results.md "Control rates")
PERIOD_RANGE = (1e-3, 1e-2)
#: the nodes that read ``tip_positions``, so the simulator waits for them before its first step
TIP_READERS = ('recorder', 'estimator', 'trajectory')
#: topics (relative to the graph's namespace) whose publishers a recorder must have matched before
#: the simulator starts stepping, so the bag holds the run from its first instant
RECORDED_BEFORE_START = ('state_estimate', 'torque_commands', 'grasp_reference')

#: a node another node's process can run beside itself → (the host, the host's flag): the estimator
#: in the controller's process hands each estimate to the controller without a DDS hop, still
#: publishing it for everyone else (docs/performance.md "The deployment loop")
HOSTS = {'estimator': ('controller', '--with-estimator')}

#: the hand's two fingers that face each other across the cube: the grasping pair of the hand
CUBE_FINGERS = (0, 2)

#: what each node of the grasp graph writes and reads, by topic name as in the node (``/clock``
#: stands for the graph's clock topic); the recorder reads every topic another node writes
WRITES = {'simulator': ('tip_positions', CLOCK, 'joint_states', 'cube_pose', 'cube_contacts'),
          'estimator': ('state_estimate',), 'trajectory': ('grasp_reference',),
          'controller': ('torque_commands',), 'recorder': ()}
READS = {'simulator': ('torque_commands',), 'estimator': ('tip_positions',),
         'trajectory': ('tip_positions', CLOCK),
         'controller': ('state_estimate', 'grasp_reference'),
         'recorder': tuple(t for node in GRASP_NODES for t in WRITES[node])}

_NAME_TOKEN = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')


def wiring_key(role: str, topic: str) -> str:
    """The /diagnostics key of a matched count: ``readers <topic>`` (the readers a node's writer
    has matched) or ``writers <topic>`` (the writers a node's reader has matched)."""
    if role not in ('readers', 'writers'):
        raise ValueError(f"role must be 'readers' or 'writers', got {role!r}")
    return f'{role} {topic}'


def readiness_problem(present: Sequence[str], reports: Mapping[str, Mapping[str, str] | None],
                      topic: Callable[[str], str]) -> str | None:
    """What keeps a grasp graph from taking its first step, or None once it may: the one start
    rule of the simulator (which waits for it), the demo and the multi-hand and multi-host runners.

    Every node of the graph has reported on /diagnostics (the controller creates its topics and
    its reporter only once its model is loaded and its kernels compiled; the estimator after its
    kernels), and for each topic :data:`WRITES` and :data:`READS` name, each node's writer has
    matched every reader the graph has of it and each node's reader every writer. Both ends
    count: a writer sends nothing to a reader it has not matched yet (the loop topics are
    volatile), and a reader drops what comes from a writer it has not matched.

    Args:
        present: the graph's node names (of :data:`GRASP_NODES`).
        reports: per node name, its newest /diagnostics values (``None`` or absent: none yet);
            the counts are under :func:`wiring_key`.
        topic: a topic name as the nodes use it → its full name in this graph
            (:meth:`GraphSpec.topic`).
    """
    problems = []
    for node in present:
        values = reports.get(node)
        if values is None:
            problems.append(f'nothing heard from the {node} yet')
            continue
        others = [n for n in present if n != node]
        for role, mine, theirs in (('readers', WRITES, READS), ('writers', READS, WRITES)):
            for name in mine.get(node, ()):
                need = sum(name in theirs.get(other, ()) for other in others)
                have = _count(values.get(wiring_key(role, topic(name))))
                if have < need:
                    problems.append(f'the {node} has matched {have} of {need} {role} of '
                                    f'{topic(name)}')
    return '; '.join(problems) or None


def _count(value: str | None) -> int:
    try:
        return int(value) if value is not None else 0
    except ValueError:
        return 0


def default_params_file(node: str) -> Path | None:
    """The shipped ``config/<node>.yaml`` in a source tree or a colcon install, if any."""
    candidates = [CONFIG_DIR / f'{node}.yaml']
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory(PACKAGE)) / 'config' / f'{node}.yaml')
    except Exception:  # noqa: BLE001 — no ament index in a pip environment: only the source tree
        pass
    return next((p for p in candidates if p.is_file()), None)


def parameter_argument(key: str, value: Any) -> str:
    """``key:=value`` for ``--ros-args -p``: booleans as YAML ``true``/``false``, lists in
    brackets, the empty string as YAML ``''`` (rcl refuses ``key:=``)."""
    if value == '':
        text = "''"
    elif isinstance(value, bool):
        text = 'true' if value else 'false'
    elif isinstance(value, (list, tuple)):
        text = '[' + ','.join(repr(v) if isinstance(v, str) else str(v) for v in value) + ']'
    else:
        text = str(value)
    return f'{key}:={text}'


def normalize_namespace(namespace: str) -> str:
    """``'left_hand'``, ``'/left_hand'`` → ``'/left_hand'``; ``''`` and ``'/'`` → ``''`` (the root).

    Raises:
        ValueError: not a valid ROS namespace (tokens of letters, digits and underscores, not
            starting with a digit).
    """
    tokens = [t for t in namespace.strip().strip('/').split('/')] if namespace.strip('/ ') else []
    bad = [t for t in tokens if not _NAME_TOKEN.fullmatch(t)]
    if bad:
        raise ValueError(f'namespace {namespace!r}: {bad[0]!r} is not a valid name token '
                         '(letters, digits and underscores, not starting with a digit)')
    return ''.join('/' + t for t in tokens)


def finger_parameters(fingers: Mapping[str, int]) -> dict[str, dict[str, Any]]:
    """Per-node parameters of a grasp graph on a subset of the hand: ``fingers`` maps each finger
    name, in message order, to the hand finger it is (0..3). Every node gets ``finger_names``, the
    simulator ``hand_fingers``, the trajectory node ``grasp_fingers``: those of the chosen
    fingers mounted at :data:`CUBE_FINGERS` (the others open away from the cube)."""
    names, mounted = list(fingers), [int(i) for i in fingers.values()]
    grasp = [k for k, i in enumerate(mounted) if i in CUBE_FINGERS]
    return {'simulator': {'finger_names': names, 'hand_fingers': mounted},
            'estimator': {'finger_names': names},
            'trajectory': {'finger_names': names, 'grasp_fingers': grasp},
            'controller': {'finger_names': names}}


def realtime_prefix(priority: int) -> tuple[str, ...]:
    """The command prefix that starts a process under SCHED_FIFO at ``priority`` (0: none)."""
    return ('chrt', '-f', str(priority)) if priority else ()


def cpus_prefix(cpus: Sequence[int]) -> tuple[str, ...]:
    """The command prefix that starts a process (every thread) on ``cpus`` (empty: anywhere)."""
    return ('taskset', '-c', ','.join(str(c) for c in cpus)) if cpus else ()


def taskset_problem() -> str | None:
    """Why no process can be started behind ``taskset`` here (util-linux missing), or None."""
    if shutil.which('taskset') is None:
        return 'needs taskset (util-linux) on the PATH; it is not there'
    return None


def _cpus(available: Sequence[int] | None) -> list[int]:
    """``available`` sorted, default the CPUs this process may run on."""
    return sorted(os.sched_getaffinity(0) if available is None else available)


def pinning_problem(available: Sequence[int] | None = None) -> str | None:
    """Why ``pin`` cannot start the graph's processes here (fewer than two CPUs in ``available``,
    default the CPUs this process may run on, or no ``taskset``), or None."""
    cpus = _cpus(available)
    if len(cpus) < len(set(PIN_SLOTS.values())):
        return (f'pinning puts the simulator and the loop on two CPUs of their own; this '
                f'process may run on {len(cpus)} ({", ".join(map(str, cpus))})')
    problem = taskset_problem()
    return f'pinning {problem}' if problem else None


def pinned_cpus(available: Sequence[int] | None = None) -> dict[str, int]:
    """Node → the CPU ``pin`` starts it on (:data:`PIN_SLOTS`), from ``available`` (default: the
    CPUs this process may run on).

    Raises:
        ValueError: :func:`pinning_problem` names why not.
    """
    problem = pinning_problem(available)
    if problem:
        raise ValueError(problem)
    cpus = _cpus(available)
    return {name: cpus[slot] for name, slot in PIN_SLOTS.items()}


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph: what ``ros2 run`` / ``ros2 launch`` starts, and with what."""

    name: str                                   # node name
    executable: str                             # console script = module under
                                                # soft_gripper_sdre.nodes
    namespace: str = ''                         # '' (root) or '/left_hand'
    params_file: Path | None = None             # a ROS parameters file keyed /**/<name>
    parameters: Mapping[str, Any] = field(default_factory=dict)     # overrides, after the files
    remappings: tuple[tuple[str, str], ...] = ()
    more_params_files: tuple[Path, ...] = ()    # a user's parameter files, after params_file
    hosted: tuple[NodeSpec, ...] = ()           # nodes run in this node's process (HOSTS)
    realtime: int = 0                           # SCHED_FIFO priority of the process (0 = none;
                                                # nodes/scheduling.py)
    cpus: tuple[int, ...] = ()                  # the CPUs the process runs on (() = any)

    @property
    def full_name(self) -> str:
        """The node's fully qualified name (``/left_hand/simulator``), as in its /diagnostics."""
        return f'{self.namespace}/{self.name}'

    @property
    def module(self) -> str:
        return f'{PACKAGE}.nodes.{self.executable}'

    @property
    def flags(self) -> tuple[str, ...]:
        """The executable's flags before ``--ros-args``: one per hosted node."""
        return tuple(HOSTS[node.name][1] for node in self.hosted)

    @property
    def params_files(self) -> tuple[Path, ...]:
        """Every parameters file the process reads, in order: each node's shipped one (this
        node's, then its hosted nodes'), then the user's, without repeats; each node takes its
        own section of each."""
        nodes = (self, *self.hosted)
        files = (*(n.params_file for n in nodes), *(f for n in nodes for f in n.more_params_files))
        return tuple(dict.fromkeys(f for f in files if f is not None))

    @property
    def overrides(self) -> dict[str, Any]:
        """The process's ``-p`` overrides: the hosted nodes' and this node's together. A ``-p``
        reaches every node of a process, so :meth:`GraphSpec.composed` refuses two nodes that
        set one name to different values."""
        return {k: v for node in (*self.hosted, self) for k, v in node.parameters.items()}

    def ros_arguments(self) -> list[str]:
        """``--ros-args`` and everything after it: namespace and node name (when not the
        executable's own), the parameters files, each override, each remapping."""
        args = ['--ros-args']
        if self.namespace:
            args += ['-r', f'__ns:={self.namespace}']
        if self.name != self.executable:
            args += ['-r', f'__node:={self.name}']
        for path in self.params_files:
            args += ['--params-file', str(path)]
        for key, value in self.overrides.items():
            args += ['-p', parameter_argument(key, value)]
        for source, target in self.remappings:
            args += ['-r', f'{source}:={target}']
        return args

    def command(self, python: str = sys.executable) -> list[str]:
        """The process that runs this node (and its hosted ones): ``[taskset -c <cpus>]
        [chrt -f <realtime>] python -m soft_gripper_sdre.nodes.<executable> [flags]
        --ros-args …``."""
        return [*self.prefix, python, '-m', self.module, *self.flags, *self.ros_arguments()]

    @property
    def prefix(self) -> tuple[str, ...]:
        """What the process is started behind: ``taskset -c <cpus>`` on its own CPUs, ``chrt -f
        <realtime>`` at a real-time priority (:mod:`soft_gripper_sdre.nodes.scheduling`)."""
        return (*cpus_prefix(self.cpus), *realtime_prefix(self.realtime))

    def with_parameters(self, **parameters: Any) -> NodeSpec:
        """The same node with ``parameters`` added to (or replacing) its overrides."""
        return replace(self, parameters={**self.parameters, **parameters})


@dataclass(frozen=True)
class GraphSpec:
    """A graph of nodes in one namespace, in start order (see :data:`GRASP_NODES`)."""

    namespace: str
    nodes: tuple[NodeSpec, ...]
    remappings: tuple[tuple[str, str], ...] = ()    # applied to every node
    lead: str = 'simulator'                         # the node whose exit ends a run

    @property
    def names(self) -> tuple[str, ...]:
        """Every node's name, hosted ones included."""
        return tuple(n.name for spec in self.nodes for n in (spec, *spec.hosted))

    def node(self, name: str) -> NodeSpec:
        """The node called ``name``, also one hosted in another's process; KeyError if the graph
        has none."""
        for spec in self.nodes:
            for node in (spec, *spec.hosted):
                if node.name == name:
                    return node
        raise KeyError(f'the graph has no node {name!r} (nodes: {", ".join(self.names)})')

    def topic(self, name: str) -> str:
        """The fully qualified topic a node of this graph uses for ``name`` (remapped, then
        expanded in the namespace): ``'tip_positions'`` → ``'/left_hand/tip_positions'``,
        ``'/clock'`` → ``'/left_hand/clock'``, ``'/diagnostics'`` → ``'/diagnostics'``."""
        absolute = name if name.startswith('/') else f'{self.namespace}/{name}'
        for source, target in self.remappings:
            if absolute == (source if source.startswith('/') else f'{self.namespace}/{source}'):
                return target if target.startswith('/') else f'{self.namespace}/{target}'
        return absolute

    def with_parameters(self, node: str, **parameters: Any) -> GraphSpec:
        """The same graph with ``parameters`` added to ``node``'s overrides (a hosted node's
        too)."""
        self.node(node)

        def updated(spec: NodeSpec) -> NodeSpec:
            spec = spec.with_parameters(**parameters) if spec.name == node else spec
            return replace(spec, hosted=tuple(updated(h) for h in spec.hosted))
        return replace(self, nodes=tuple(updated(n) for n in self.nodes))

    def composed(self) -> GraphSpec:
        """The same graph with every node of :data:`HOSTS` run in its host's process
        (``controller --with-estimator``): one process and one DDS hop fewer per period.

        Raises:
            ValueError: a node to host or its host is missing or renamed (``-r __node:=`` would
                rename every node of the process), or the two set one parameter to different
                values (a ``-p`` reaches both).
        """
        nodes = list(self.nodes)
        for guest, (host, _flag) in HOSTS.items():
            index = {n.name: i for i, n in enumerate(nodes)}
            if guest not in index or host not in index:
                raise ValueError(f'composing needs the nodes {guest} and {host}; the graph has '
                                 f'{", ".join(self.names)}')
            g, h = nodes[index[guest]], nodes[index[host]]
            if g.name != g.executable or h.name != h.executable:
                raise ValueError(f'composing needs {guest} and {host} under their own names')
            clash = sorted(k for k in set(g.parameters) & set(h.parameters)
                           if g.parameters[k] != h.parameters[k])
            if clash:
                raise ValueError(f'{guest} and {host} would share a process but set '
                                 f'{", ".join(clash)} to different values')
            nodes[index[host]] = replace(h, hosted=(*h.hosted, g),
                                         realtime=max(h.realtime, g.realtime),
                                         cpus=h.cpus or g.cpus)
            del nodes[index[guest]]
        return replace(self, nodes=tuple(nodes))

    def without(self, *names: str) -> GraphSpec:
        """The graph without the nodes ``names`` (e.g. the recorder); the simulator no longer
        waits for them (``wait_for_nodes``)."""
        nodes = []
        for node in self.nodes:
            if node.name in names:
                continue
            node = replace(node, hosted=tuple(h for h in node.hosted if h.name not in names))
            waited = node.parameters.get('wait_for_nodes')
            if node.name == 'simulator' and isinstance(waited, str):
                kept = ','.join(n for n in waited.split(',') if n and n not in names)
                node = (node.with_parameters(wait_for_nodes=kept) if kept else
                        replace(node, parameters={k: v for k, v in node.parameters.items()
                                                  if k != 'wait_for_nodes'}))
            nodes.append(node)
        return replace(self, nodes=tuple(nodes))


def grasp_graph(namespace: str = '', *, record: bool = True,
                parameters: Mapping[str, Mapping[str, Any]] | None = None,
                clock: str | None = None, control_period: float | None = None,
                params_files: Sequence[Path | str] = (), composed: bool = False,
                realtime: int = 0, pin: bool = False) -> GraphSpec:
    """The grasp graph: recorder (if ``record``), estimator, trajectory, controller, simulator.

    Args:
        namespace: '' for the root, or the hand's namespace (``'left_hand'`` or ``'/left_hand'``).
        record: include the recorder (its ``output`` parameter names the bag directory).
        parameters: per node name, overrides on top of its ``config/<node>.yaml``. The simulator
            waits for as many ``tip_positions`` readers as the graph has (``min_tip_subscribers``)
            unless told otherwise.
        clock: the topic that carries this graph's sim time. Default ``/clock`` in the root
            namespace and the relative ``clock`` in any other (one clock per hand).
        control_period: the loop's period [s], set on every node of :data:`PERIOD_NODES` (the
            simulator's step and its physics substeps, the estimator's nominal period, the
            controller's roll-off and skip count); None keeps the parameter files' (1 ms).
        params_files: a user's ROS parameter files, given to every node after its shipped one
            (each node takes its own section, ``/**/<node>`` or ``/**``), before ``parameters``.
        composed: run the estimator in the controller's process (:meth:`GraphSpec.composed`).
        realtime: the SCHED_FIFO priority of the loop's processes (:data:`REALTIME_NODES`: the
            simulator, the estimator, the controller; :mod:`~soft_gripper_sdre.nodes.scheduling`),
            0 for none. The trajectory node and the recorder stay ordinary.
        pin: the simulator on one CPU, the estimator and the controller on another
            (:func:`pinned_cpus`); the trajectory node and the recorder anywhere.

    The simulator waits for the graph's other nodes by :func:`readiness_problem`
    (``wait_for_nodes``), unless told otherwise.

    Raises:
        ValueError: a bad namespace, parameters for a node the graph does not have, a
            ``control_period`` that a node's own parameters contradict, or ``pin`` where
            :func:`pinned_cpus` cannot.
    """
    namespace = normalize_namespace(namespace)
    cpus = pinned_cpus() if pin else {}
    names = GRASP_NODES if record else tuple(n for n in GRASP_NODES if n != 'recorder')
    parameters = dict(parameters or {})
    unknown = sorted(set(parameters) - set(names))
    if unknown:
        raise ValueError(f'parameters for {unknown}: the graph has the nodes {", ".join(names)}')
    if control_period is not None:
        for name in PERIOD_NODES:
            own = dict(parameters.get(name, {}))
            if own.get('control_period', control_period) != control_period:
                raise ValueError(f'control_period {control_period:g} s for the graph, but '
                                 f'{own["control_period"]:g} s in the {name} parameters: '
                                 'set it once')
            parameters[name] = {**own, 'control_period': float(control_period)}
    clock = clock or ('clock' if namespace else CLOCK)
    remappings = () if clock == CLOCK else ((CLOCK, clock),)
    simulator = dict(parameters.get('simulator', {}))
    simulator.setdefault('min_tip_subscribers', sum(n in TIP_READERS for n in names))
    if len(names) > 1:
        simulator.setdefault('wait_for_nodes', ','.join(n for n in names if n != 'simulator'))
    parameters['simulator'] = simulator
    extra = tuple(Path(f) for f in params_files)
    nodes = tuple(NodeSpec(name, name, namespace, default_params_file(name),
                           dict(parameters.get(name, {})), remappings, extra,
                           realtime=realtime if name in REALTIME_NODES else 0,
                           cpus=(cpus[name],) if name in cpus else ()) for name in names)
    graph = GraphSpec(namespace, nodes, remappings)
    return graph.composed() if composed else graph
