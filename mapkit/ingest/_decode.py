"""Depth images, camera info and pose messages → numpy, following REP 118 for depth."""

from __future__ import annotations

import io
import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit.geometry import transform_from_pose
from mapkit.ingest._errors import IngestError

DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
READABLE_ENCODINGS = (*DEPTH_ENCODINGS, "compressedDepth")
ACCEPTED = "16UC1, mono16, 32FC1 or compressedDepth"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped")
TF_TYPE = "tf2_msgs/msg/TFMessage"


def stamp_ns(header: Any) -> int:
    """Header stamp in integer nanoseconds (ROS1 `secs/nsecs` and ROS2 `sec/nanosec` alike)."""
    s = header.stamp
    return int(s.sec) * 1_000_000_000 + int(s.nanosec)


def frame_name(frame_id: str) -> str:
    """ROS1 frame ids may carry a leading slash; tf2 does not."""
    return frame_id.strip().lstrip("/")


def image_encoding(msg: Any, msgtype: str) -> str:
    """The depth encoding of an Image or CompressedImage ('compressedDepth' for the latter)."""
    if msgtype.endswith("CompressedImage"):
        return "compressedDepth" if "compresseddepth" in msg.format.lower() else msg.format
    return msg.encoding


def decode_depth(msg: Any, msgtype: str, *, topic: str) -> NDArray[np.float32]:
    """Depth in metres (float32, NaN invalid) from an Image or compressedDepth CompressedImage."""
    if msgtype.endswith("CompressedImage"):
        return _decode_compressed_depth(msg, topic=topic)
    enc = msg.encoding
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height == 0 or width == 0:
        raise IngestError(f"topic {topic} has a {width}x{height} image at stamp {stamp_ns(msg.header)} ns; "
                          "a depth image needs pixels (check the camera driver)")
    if enc in ("16UC1", "mono16"):
        bpp, kind = 2, "u2"
    elif enc == "32FC1":
        bpp, kind = 4, "f4"
    else:
        raise IngestError(f"topic {topic} has encoding {enc}; expected {ACCEPTED}; pass --depth-topic")
    data = msg.data
    if step < width * bpp or len(data) < step * (height - 1) + width * bpp:
        raise IngestError(f"topic {topic}: image at stamp {stamp_ns(msg.header)} ns has {len(data)} bytes for "
                          f"{width}x{height} {enc} with step {step}; the message is corrupted")
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    # A strided view honours row padding (step > width * bpp) without copying.
    raw = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(step, bpp))
    if kind == "u2":
        return _from_millimetres(raw)
    depth = raw.astype(np.float32)
    depth[~(depth > 0) | ~np.isfinite(depth)] = np.nan  # NaN, 0, inf and negatives: invalid
    return depth


def _from_millimetres(mm: NDArray[Any]) -> NDArray[np.float32]:
    """16-bit millimetres (0 invalid) → float32 metres (NaN invalid)."""
    depth = mm.astype(np.float32)
    depth *= np.float32(0.001)
    depth[mm == 0] = np.nan
    return depth


def _decode_compressed_depth(msg: Any, *, topic: str) -> NDArray[np.float32]:
    """compressed_depth_image_transport: 12-byte config header, then a 16-bit PNG."""
    from PIL import Image

    fmt = msg.format
    enc = fmt.split(";")[0].strip()
    data = bytes(msg.data)
    if len(data) < 12 + 8:
        raise IngestError(f"topic {topic}: compressedDepth message of {len(data)} bytes is too short; corrupted")
    _, quant_a, quant_b = struct.unpack("<iff", data[:12])
    try:
        png = Image.open(io.BytesIO(data[12:]))
        png.load()
    except Exception as exc:  # noqa: BLE001 - Pillow raises many kinds for a broken PNG
        raise IngestError(f"topic {topic}: compressedDepth PNG does not decode ({exc}); corrupted message") from None
    if not png.mode.startswith("I"):  # 8-bit grey or colour would read as millimetres silently
        raise IngestError(f"topic {topic}: compressedDepth PNG is mode {png.mode}, not a 16-bit greyscale image; "
                          "corrupted message or not a depth stream")
    q = np.asarray(png)
    if q.ndim != 2 or q.size == 0:
        raise IngestError(f"topic {topic}: compressedDepth PNG has shape {q.shape}; expected a 2-D 16-bit image")
    q = q.astype(np.uint16, copy=False)
    if enc in ("16UC1", "mono16"):
        return _from_millimetres(q)
    if enc == "32FC1":
        # Quantised inverse depth: stored = A / depth + B, so depth = A / (stored - B); 0 = invalid.
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (np.float32(quant_a) / (q.astype(np.float32) - np.float32(quant_b))).astype(np.float32)
        depth[(q == 0) | ~(depth > 0)] = np.nan
        return depth
    raise IngestError(f"topic {topic} has compressedDepth format {fmt!r}; expected 16UC1 or 32FC1 inside")


