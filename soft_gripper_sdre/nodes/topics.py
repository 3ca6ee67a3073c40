"""The topic contract of the node graph: names, message types, QoS (see README "Topics").

Each loop topic (``tip_positions``, ``state_estimate``, ``torque_commands``) carries one message
per control period for all four fingers; ``grasp_reference`` carries the whole planned grasp, once
per plan; ``/clock`` and the state topics run at 100 Hz of sim time. Every stamp is sim time.
"""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

CLOCK = '/clock'
TIP_POSITIONS = 'tip_positions'
STATE_ESTIMATE = 'state_estimate'
GRASP_REFERENCE = 'grasp_reference'
TORQUE_COMMANDS = 'torque_commands'
JOINT_STATES = 'joint_states'
CUBE_POSE = 'cube_pose'
CUBE_CONTACTS = 'cube_contacts'
DIAGNOSTICS = '/diagnostics'

#: topic → message class, for the recorder, the echo tool and the tests
TOPIC_TYPES = {
    CLOCK: Clock,
    TIP_POSITIONS: PoseArray,
    STATE_ESTIMATE: MultiDOFJointTrajectory,
    GRASP_REFERENCE: MultiDOFJointTrajectory,
    TORQUE_COMMANDS: JointState,
    JOINT_STATES: JointState,
    CUBE_POSE: PoseStamped,
    CUBE_CONTACTS: JointState,
    DIAGNOSTICS: DiagnosticArray,
}

#: the control loop's publishers, and readers that must see every message (the recorder, tests):
#: reliable, so lockstep never loses a period; a small queue absorbs bursts
LOOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
#: the loop nodes' own readers (the estimator's tips, the controller's estimates, the simulator's
#: commands): only the newest message is kept, so a node that fell behind (a busy machine) goes on
#: from the present instead of working off a queue, and the loop latency cannot build up. Lockstep
#: has one message in flight per topic and loses nothing; what a node skipped shows as a gap in
#: the stamps it receives
NEWEST_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: the grasp plan: only the newest matters, and a late-joining controller or recorder still gets
#: it (transient local), so start-up order between the trajectory node and the others does not
#: matter
REFERENCE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: slower streams (joint states, cube pose, diagnostics)
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: /clock (100 Hz of sim time by default): reliable, so the recorder keeps every tick; rclpy's time
#: source subscribes best-effort, which a reliable publisher serves too
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def type_name(msg_class) -> str:
    """'pkg/msg/Type' of a message class."""
    module = msg_class.__module__.split('.')[0]
    return f'{module}/msg/{msg_class.__name__}'
