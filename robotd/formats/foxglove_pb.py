"""Foxglove's well-known schemas as protobuf messages, for recordings (robotd.formats.record).

The message classes are Foxglove's own published definitions (``foxglove-schemas-protobuf``);
this module only fills them from robotd's messages and builds the MCAP schema record of each
(a ``FileDescriptorSet`` holding the schema's ``.proto`` file and everything it imports, which is
what Foxglove and the ``mcap`` tools decode protobuf channels with).

Frames: ``world`` (the robot at start-up, FRD: LOCAL_FRD), ``robot`` (FRD at the baseline centre
of the rectified rig), ``camera_left`` / ``camera_right`` (optical: x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.Odometry_pb2 import Odometry as FoxOdometry
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError, Message
from google.protobuf.timestamp_pb2 import Timestamp

from robotd.core.geometry import R_ROBOT_OPTICAL, R_to_quat

__all__ = [
    "CameraCalibration",
    "CompressedImage",
    "DecodeError",
    "FoxOdometry",
    "FrameTransforms",
    "ImageAnnotations",
    "PointCloud",
    "PoseInFrame",
    "PosesInFrame",
    "RawImage",
    "SceneUpdate",
]

WORLD, ROBOT = "world", "robot"
CAMERA = {"left": "camera_left", "right": "camera_right"}

# the classes a robotd recording uses, by their schema name (what the MCAP Schema record says)
CLASSES: dict[str, type[Message]] = {
    c.DESCRIPTOR.full_name: c
    for c in (
        CompressedImage, RawImage, CameraCalibration, PoseInFrame, PosesInFrame, FrameTransforms,
        PointCloud, ImageAnnotations, SceneUpdate, FoxOdometry,
    )
}  # fmt: skip


def file_descriptor_set(cls: type[Message]) -> bytes:
    """The MCAP schema data of a protobuf class: a FileDescriptorSet of its file and its imports,
    imports first."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: Any) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()  # type: ignore[no-any-return]


def stamp(wall_ns: int) -> Timestamp:
    sec, nsec = divmod(int(wall_ns), 1_000_000_000)
    return Timestamp(seconds=sec, nanos=nsec)


def _quat(R: np.ndarray) -> Quaternion:
    w, x, y, z = (float(v) for v in R_to_quat(R))
    return Quaternion(x=x, y=y, z=z, w=w)


def pose_pb(T: np.ndarray) -> Pose:
    """(4, 4) homogeneous transform -> foxglove Pose."""
    x, y, z = (float(v) for v in T[:3, 3])
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=_quat(T[:3, :3]))


def transform(wall_ns: int, parent: str, child: str, T_parent_child: np.ndarray) -> FrameTransform:
    x, y, z = (float(v) for v in T_parent_child[:3, 3])
    return FrameTransform(
        timestamp=stamp(wall_ns),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=x, y=y, z=z),
        rotation=_quat(T_parent_child[:3, :3]),
    )


def camera_transforms(wall_ns: int, baseline_m: float) -> list[FrameTransform]:
    """robot -> camera_left / camera_right: the optical axes at ∓b/2 along the robot's y (right)."""
    out = []
    for side, y in (("left", -0.5 * baseline_m), ("right", 0.5 * baseline_m)):
        T = np.eye(4)
        T[:3, :3] = R_ROBOT_OPTICAL
        T[1, 3] = y
        out.append(transform(wall_ns, ROBOT, CAMERA[side], T))
    return out


def points_cloud(wall_ns: int, xyz_W_m: np.ndarray, ids: np.ndarray) -> PointCloud:
    """The landmark map as a PointCloud in ``world``: x, y, z float32 and the landmark id (uint32)."""
    n = int(xyz_W_m.shape[0])
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz_W_m[:, 0], xyz_W_m[:, 1], xyz_W_m[:, 2]
    rec["id"] = np.asarray(ids, np.int64) & 0xFFFFFFFF
    F = PackedElementField
    return PointCloud(
        timestamp=stamp(wall_ns),
        frame_id=WORLD,
        pose=pose_pb(np.eye(4)),
        point_stride=16,
        fields=[
            F(name="x", offset=0, type=F.FLOAT32),
            F(name="y", offset=4, type=F.FLOAT32),
            F(name="z", offset=8, type=F.FLOAT32),
            F(name="id", offset=12, type=F.UINT32),
        ],
        data=rec.tobytes(),
    )


