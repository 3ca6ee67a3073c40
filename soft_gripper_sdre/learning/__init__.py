"""Learning the SDC model from tip measurements (no ROS): derivative labels by KF + RTS, datasets,
the two networks A(x), G(x) and their training. The only subpackage that imports torch.
"""
