"""The Where2Explore network and its training: sizes (``config``), PointNet++
(``pointnet2_geometry``, ``pointnet2``), the encoder with its affordance and similarity heads
and the checkpoints (``network``), ``training/``, predictions on stored interactions
(``predict``), the manipulate policy (``policy``), metrics (``metrics``) and figures
(``viz``). Stands on :mod:`w2e_ros.core.robot`, :mod:`w2e_ros.core.dataset` and
:mod:`w2e_ros.core.infra`; knows nothing of exploration."""
