"""Tools that run the node graph as separate processes (what ``ros2 run`` would start)."""
