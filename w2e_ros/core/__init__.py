"""The ROS-free core: model, training, exploration strategies and loop, metrics, data.

Nothing here imports rclpy: the offline ``w2e`` commands use it directly and the ROS nodes
wrap it. Nothing here imports the simulator or the simulator experiments
(:mod:`w2e_ros.experiments`) either, not even inside a function: a robot workstation runs the
core without them.
"""
