"""The robot side of the core, which the simulator and a real-arm adapter implement: the
primitives contract (action, gripper frame, waypoint schedule, success rule:
``primitives``), action frames and their encoding (``actions``), the Panda's kinematics
(``kinematics``), whether an approach runs into the observed object (``feasibility``), the
outcome judged from two clouds (``outcome``) and point cloud helpers (``pointcloud``,
``fps``). Imports only :mod:`w2e_ros.core.infra`: no model, no learning."""
