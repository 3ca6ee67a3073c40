"""The simulated gripper (no ROS): the PyBullet finger and hand, excitation signals, SI/sim units
and the finger's exact task-space dynamics (the ground truth a learned model is judged against).
"""
