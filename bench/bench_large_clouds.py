"""Large best-effort clouds between two processes, with and without the transport profile.

    .venv/bin/python bench/bench_large_clouds.py [--duration 15] [--rate 2] [--width 640]
                                                 [--height 576]

One process publishes a ``PointCloud2`` of ``width x height`` points x 32 bytes (an Azure
Kinect frame: 11.8 MB) best effort at ``rate`` Hz for ``duration`` s; a second process
subscribes with ``qos_profile_sensor_data`` and counts what arrives. Run once with Fast DDS's
builtin transports (neither profile variable set in the two processes) and once with
``config/fastdds_large_messages.xml`` (both set, as w2e bringup sets them). Discovery range
as w2e bringup's (this shell's ROS_AUTOMATIC_DISCOVERY_RANGE), on a domain of its own.

First it prints the milliseconds of ``arrays_to_cloud`` + ``cloud_to_arrays`` (points,
normals, one field) for a cloud of that size and of 200,000 points, the median of 5.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays
from w2e_ros.ros.processes import clean_shm, pick_domain_id, ros_env, shm_files
from w2e_ros.ros.transport import (
    measure_delivery,
    profile_path,
    with_transport_profile,
    without_transport_profile,
)


def conversion_ms(n: int, repeat: int = 5) -> float:
    """Median ms of one cloud of ``n`` points to a PointCloud2 and back (as the nodes do)."""
    pts = np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        cloud_to_arrays(arrays_to_cloud(pts, pts, {"a": pts[:, 0]}))
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=15.0, help="seconds of publishing, each way")
    p.add_argument("--rate", type=float, default=2.0, help="Hz")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=576)
    a = p.parse_args()

    for n in (200_000, a.width * a.height):
        print(f"{f'conversion, {n:,} points':>40}: {conversion_ms(n):.1f} ms to PointCloud2 "
              "and back", flush=True)
    for label, setup in (("builtin transports", without_transport_profile),
                         (f"profile {profile_path().name}", with_transport_profile)):
        before = shm_files()
        env = setup(ros_env(domain_id=pick_domain_id(), localhost_only=False))
        try:
            result = measure_delivery(env, width=a.width, height=a.height, rate=a.rate,
                                      duration=a.duration)
        finally:
            clean_shm(before)
        print(f"{label:>40}: {result}", flush=True)


if __name__ == "__main__":
    main()
