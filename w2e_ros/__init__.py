"""w2e_ros: Where2Explore few-shot affordance learning as a ROS 2 stack.

``w2e_ros.core`` is ROS-free (model, training, exploration, metrics, data) and is what the
``w2e`` command line uses directly; ``w2e_ros.nodes`` wrap it as ROS 2 nodes.
"""

__version__ = "0.1.0"
