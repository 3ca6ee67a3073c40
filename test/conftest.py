"""Shared test set-up: DDS stays on loopback, each test session gets its own domain."""
import os
import random

# Must be set before any rclpy.init(); subprocesses started by tests inherit them.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault(
    'ROS_DOMAIN_ID', str(random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), 'little')).randint(1, 101))
)
os.environ.setdefault('OMP_NUM_THREADS', '1')
