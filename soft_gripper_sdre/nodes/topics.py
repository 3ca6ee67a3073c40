"""The topic contract of the node graph: names, message types, QoS (see README "Topics").

One message per topic per control period carries all four fingers; every stamp is sim time.
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

#: the control loop: reliable, so lockstep never loses a period; a small queue absorbs bursts
LOOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
#: the grasp reference: a late-joining controller still gets the last horizons (transient local),
#: so start-up order between the trajectory node and the controller does not matter
REFERENCE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: slower streams (joint states, cube pose, diagnostics)
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                        reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
#: /clock: reliable, so the recorder keeps every tick of a busy 1 kHz run; rclpy's time source
#: subscribes best-effort, which a reliable publisher serves too
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def type_name(msg_class) -> str:
    """'pkg/msg/Type' of a message class."""
    module = msg_class.__module__.split('.')[0]
    return f'{module}/msg/{msg_class.__name__}'
