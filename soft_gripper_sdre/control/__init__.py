"""Tracking control with a learned SDC model (no ROS): Riccati solvers, the SDRE supervisor, the
control laws, the Kalman filter, grasp references and reference horizons.
"""
