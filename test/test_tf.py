"""The TF buffer and listener (w2e_ros.ros.tf): chains through the tree, transforms at a stamp
(interpolated, nearest within the tolerance, the latest common time), errors that name the
missing edge or the stamp, and a tree published from a separate process (static joints on
/tf_static, a moving one on /tf, as robot_state_publisher does) read back in this one.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from scipy.spatial.transform import Rotation

from w2e_ros.ros.tf import NS, TfBuffer, TfError

T0 = 1_700_000_000 * NS  # a stamp as a robot's clock gives it
BASE = [0.95, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]  # world -> panda_link0 (the stack's arm base)
MOUNT = [0.1, 0.0, 0.3, 0.0, 0.0, 0.0, 1.0]  # panda_link1 -> camera_link (a wrist camera)
OPTICAL = [0.0, 0.0, 0.0, -0.5, 0.5, -0.5, 0.5]  # camera_link -> camera_optical_frame (REP 103)


def matrix(pose) -> np.ndarray:
    """x y z qx qy qz qw -> (4, 4)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(pose[3:]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def joint1(t_s: float) -> list[float]:
    """panda_link0 -> panda_link1 with joint 1 at 0.4 t rad (about z, 0.333 m up)."""
    return [0.0, 0.0, 0.333, *Rotation.from_rotvec([0.0, 0.0, 0.4 * t_s]).as_quat()]


def as_matrix(tr) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = tr.rotation, tr.translation
    return T


def robot_tree(buffer: TfBuffer, stamps_s=(0.0, 0.5, 1.0, 1.5, 2.0)) -> None:
    buffer.set_transform("world", "panda_link0", 0, BASE[:3], BASE[3:], static=True)
    buffer.set_transform("panda_link1", "camera_link", 0, MOUNT[:3], MOUNT[3:], static=True)
    buffer.set_transform("camera_link", "camera_optical_frame", 0, OPTICAL[:3], OPTICAL[3:],
                         static=True)
    for t in stamps_s:
        p = joint1(t)
        buffer.set_transform("panda_link0", "panda_link1", T0 + int(t * NS), p[:3], p[3:])


def expected(t_s: float) -> np.ndarray:
    """camera_optical_frame -> world at ``t_s``."""
    return matrix(BASE) @ matrix(joint1(t_s)) @ matrix(MOUNT) @ matrix(OPTICAL)


def test_a_chain_of_static_and_moving_edges_is_composed_at_the_stamp():
    buf = TfBuffer()
    robot_tree(buf)
    for t in (0.0, 0.5, 0.8, 1.25, 2.0):  # on samples and between them (slerp of joint 1)
        got = as_matrix(buf.lookup("world", "camera_optical_frame", T0 + int(t * NS)))
        np.testing.assert_allclose(got, expected(t), atol=1e-9)
    # the inverse direction, and between two branches of the tree
    got = as_matrix(buf.lookup("camera_optical_frame", "world", T0 + int(0.8 * NS)))
    np.testing.assert_allclose(got, np.linalg.inv(expected(0.8)), atol=1e-9)
    got = as_matrix(buf.lookup("panda_link0", "camera_link", T0 + NS))
    np.testing.assert_allclose(got, matrix(joint1(1.0)) @ matrix(MOUNT), atol=1e-9)
    assert np.allclose(as_matrix(buf.lookup("world", "world")), np.eye(4))
    # stamp 0: the latest time every moving edge of the chain has
    np.testing.assert_allclose(as_matrix(buf.lookup("world", "camera_optical_frame")),
                               expected(2.0), atol=1e-9)
    # static-only chains need no stamp at all
    np.testing.assert_allclose(as_matrix(buf.lookup("panda_link1", "camera_optical_frame",
                                                    T0 + 100 * NS)),
                               matrix(MOUNT) @ matrix(OPTICAL), atol=1e-9)


def test_stamps_outside_the_history_take_the_nearest_within_tolerance_or_fail_naming_the_edge():
    buf = TfBuffer(cache_s=1.0)
    robot_tree(buf)  # samples 0 .. 2 s; 1 s of history: 1.0 .. 2.0 s kept
    late = T0 + int(2.05 * NS)
    np.testing.assert_allclose(as_matrix(buf.lookup("world", "camera_optical_frame", late,
                                                    tolerance_s=0.1)), expected(2.0), atol=1e-9)
    with pytest.raises(TfError, match="edge 'panda_link0' -> 'panda_link1': no transform at "
                       r"1700000002\.050 s yet") as err:
        buf.lookup("world", "camera_optical_frame", late)
    assert err.value.retriable  # a later message may answer it
    with pytest.raises(TfError, match=r"too old, its oldest kept transform is 1700000001\.000 s"
                       r".*1 s of history") as err:
        buf.lookup("world", "camera_optical_frame", T0 + int(0.5 * NS))
    assert not err.value.retriable


def test_a_missing_edge_is_named():
    buf = TfBuffer()
    robot_tree(buf)
    with pytest.raises(TfError, match="frame 'camera_depth_frame' is not in TF.*frames known: "
                       "camera_link, camera_optical_frame, panda_link0, panda_link1, world"):
        buf.lookup("world", "camera_depth_frame", T0)
    # the camera mount on a second tree: nothing joins camera_link to the arm
    other = TfBuffer()
    other.set_transform("world", "panda_link0", 0, BASE[:3], BASE[3:], static=True)
    other.set_transform("camera_link", "camera_optical_frame", 0, OPTICAL[:3], OPTICAL[3:],
                        static=True)
    with pytest.raises(TfError, match="two trees.*'camera_optical_frame' goes up to "
                       "'camera_link', 'world' to 'world'.*nothing publishes the parent of "
                       "'camera_link'"):
        other.lookup("world", "camera_optical_frame")
    empty = TfBuffer()
    with pytest.raises(TfError, match="nothing received on /tf or /tf_static"):
        empty.lookup("world", "camera_optical_frame")


def test_malformed_transforms_are_refused_and_history_is_bounded():
    buf = TfBuffer(cache_s=0.5)
    with pytest.raises(ValueError, match="zero norm"):
        buf.set_transform("a", "b", 0, [0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="two different frames"):
        buf.set_transform("a", "a", 0, [0, 0, 0], [0, 0, 0, 1])
    for k in range(100):
        buf.set_transform("a", "b", T0 + k * NS // 10, [k, 0, 0], [0, 0, 0, 1])
    edge = buf._edges["b"]
    assert edge.stamps[0] == T0 + 94 * NS // 10 and len(edge.stamps) == 6  # 9.4 .. 9.9 s
    # out of order samples land in order; a leading '/' is tf1's and is dropped
    buf.set_transform("/a", "b", T0 + 97 * NS // 10 + NS // 20, [97.5, 0, 0], [0, 0, 0, 1])
    assert edge.stamps == sorted(edge.stamps)
    assert buf.lookup("a", "b", T0 + 97 * NS // 10 + NS // 20).translation[0] == 97.5


# -- a tree published by another process -----------------------------------------------------

STAMPS = [0.0, 0.5, 1.0, 1.5, 2.0]


def tree_spec() -> dict:
    return {"static": [["world", "panda_link0", *BASE], ["panda_link1", "camera_link", *MOUNT],
                       ["camera_link", "camera_optical_frame", *OPTICAL]],
            "dynamic": [["panda_link0", "panda_link1", T0 + int(t * NS), *joint1(t)]
                        for t in STAMPS],
            "rate_hz": 10.0}


def start_tree(spec: dict, domain: int, log_dir: Path) -> subprocess.Popen:
    from w2e_ros.ros.processes import ros_env

    proc = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("tf_tree.py")), json.dumps(spec)],
        env=ros_env(domain_id=domain, log_dir=log_dir), start_new_session=True,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout.readline().strip() == "ready", proc.stdout.read()
    return proc


@pytest.mark.slow
def test_listener_reads_a_tree_published_by_another_process(tmp_path):
    from rclpy.executors import MultiThreadedExecutor

    from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, stop_process
    from w2e_ros.ros.tf import TfListener

    clean_shm_at_exit()
    domain = pick_domain_id()
    # the static tree is published (latched) before this process subscribes
    proc = start_tree(tree_spec(), domain, tmp_path / "ros_log")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("tf_listener_test", context=ctx)
    exe = MultiThreadedExecutor(num_threads=2, context=ctx)
    exe.add_node(node)
    try:
        listener = TfListener(node)
        threading.Thread(target=exe.spin, daemon=True).start()
        stamp = type("Stamp", (), {"sec": 1_700_000_000, "nanosec": 800_000_000})()
        tr = listener.lookup("world", "camera_optical_frame", stamp, timeout_s=20.0)
        np.testing.assert_allclose(as_matrix(tr), expected(0.8), atol=1e-9)
        # a missing edge: a clear error after the wait, no exception of another kind
        t = time.monotonic()
        with pytest.raises(TfError, match=r"frame 'camera_depth_frame' is not in TF.*"
                                          r"\(waited 0.3 s\)"):
            listener.lookup("world", "camera_depth_frame", stamp, timeout_s=0.3)
        assert time.monotonic() - t >= 0.3
        # too old for the moving edge: at once, it cannot get better by waiting (an error
        # that is not retried says nothing of a wait; a retried one ends "(waited 20 s)")
        old = type("Stamp", (), {"sec": 1_699_999_990, "nanosec": 0})()
        with pytest.raises(TfError, match="'panda_link0' -> 'panda_link1'.*too old") as err:
            listener.lookup("world", "camera_optical_frame", old, timeout_s=20.0)
        assert not err.value.retriable and "waited" not in str(err.value), err.value
    finally:
        exe.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        stop_process(proc)
