"""The ROS-free core, in layers; each imports only the layers below it:

- ``exploration/``: the few-shot loop, its rules and their registry, fine-tuning, proposals;
- ``model/``: the network, its training, predictions, the manipulate policy;
- ``robot/`` and ``dataset/``: the primitives contract and the robot's geometry; the
  interactions, categories and targets;
- ``infra/``: settings, threads, the allocator.

Nothing here imports rclpy: the offline ``w2e`` commands use it directly and the ROS nodes
wrap it. Nothing here imports the simulator or the simulator experiments
(:mod:`w2e_ros.experiments`) either, not even inside a function: a robot workstation runs the
core without them.
"""
