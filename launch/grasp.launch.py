"""The grasp graph for ``ros2 launch`` on a ROS 2 Jazzy install.

    ros2 launch soft_gripper_sdre grasp.launch.py [namespace:=left_hand] [duration:=6.0]
        [control_period:=0.005] [mode:=pipelined] [law:=sdre_ff] [noise:=0.05] [seed:=0]
        [record:=true] [output:=runs/grasp_bag] [startup_timeout:=300] [params_file:=my_params.yaml]
        [composed:=true] [realtime_priority:=50] [pin_cores:=true]

Starts the recorder (with ``record:=true``), the estimator, the trajectory node, the controller
and the simulator of :func:`soft_gripper_sdre.nodes.graph.grasp_graph`, the same description the
demo and the tests start as processes: each node with its ``config/<node>.yaml`` from the
package's share directory, then the user's ``params_file``, then the overrides the arguments ask
for, and in a namespace its own clock (``/clock`` remapped to ``<namespace>/clock``).

Every argument is checked before any node starts (the law against the controller's own choices,
the numbers against the simulator's limits, the parameters file read as YAML and each node's
sections of it against the parameters the node declares: a value of the wrong type or an unknown
key); a bad one ends the launch with an error naming it. The simulator takes its first step once
the whole graph is wired and ready (:func:`soft_gripper_sdre.nodes.graph.readiness_problem`). The
launch ends when the simulator finishes (after ``duration`` seconds of sim time; ``duration:=0``
runs until Ctrl-C), or as soon as any node exits on its own before that: then with an error
naming the node and its status (:func:`exit_verdict`), so ``ros2 launch`` exits non-zero.

The namespace is passed to launch_ros as a relative one, so an including launch file's
``PushRosNamespace`` still applies. :func:`grasp_nodes` is the node list as plain data (package,
executable, name, namespace, parameters, remappings); the launch packages are imported only
inside :func:`generate_launch_description`.
"""
from soft_gripper_sdre.nodes.graph import PACKAGE, PERIOD_RANGE, grasp_graph

#: (name, default, description) of each launch argument
ARGUMENTS = (
    ('namespace', '', "the hand's namespace ('' = the root, e.g. left_hand); in a namespace the "
     'hand keeps its sim time on <namespace>/clock'),
    ('duration', '6.0', 'sim time to run [s]; the launch ends when the simulator stops '
     '(0 = until Ctrl-C)'),
    ('control_period', '', "the loop's period [s], given to the simulator, the estimator and the "
     "controller alike (0.001 to 0.01; '' = the config files, 0.001)"),
    ('mode', '', "the simulator's stepping: lockstep, pipelined (the physics one period behind the "
     "commands, stepped while they are computed) or realtime ('' = config/simulator.yaml, "
     'lockstep)'),
    ('law', '', "control law of the controller, one the files of soft_gripper_sdre/control/laws "
     "register for the graph ('' = config/controller.yaml)"),
    ('noise', '', "tip measurement noise σ [mm] ('' = config/simulator.yaml, 0.05 mm)"),
    ('seed', '', "seed of the measurement noise ('' = config/simulator.yaml)"),
    ('record', 'false', 'record every topic of the graph to a rosbag2 (MCAP) directory'),
    ('output', '', "with record:=true, the bag directory to create ('' = rosbag2_<date>-<time> "
     'here)'),
    ('startup_timeout', '300', 'wall time the simulator waits for the graph to be wired and ready '
     'before it gives up [s]; the first launch of a fresh install compiles the control kernels '
     'first'),
    ('params_file', '', "a ROS parameters file of your own, given to every node after its shipped "
     "config/<node>.yaml (sections /**/<node> or /**); '' = none"),
    ('composed', 'false', "run the estimator in the controller's process (controller "
     '--with-estimator): one process and one DDS hop fewer per period'),
    ('realtime_priority', '0', 'run the simulator, the estimator and the controller under '
     'SCHED_FIFO at this priority (1 to 98, behind chrt -f; 0 = ordinary scheduling): on time on a '
     'busy machine; needs root, CAP_SYS_NICE or an rtprio limit'),
    ('pin_cores', 'false', 'run the simulator on one CPU and the estimator and the controller on '
     'another (behind taskset -c; needs two CPUs): each keeps its caches from period to period'),
)

_TRUE, _FALSE = ('true', '1', 'yes', 'on'), ('false', '0', 'no', 'off', '')
#: wall time [s] a node gets to close after launch's SIGINT (its final /diagnostics, up to 2 s for
#: its readers' acknowledgements, the recorder its bag) before launch sends SIGTERM; measured 1 to
#: 5.5 s on two loaded cores, more than launch's default of 5 s
CLOSE_TIMEOUT = 15


