"""ROS-side helpers shared by the nodes: message conversions, parameters, QoS, processes.

``pointcloud``, ``conversions``, ``params`` and ``qos`` import ROS message/rclpy modules;
``waypoints`` and ``processes`` are plain Python (the bridge geometry and process control are
testable without a ROS graph).
"""
