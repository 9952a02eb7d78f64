"""The SAPIEN world standing in for the Franka Panda and the Azure Kinect.

ROS-free: procedural articulated objects (``objects``), the PartNet-Mobility loader
(``urdf_loader``), the flying gripper and push/pull primitives (``physics``, ``world``) and the
camera (``camera``). ``bridge_node`` puts it behind the robot's topics, services and actions.
"""

import warnings

# SAPIEN warns at import when the machine has no system Vulkan; the physics-only scenes and
# the ray-cast camera used by default never need it.
warnings.filterwarnings("ignore", message="Failed to find system libvulkan")