def camera_intrinsics(msg: Any, *, topic: str) -> tuple[NDArray[np.float64], int, int]:
    """(K 3x3, width, height) from a CameraInfo (ROS1 field K, ROS2 field k)."""
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.all(np.isfinite(K)):
        raise IngestError(f"topic {topic} has camera matrix K={K.ravel().tolist()} with no focal length; "
                          "the camera is uncalibrated: pass --intrinsics fx,fy,cx,cy")
    return K, int(msg.width), int(msg.height)


def pose_sample(msg: Any, msgtype: str) -> tuple[int, str, str | None, NDArray[np.float64], NDArray[np.float64]]:
    """(stamp ns, parent frame, child frame or None, translation, quaternion xyzw) of a pose message."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return _transform_sample(msg)
    if msgtype == "nav_msgs/msg/Odometry":
        pose, child = msg.pose.pose, frame_name(msg.child_frame_id) or None
    elif msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        pose, child = msg.pose.pose, None
    else:
        pose, child = msg.pose, None
    p, q = pose.position, pose.orientation
    return (stamp_ns(msg.header), frame_name(msg.header.frame_id), child, np.array([p.x, p.y, p.z], dtype=np.float64),
            np.array([q.x, q.y, q.z, q.w], dtype=np.float64))


def _transform_sample(tr: Any) -> tuple[int, str, str, NDArray[np.float64], NDArray[np.float64]]:
    """(stamp, parent, child, translation, quaternion xyzw) of a geometry_msgs/TransformStamped."""
    t, r = tr.transform.translation, tr.transform.rotation
    return (stamp_ns(tr.header), frame_name(tr.header.frame_id), frame_name(tr.child_frame_id),
            np.array([t.x, t.y, t.z], dtype=np.float64), np.array([r.x, r.y, r.z, r.w], dtype=np.float64))


def tf_samples(msg: Any) -> list[tuple[int, str, str, NDArray[np.float64], NDArray[np.float64]]]:
    """Every transform of a TFMessage as (stamp, parent, child, translation, quaternion xyzw)."""
    return [_transform_sample(tr) for tr in msg.transforms]


def parse_intrinsics(text: str) -> NDArray[np.float64]:
    """K from 'fx,fy,cx,cy'."""
    try:
        fx, fy, cx, cy = (float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise IngestError(f"--intrinsics {text!r} is not four numbers fx,fy,cx,cy (e.g. 387.2,387.2,319.5,239.5)") from None
    if not (fx > 0 and fy > 0):
        raise IngestError(f"--intrinsics {text!r}: focal lengths must be positive")
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


def parse_extrinsic(text: str) -> NDArray[np.float64]:
    """T_body_camera from 'x,y,z,qx,qy,qz,qw' or 'identity'."""
    if text.strip().lower() == "identity":
        return np.eye(4)
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) != 7 or not np.all(np.isfinite(vals)) or np.linalg.norm(vals[3:]) < 1e-6:
        raise IngestError(f"extrinsic {text!r} is not x,y,z,qx,qy,qz,qw (T_body_camera, camera optical frame) "
                          "with a non-zero quaternion, nor 'identity'")
    return transform_from_pose(vals[:3], vals[3:])