def argument_help(name: str, text: str) -> str:
    """The help of the launch argument ``name`` (``text`` from :data:`ARGUMENTS`): the ``law``
    argument's lists the laws the registry holds for the graph
    (:data:`~soft_gripper_sdre.control.laws.GRAPH_LAWS`, imported here, when launching)."""
    if name != 'law':
        return text
    from soft_gripper_sdre.control.laws import GRAPH_LAWS
    return f'{text}: {", ".join(GRAPH_LAWS)}'


def _number(name: str, text: str, kind=float):
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f'launch argument {name}:={text!r} is not a number') from None


def _within(name: str, text: str, value, param: str) -> None:
    """Refuse ``value`` if the simulator's own declaration of ``param`` would."""
    from soft_gripper_sdre.nodes.simulator import PARAMS
    reason = next(p for p in PARAMS if p.name == param).check(value)
    if reason or value != value:
        raise ValueError(f'launch argument {name}:={text!r}: {reason or "not a number"}')


def _params_file(text: str):
    """The user's parameters file: an existing, readable YAML mapping."""
    from pathlib import Path

    import yaml

    path = Path(text).expanduser()
    try:
        document = yaml.safe_load(path.read_text(encoding='utf-8'))
    except OSError as exc:
        raise ValueError(f'launch argument params_file:={text!r}: cannot read {path}: '
                         f'{exc.strerror}') from None
    except yaml.YAMLError as exc:
        raise ValueError(f'launch argument params_file:={text!r}: {path} is not YAML: '
                         f'{str(exc).splitlines()[0]}') from None
    if not isinstance(document, dict):
        raise ValueError(f'launch argument params_file:={text!r}: {path} is not a ROS parameters '
                         'file (a mapping of node names to ros__parameters)')
    return path.resolve()


def grasp_nodes(namespace: str = '', duration: str = '6.0', control_period: str = '',
                mode: str = '', law: str = '', noise: str = '', seed: str = '',
                record: str = 'false', output: str = '', startup_timeout: str = '300',
                params_file: str = '', composed: str = 'false',
                realtime_priority: str = '0', pin_cores: str = 'false') -> list[dict]:
    """The launch arguments (strings, as launch gives them) → one dict per process, for
    ``launch_ros.actions.Node(**d)``: package, executable, name, namespace (relative, None at the
    root), parameters (the shipped params-file path, the user's, then a dict of overrides),
    remappings; with ``composed:=true`` the controller's process also runs the estimator
    (``arguments`` ['--with-estimator'], both nodes' files and overrides, and no ``name``, which
    launch_ros would give every node of the process); with ``realtime_priority:=N`` the loop's
    processes get ``prefix`` 'chrt -f N', with ``pin_cores:=true`` 'taskset -c <cpu>' before it.

    Raises:
        ValueError: naming the argument: not a number, a boolean, a namespace or a law where one
            is needed, a number or mode outside the simulator's limits, a control period outside
            0.001 to 0.01 s, a parameters file that cannot be read as one, or one that gives a
            node of the graph a value of the wrong type or a key it does not declare; a
            real-time priority out of range or not permitted for this user; pinning on a
            machine (or a process) with fewer than two CPUs.
    """
    from soft_gripper_sdre.control.laws import GRAPH_LAWS

    recording, composing = _boolean('record', record), _boolean('composed', composed)
    simulator = {'duration': _number('duration', duration),
                 'startup_timeout': _number('startup_timeout', startup_timeout)}
    _within('duration', duration, simulator['duration'], 'duration')
    _within('startup_timeout', startup_timeout, simulator['startup_timeout'], 'startup_timeout')
    parameters: dict[str, dict] = {'simulator': simulator, 'controller': {}}
    if noise.strip():
        simulator['noise_std'] = _number('noise', noise) * 1e-3
        _within('noise', noise, simulator['noise_std'], 'noise_std')
    if seed.strip():
        simulator['seed'] = _number('seed', seed, int)
        _within('seed', seed, simulator['seed'], 'seed')
    if mode.strip():
        simulator['mode'] = mode.strip()
        _within('mode', mode, simulator['mode'], 'mode')
    if law.strip():
        if law.strip() not in GRAPH_LAWS:
            raise ValueError(f'launch argument law:={law!r} is not a law of the controller '
                             f'({", ".join(GRAPH_LAWS)})')
        parameters['controller']['law'] = law.strip()
    if recording and output.strip():
        parameters['recorder'] = {'output': output.strip()}
    period = None
    if control_period.strip():
        period = _number('control_period', control_period)
        if not PERIOD_RANGE[0] <= period <= PERIOD_RANGE[1]:
            raise ValueError(f'launch argument control_period:={control_period!r} must be from '
                             f'{PERIOD_RANGE[0]:g} to {PERIOD_RANGE[1]:g} s')
    extra = [_params_file(params_file.strip())] if params_file.strip() else []
    priority = _number('realtime_priority', realtime_priority, int)
    if priority:
        from soft_gripper_sdre.nodes.scheduling import fifo_problem
        problem = fifo_problem(priority)
        if problem:
            raise ValueError(f'launch argument realtime_priority:={realtime_priority!r}: {problem}')
    pinning = _boolean('pin_cores', pin_cores)
    if pinning:
        from soft_gripper_sdre.nodes.graph import pinning_problem
        problem = pinning_problem()
        if problem:
            raise ValueError(f'launch argument pin_cores:={pin_cores!r}: {problem}')
    spec = grasp_graph(namespace, record=recording, parameters=parameters, control_period=period,
                       params_files=extra, composed=composing, realtime=priority, pin=pinning)
    for path in extra:
        _check_sections(params_file, path, [n for node in spec.nodes
                                            for n in (node, *node.hosted)])
    return [_launched(node) for node in spec.nodes]


