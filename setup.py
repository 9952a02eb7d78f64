"""ament_python package: the w2e_ros core + nodes and the sim_bridge world."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "w2e_ros"

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
        (f"share/{PACKAGE}/checkpoints", glob("checkpoints/*.pt")),
        (f"share/{PACKAGE}/checkpoints/replay_cfw", glob("checkpoints/replay_cfw/*")),
    ],
    package_data={"w2e_ros": ["../config/*.yaml", "../config/*.xml"]},
    install_requires=["numpy", "pyyaml", "tqdm"],
    python_requires=">=3.10",
    zip_safe=True,
    description="Where2Explore few-shot affordance learning as a ROS 2 stack",
    license="MIT",
    entry_points={
        "console_scripts": ["w2e = w2e_ros.cli:main"]
        + [f"{name} = {target}" for name, target in NODES.items()],
    },
)
