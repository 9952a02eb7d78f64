"""The ROS 2 nodes of the stack: thin wrappers over the core and the simulator bridge."""
