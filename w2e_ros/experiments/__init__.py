"""Simulator experiments: data collection, the benchmark, the learnability study, the ceiling
checks, the simulated world they act on and the backends their jobs run on.

They are kept apart from :mod:`w2e_ros.core` because they drive the simulator (``sim_bridge``
and SAPIEN) or study what it collected, while the core is the library a robot workstation
runs without the simulator: the experiments import the core, the core never imports them
(``test/test_architecture.py`` checks it, imports inside functions included).
"""
