"""Judging models and loops (no ROS): the in-process closed loop, tracking metrics, reading bags,
figures, ground-truth surveys and the oracle laws.
"""
