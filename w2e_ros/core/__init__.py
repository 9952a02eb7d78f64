"""The ROS-free core: model, training, exploration strategies and loop, metrics, data.

Nothing here imports rclpy: the offline ``w2e`` commands use it directly and the ROS nodes
wrap it.
"""