def covariance_ellipsoids(wall_ns: int, xyz_W_m: np.ndarray, cov_W: np.ndarray, n_sigma: float = 2.0) -> SceneUpdate:
    """One SceneEntity of spheres: each landmark's ``n_sigma`` ellipsoid (principal axes of its
    3×3 covariance), replacing the previous update's."""
    spheres = []
    if xyz_W_m.shape[0]:
        w, V = np.linalg.eigh(0.5 * (cov_W + np.swapaxes(cov_W, 1, 2)))
        V = V * np.where(np.linalg.det(V) < 0, -1.0, 1.0)[:, None, None]  # proper rotations
        size = 2.0 * n_sigma * np.sqrt(np.clip(w, 0.0, None))
        q = R_to_quat(V)  # (M, 4) w, x, y, z
        colour = Color(r=0.2, g=0.6, b=1.0, a=0.35)
        for p, s, qq in zip(xyz_W_m, size, q):
            pose = Pose(
                position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(w=float(qq[0]), x=float(qq[1]), y=float(qq[2]), z=float(qq[3])),
            )
            spheres.append(SpherePrimitive(pose=pose, size=Vector3(x=float(s[0]), y=float(s[1]), z=float(s[2])),
                                           color=colour))  # fmt: skip
    entity = SceneEntity(timestamp=stamp(wall_ns), frame_id=WORLD, id="landmark_covariance", spheres=spheres)
    return SceneUpdate(entities=[entity])


def feature_annotations(
    wall_ns: int, uv_px: np.ndarray, is_new: np.ndarray, tracks: Iterable[tuple[float, float, float, float]]
) -> ImageAnnotations:
    """The features the filter used, on the left image: re-observed landmarks green, new ones
    orange, and each re-observed landmark's track from its pixel in the previous annotated frame."""
    ts = stamp(wall_ns)
    anns = []
    for mask, colour in ((~is_new, Color(r=0.1, g=0.9, b=0.2, a=1.0)), (is_new, Color(r=1.0, g=0.6, b=0.0, a=1.0))):
        pts = [Point2(x=float(u), y=float(v)) for u, v in uv_px[mask][:, [0, 2]]]
        anns.append(PointsAnnotation(timestamp=ts, type=PointsAnnotation.POINTS, points=pts, outline_color=colour,
                                     thickness=4.0))  # fmt: skip
    seg = [Point2(x=float(x), y=float(y)) for x0, y0, x1, y1 in tracks for x, y in ((x0, y0), (x1, y1))]
    if seg:
        anns.append(PointsAnnotation(timestamp=ts, type=PointsAnnotation.LINE_LIST, points=seg,
                                     outline_color=Color(r=0.1, g=0.9, b=0.2, a=0.8), thickness=1.5))  # fmt: skip
    return ImageAnnotations(points=anns)


def odometry_pb(
    wall_ns: int, t_ns: int, vel: np.ndarray, rate: np.ndarray, cov: np.ndarray | None, source: str
) -> FoxOdometry:
    """A vehicle odometry sample (a body velocity: the pose is left at identity, its covariance
    zero, meaning unknown). robotd's own facts ride in the metadata: the capture time ``t_ns`` on
    the recording host's monotonic clock, the ``source``, and whether ``cov`` was stated
    (Foxglove's "zero if unknown" cannot tell an unstated noise from a stated zero)."""
    meta = [KeyValuePair(key="t_ns", value=str(int(t_ns))), KeyValuePair(key="source", value=source),
            KeyValuePair(key="cov", value="none" if cov is None else "given")]  # fmt: skip
    return FoxOdometry(
        timestamp=stamp(wall_ns),
        frame_id=ROBOT,
        body_frame_id=ROBOT,
        pose=pose_pb(np.eye(4)),
        linear_velocity=Vector3(x=float(vel[0]), y=float(vel[1]), z=float(vel[2])),
        angular_velocity=Vector3(x=float(rate[0]), y=float(rate[1]), z=float(rate[2])),
        pose_covariance=[0.0] * 36,
        velocity_covariance=[0.0] * 36 if cov is None else [float(v) for v in np.asarray(cov, float).ravel()],
        metadata=meta,
    )
