"""What the robot learns from and acts on: the interactions grouped by observed cloud and
their shard format (``interactions``), the categories and instance splits of
``config/categories.yaml`` (``categories``) and the object-in-a-start-state unit of the
offline runs with its seeds (``targets``). Imports only :mod:`w2e_ros.core.infra`."""
