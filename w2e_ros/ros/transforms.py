"""Camera clouds into the robot frame: from the robot's TF tree or a static camera pose.

A real depth camera (Azure Kinect, RealSense) publishes its cloud in its optical frame (z
forward, x right, y down); the segmentation and everything after it work in the robot's frame
(``frame_id``, ``world`` in the simulator). :class:`CameraFrames` decides, per cloud, which
transform takes it there:

* the cloud is already in the robot frame (or has no frame): none;
* ``tf``: looked up in TF (:mod:`w2e_ros.ros.tf`: ``/tf`` and ``/tf_static``) at the cloud's
  stamp, waiting up to a timeout; no transform is a :class:`FrameError` naming the missing
  edge or the stamp that is too old (no fallback: the robot's tree is the one source);
* ``auto``: TF as above, and when TF has no transform, the static ``camera_pose`` if the user
  set one for that frame (a frame TF has never heard of falls back at once, without waiting);
* ``static``: the static ``camera_pose`` only, given as ``static_transform_publisher`` takes it
  (x y z qx qy qz qw: the pose of the camera frame in the robot frame, which maps camera
  points into the robot frame).

The geometry here is plain numpy and imports nothing of TF; the lookup that reads the
robot's tree is :class:`w2e_ros.ros.tf.TfLookup`, which stands on this module.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from w2e_ros.ros.conversions import matrix_from_quaternion
from w2e_ros.ros.pointcloud import CloudFormatError

TRANSFORM_SOURCES = ("auto", "tf", "static")


class FrameError(CloudFormatError):
    """A cloud in a frame the node has no transform for into the robot frame (and why)."""


def rotation_from_quaternion(q: Sequence[float]) -> np.ndarray:
    """(x, y, z, w) -> (3, 3) rotation; a quaternion that is not finite or has zero norm is
    refused (ValueError), any other is normalised, as ``static_transform_publisher`` does."""
    q = np.asarray(q, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or not np.isfinite(q).all():
        raise ValueError(f"a quaternion needs 4 finite values (qx qy qz qw), got {q.tolist()}")
    norm = np.linalg.norm(q)
    if norm < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} has zero norm: not a rotation")
    return matrix_from_quaternion(q)


@dataclass(frozen=True)
class RigidTransform:
    """``p_target = rotation @ p_source + translation``."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    @classmethod
    def from_pose(cls, translation: Sequence[float], quaternion: Sequence[float]
                  ) -> RigidTransform:
        """From a position (x, y, z) and an orientation (qx, qy, qz, qw) of the source frame
        in the target frame."""
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise ValueError(f"a translation needs 3 finite values (x y z), got {t.tolist()}")
        return cls(rotation_from_quaternion(quaternion), t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points -> (N, 3) float32 in the target frame (computed in float64)."""
        p = np.asarray(points, dtype=np.float64)
        return (p @ self.rotation.T + self.translation).astype(np.float32)

    def rotate(self, vectors: np.ndarray) -> np.ndarray:
        """(N, 3) directions (normals) -> (N, 3) float32 in the target frame."""
        return (np.asarray(vectors, dtype=np.float64) @ self.rotation.T).astype(np.float32)


def parse_camera_pose(values: Sequence[float]) -> RigidTransform | None:
    """The ``camera_pose`` parameter: [] -> None (not set); x y z qx qy qz qw -> the transform.

    Raises ValueError naming the parameter for any other length, a value that is not finite
    or a quaternion of zero norm.
    """
    values = list(values)
    if not values:
        return None
    if len(values) != 7:
        raise ValueError(
            f"camera_pose needs 7 values, x y z qx qy qz qw (static_transform_publisher's "
            f"order), got {len(values)}: {values}")
    try:
        return RigidTransform.from_pose(values[:3], values[3:])
    except ValueError as err:
        raise ValueError(f"camera_pose {values}: {err}") from err


def transform_from_msg(msg) -> RigidTransform:
    """geometry_msgs/Transform (``TransformStamped.transform``) -> RigidTransform."""
    t, q = msg.translation, msg.rotation
    return RigidTransform.from_pose((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


Lookup = Callable[..., RigidTransform]
"""(source frame, header stamp, wait=True) -> transform into the target frame; raises
FrameError. ``wait=False``: answer from what has arrived, at once."""


class CameraFrames:
    """Which transform takes a cloud in ``frame`` into ``target_frame`` (see the module doc).

    ``lookup`` is the TF lookup (:class:`w2e_ros.ros.tf.TfLookup`; None where TF is not used),
    ``knows(frame)`` whether TF has heard of a frame at all (auto: a frame it has not falls
    back to the static pose without waiting), ``warn`` gets the note that a failed lookup fell
    back to the static pose.
    """

    def __init__(self, target_frame: str, source: str = "auto",
                 static_pose: RigidTransform | None = None, static_frame: str = "",
                 lookup: Lookup | None = None,
                 warn: Callable[[str], None] | None = None,
                 knows: Callable[[str], bool] | None = None) -> None:
        if source not in TRANSFORM_SOURCES:
            raise ValueError(f"transform_source must be one of {TRANSFORM_SOURCES}, got "
                             f"{source!r}")
        if source in ("tf", "auto") and lookup is None and target_frame:
            raise ValueError(f"transform_source {source!r} needs a TF lookup")
        self.target_frame = target_frame
        self.source = source
        self.static_pose = static_pose
        self.static_frame = static_frame
        self.lookup = lookup if source in ("auto", "tf") else None
        self.warn = warn or (lambda _msg: None)
        self.knows = knows or (lambda _frame: True)

    def uses_tf(self) -> bool:
        """Whether clouds in other frames are looked up in TF."""
        return self.lookup is not None

    def transform_for(self, frame: str, stamp=None) -> RigidTransform | None:
        """The transform of a cloud in ``frame`` into the target frame, None when it is
        already there; raises FrameError when there is none."""
        if not self.target_frame or frame in ("", self.target_frame):
            return None
        if self.lookup is not None:
            static = self._static_for(frame) if self.source == "auto" else None
            try:
                # auto with a static pose for a frame TF has never named: no wait for TF
                wait = static is None or self.knows(frame)
                return self.lookup(frame, stamp, wait=wait)
            except FrameError as err:
                if static is None and self.source == "auto" and self.static_pose is None:
                    raise FrameError(f"{err}; or set camera_pose (x y z qx qy qz qw of the "
                                     f"camera frame in {self.target_frame!r})") from None
                if static is None:
                    raise
                self.warn(f"{err}; using the static camera_pose instead")
                return static
        static = self._static_for(frame)
        if static is not None:
            return static
        if self.static_pose is not None:  # set, but for another frame
            raise FrameError(
                f"cloud is in frame {frame!r}; camera_pose is the pose of "
                f"{self.static_frame!r} in {self.target_frame!r} (camera_frame)")
        raise FrameError(
            f"cloud is in frame {frame!r}, not {self.target_frame!r}, and there is no "
            f"transform: set camera_pose (x y z qx qy qz qw of the camera frame in "
            f"{self.target_frame!r}) or transform_source tf / auto")

    def _static_for(self, frame: str) -> RigidTransform | None:
        if self.static_pose is None or (self.static_frame and frame != self.static_frame):
            return None
        return self.static_pose

