"""The grasp graph for ``ros2 launch`` on a ROS 2 Jazzy install.

    ros2 launch soft_gripper_sdre grasp.launch.py [namespace:=left_hand] [duration:=6.0]
        [control_period:=0.005] [law:=sdre_ff] [noise:=0.05] [seed:=0] [record:=true]
        [output:=runs/grasp_bag] [startup_timeout:=300]

Starts the recorder (with ``record:=true``), the estimator, the trajectory node, the controller
and the simulator of :func:`soft_gripper_sdre.nodes.graph.grasp_graph`, the same description the
demo and the tests start as processes: each node with its ``config/<node>.yaml`` from the
package's share directory, the overrides the arguments ask for, and in a namespace its own clock
(``/clock`` remapped to ``<namespace>/clock``). The launch ends when the simulator exits (after
``duration`` seconds of sim time; ``duration:=0`` runs until Ctrl-C).

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
    ('duration', '6.0', 'sim time to run [s]; the launch ends when the simulator stops (0 = until Ctrl-C)'),
    ('control_period', '', "the loop's period [s], given to the simulator, the estimator and the controller "
     "alike (0.001 to 0.01; '' = the config files, 0.001)"),
    ('law', '', "control law of the controller (sdre_ff, sdre, lqr, pd; '' = config/controller.yaml)"),
    ('noise', '', "tip measurement noise σ [mm] ('' = config/simulator.yaml, 0.05 mm)"),
    ('seed', '', "seed of the measurement noise ('' = config/simulator.yaml)"),
    ('record', 'false', 'record every topic of the graph to a rosbag2 (MCAP) directory'),
    ('output', '', "with record:=true, the bag directory to create ('' = rosbag2_<date>-<time> here)"),
    ('startup_timeout', '300', 'wall time the simulator waits for the controller and its tip readers before '
     'stepping anyway [s]; the first launch of a fresh install compiles the control kernels first'),
)

_TRUE, _FALSE = ('true', '1', 'yes', 'on'), ('false', '0', 'no', 'off', '')


def _number(name: str, text: str, kind=float):
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f'launch argument {name}:={text!r} is not a number') from None


def grasp_nodes(namespace: str = '', duration: str = '6.0', control_period: str = '', law: str = '',
                noise: str = '', seed: str = '', record: str = 'false', output: str = '',
                startup_timeout: str = '300') -> list[dict]:
    """The launch arguments (strings, as launch gives them) → one dict per node, for
    ``launch_ros.actions.Node(**d)``: package, executable, name, namespace (relative, None at the
    root), parameters (the params-file path, then a dict of overrides), remappings.

    Raises:
        ValueError: an argument that is not a number, a boolean or a namespace where one is needed,
            or a control period outside 0.001 to 0.01 s.
    """
    if record.strip().lower() not in _TRUE + _FALSE:
        raise ValueError(f"launch argument record:={record!r} must be 'true' or 'false'")
    recording = record.strip().lower() in _TRUE
    parameters: dict[str, dict] = {'simulator': {'duration': _number('duration', duration),
                                                 'startup_timeout': _number('startup_timeout', startup_timeout)},
                                   'controller': {}}
    if noise.strip():
        parameters['simulator']['noise_std'] = _number('noise', noise) * 1e-3
    if seed.strip():
        parameters['simulator']['seed'] = _number('seed', seed, int)
    if law.strip():
        parameters['controller']['law'] = law.strip()
    if recording and output.strip():
        parameters['recorder'] = {'output': output.strip()}
    period = None
    if control_period.strip():
        period = _number('control_period', control_period)
        if not PERIOD_RANGE[0] <= period <= PERIOD_RANGE[1]:
            raise ValueError(f'launch argument control_period:={control_period!r} must be from '
                             f'{PERIOD_RANGE[0]:g} to {PERIOD_RANGE[1]:g} s')
    spec = grasp_graph(namespace, record=recording, parameters=parameters, control_period=period)
    return [{'package': PACKAGE, 'executable': node.executable, 'name': node.name,
             'namespace': node.namespace.lstrip('/') or None,
             'parameters': ([str(node.params_file)] if node.params_file else [])
             + ([dict(node.parameters)] if node.parameters else []),
             'remappings': [tuple(rule) for rule in node.remappings]}
            for node in spec.nodes]


def generate_launch_description():
    """The LaunchDescription: the arguments, and the nodes once their values are known."""
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    def nodes(context):
        values = {name: LaunchConfiguration(name).perform(context) for name, _, _ in ARGUMENTS}
        return [Node(**node, output='screen', emulate_tty=True,
                     on_exit=Shutdown(reason='the simulator stopped') if node['name'] == 'simulator' else None)
                for node in grasp_nodes(**values)]

    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text) for name, default, text in ARGUMENTS]
        + [OpaqueFunction(function=nodes)])