def _check_sections(text: str, path, nodes) -> None:
    """Refuse the user's parameters file if it gives a node of the graph a value of the wrong
    type or a key the node does not declare, as the node itself would at start-up
    (:mod:`soft_gripper_sdre.nodes.params_files`); here before any node starts."""
    import importlib

    from soft_gripper_sdre.nodes.params import declared_types
    from soft_gripper_sdre.nodes.params_files import file_problems, package_parameter_names

    package = package_parameter_names()
    for node in nodes:
        params = importlib.import_module(node.module).PARAMS
        declared = declared_types(params)
        for problem in file_problems(node.full_name, declared, str(path), package):
            if problem.refuse:
                raise ValueError(f'launch argument params_file:={text!r}: {problem.message}')


def _boolean(name: str, text: str) -> bool:
    if text.strip().lower() not in _TRUE + _FALSE:
        raise ValueError(f"launch argument {name}:={text!r} must be 'true' or 'false'")
    return text.strip().lower() in _TRUE


def _launched(node) -> dict:
    """``launch_ros.actions.Node`` keywords for the process of ``node`` (a NodeSpec)."""
    launched = {'package': PACKAGE, 'executable': node.executable, 'name': node.name,
                'namespace': node.namespace.lstrip('/') or None,
                'parameters': [str(f) for f in node.params_files]
                + ([dict(node.overrides)] if node.overrides else []),
                'remappings': [tuple(rule) for rule in node.remappings]}
    if node.flags:
        launched.update(name=None, arguments=list(node.flags))
    if node.prefix:
        launched['prefix'] = ' '.join(node.prefix)
    return launched


def exit_verdict(node: str, returncode: int, shutting_down: bool,
                 lead: str = 'simulator') -> tuple[str, str] | None:
    """What the launch does when ``node`` exits with ``returncode``: None while it is already
    shutting down; ``('done', reason)`` when the lead finished (status 0): shut down cleanly;
    ``('failed', message)`` for any other exit, a node that ended on its own before the lead
    finished: end the launch with that error (``ros2 launch`` then exits non-zero)."""
    if shutting_down:
        return None
    if node == lead and returncode == 0:
        return 'done', f'the {lead} finished'
    return 'failed', (f'the {node} node exited with status {returncode} before the {lead} '
                      f'finished; see its log above')


def generate_launch_description():
    """The LaunchDescription: the arguments, and the nodes once their values are checked."""
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    from launch import LaunchDescription
    from soft_gripper_sdre.tools.graph.procs import pinned_kernels

    def watch(name):
        def on_exit(event, context):
            verdict = exit_verdict(name, event.returncode, context.is_shutdown)
            if verdict is None:
                return None
            kind, text = verdict
            if kind == 'failed':
                raise RuntimeError(text)        # launch logs it, stops the others, exits with 1
            return [Shutdown(reason=text)]
        return on_exit

    def nodes(context):
        values = {name: LaunchConfiguration(name).perform(context) for name, _, _ in ARGUMENTS}
        # the math kernels every AVX2 machine runs alike, as the demo's processes get them
        env = pinned_kernels()
        return [Node(**node, output='screen', emulate_tty=True,
                     on_exit=watch(node['name'] or node['executable']),
                     sigterm_timeout=str(CLOSE_TIMEOUT), additional_env=env or None)
                for node in grasp_nodes(**values)]

    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default,
                               description=argument_help(name, text))
         for name, default, text in ARGUMENTS]
        + [OpaqueFunction(function=nodes)])
