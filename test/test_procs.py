"""The process-graph helpers' own ROS side: the diagnostics monitor takes every queued message."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import pytest
from rclpy.duration import Duration
from rosutil import Probe, ros_context, spin_until

from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS
from soft_gripper_sdre.tools.graph.procs import DiagnosticsMonitor, ros_env

pytestmark = pytest.mark.ros


def test_one_poll_takes_every_message_that_has_arrived():
    monitor = DiagnosticsMonitor(ros_env())
    try:
        with ros_context() as (ctx, executor):
            probe = Probe(ctx)
            executor.add_node(probe)
            pub = probe.create_publisher(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
            assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0)
            for i in range(20):
                msg = DiagnosticArray()
                msg.status = [DiagnosticStatus(name=f'/node_{i}',
                                               values=[KeyValue(key='k', value=str(i))])]
                pub.publish(msg)
            # acknowledged: all 20 are in the monitor's reader, none taken yet
            assert pub.wait_for_all_acked(Duration(seconds=10.0))
            assert monitor.values == {}
            monitor.poll()
            assert sorted(monitor.values) == sorted(f'node_{i}' for i in range(20))
            assert (monitor.get('node_7', 'k') == 7.0
                    and monitor.get('node_7', 'missing', -1.0) == -1.0)
    finally:
        monitor.close()
