"""BagRecorder: numpy depth images and 4x4 poses → the ROS messages a drone publishes, in a bare MCAP
(the ``mcap`` package, ROS2 CDR, zstd chunks), a rosbag2 directory or a ROS1 bag (rosbags' writers).
Output is atomic: written under a hidden temporary name, renamed into place only on a clean exit.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import struct
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mapkit.errors import MapkitError
from mapkit.geometry import quat_xyzw_from_matrix

BagFormat = Literal["mcap", "ros2", "ros1"]
FORMATS: tuple[str, ...] = ("mcap", "ros2", "ros1")
DEPTH_ENCODINGS: tuple[str, ...] = ("16UC1", "mono16", "32FC1")

# compressed_depth_image_transport::compressionFormat; INV_DEPTH is the only defined value.
_INV_DEPTH = 0
_TF_TOPIC = "/tf"
_TF_STATIC_TOPIC = "/tf_static"


class BagError(MapkitError):
    """A bad recorder input (format, output path, depth image, transform, ...), naming the value and the fix."""


def output_path(path: str | os.PathLike[str], format: str) -> Path:
    """The path a recording of ``format`` gets for a user-given ``path`` (suffix optional): mcap →
    ``OUT.mcap`` (a single file), ros1 → ``OUT.bag``, ros2 → ``OUT/`` (a directory)."""
    if format not in FORMATS:
        raise BagError(f"unknown bag format {format!r}; use one of {', '.join(FORMATS)}")
    p = Path(path)
    if p.suffix in (".mcap", ".bag", ".db3"):
        p = p.with_suffix("")
    return p if format == "ros2" else p.with_name(p.name + {"mcap": ".mcap", "ros1": ".bag"}[format])


class BagRecorder:
    """Context manager writing ROS messages to a bare MCAP file, a rosbag2 directory or a ROS1 bag.

    Args:
        path: output path, with or without suffix (see :func:`output_path`).
        format: ``"mcap"`` (bare ``.mcap``, ROS2 CDR), ``"ros2"`` (rosbag2 dir, sqlite3 ``.db3``)
            or ``"ros1"`` (``.bag``).
        compression: zstd chunks (mcap), LZ4 chunks (ros1); ros2/sqlite3 stays uncompressed
            because that is what ``ros2 bag record`` writes by default.
        overwrite: replace an existing output (only once the new one is complete).

    Attributes:
        path: the final output path.
        typestore: the rosbags typestore (ROS1 Noetic or ROS2 Humble) to build messages with.
        counts: messages written per topic (also the next ROS1 header ``seq`` and MCAP ``sequence``).
    """

    def __init__(self, path: str | os.PathLike[str], format: str = "mcap", *, compression: bool = True,
                 overwrite: bool = False) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.format = format
        self.path = output_path(path, format)
        self.compression = compression
        self.overwrite = overwrite
        if self.path.exists() and not overwrite:
            raise BagError(f"output {self.path} exists; pass overwrite=True (--overwrite) or choose another path")
        if not self.path.parent.is_dir():
            raise BagError(f"output directory {self.path.parent} does not exist; create it first")
        self.is_ros1 = format == "ros1"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.is_ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.typestore.types:
            # rosbags' Noetic store lacks tf2_msgs; its definition is one line.
            from rosbags.typesys import get_types_from_msg

            self.typestore.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                       "tf2_msgs/msg/TFMessage"))
        self.counts: dict[str, int] = {}
        self._connections: dict[tuple[str, str], Any] = {}
        self._tmpdir: Path | None = None
        self._writer: Any = None
        self._file: Any = None

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> BagRecorder:
        self.open()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def open(self) -> None:
        """Start writing under a temporary name next to the final path."""
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent))
        tmp_out = self._tmpdir / self.path.name
        if self.format == "mcap":
            from mcap.writer import CompressionType
            from mcap.writer import Writer as McapWriter

            self._file = open(tmp_out, "wb")  # noqa: SIM115 - held open across calls, closed by close()/abort()
            compression = CompressionType.ZSTD if self.compression else CompressionType.NONE
            self._writer = McapWriter(self._file, compression=compression)
            from mapkit import __version__

            self._writer.start(profile="ros2", library=f"mapkit-{__version__}")
            self._schemas: dict[str, int] = {}
        elif self.format == "ros2":
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Rosbag2Writer

            self._writer = Rosbag2Writer(tmp_out, version=8, storage_plugin=StoragePlugin.SQLITE3)
            self._writer.open()
        else:
            from rosbags.rosbag1 import Writer as Rosbag1Writer

            self._writer = Rosbag1Writer(tmp_out)
            if self.compression:
                self._writer.set_compression(Rosbag1Writer.CompressionFormat.LZ4)
            self._writer.open()

    def close(self) -> None:
        """Finish the file and move it to its final path (replacing an old one if overwrite)."""
        if self._writer is None:
            return
        if self.format == "mcap":
            self._writer.finish()
            self._file.close()
        else:
            self._writer.close()
        self._writer = None
        assert self._tmpdir is not None
        tmp_out = self._tmpdir / self.path.name
        if self.path.exists():
            if not self.overwrite:
                self.abort()
                raise BagError(f"output {self.path} appeared while writing; pass --overwrite or choose another path")
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        os.replace(tmp_out, self.path)
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        self._tmpdir = None

    def abort(self) -> None:
        """Drop everything written so far; the final path is left untouched."""
        try:
            if self._writer is not None:
                if self.format == "mcap":
                    self._file.close()
                else:
                    with contextlib.suppress(Exception):  # the partial output is deleted anyway
                        self._writer.close()
        finally:
            self._writer = None
            if self._tmpdir is not None:
                shutil.rmtree(self._tmpdir, ignore_errors=True)
                self._tmpdir = None

    # ------------------------------------------------------------------ low level
    def _connection(self, topic: str, msgtype: str) -> Any:
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is not None:
            return conn
        if self._writer is None:
            raise BagError("BagRecorder is not open; use it as a context manager (with BagRecorder(...) as rec:)")
        latched = topic == _TF_STATIC_TOPIC
        if self.format == "mcap":
            if msgtype not in self._schemas:
                msgdef, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
                self._schemas[msgtype] = self._writer.register_schema(name=msgtype, encoding="ros2msg",
                                                                      data=msgdef.encode())
            conn = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=self._schemas[msgtype],
                                                 metadata={"offered_qos_profiles": _qos_yaml(latched)})
        elif self.format == "ros2":
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                               offered_qos_profiles=_qos_profiles(latched))
        else:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore, callerid="/mapkit_sim",
                                               latching=1 if latched else None)
        self._connections[key] = conn
        return conn

    def write_bytes(self, topic: str, msgtype: str, data: bytes, stamp_ns: int) -> None:
        """Write already-serialised bytes (CDR for mcap/ros2, ROS1 for ros1) as one message (tests craft
        broken messages with it); ``msgtype`` like ``sensor_msgs/msg/Image``."""
        conn = self._connection(topic, msgtype)
        stamp_ns = int(stamp_ns)
        if self.format == "mcap":
            self._writer.add_message(channel_id=conn, log_time=stamp_ns, publish_time=stamp_ns, data=bytes(data),
                                     sequence=self.counts.get(topic, 0))
        else:
            self._writer.write(conn, stamp_ns, bytes(data))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_raw(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        """Serialise a message object built from ``self.typestore`` and write it."""
        serialize = self.typestore.serialize_ros1 if self.is_ros1 else self.typestore.serialize_cdr
        data = serialize(msg, msgtype)
        self.write_bytes(topic, msgtype, bytes(data), stamp_ns)

    # ------------------------------------------------------------------ message builders
    def _type(self, name: str) -> Any:
        return self.typestore.types[name]

    def header(self, stamp_ns: int, frame_id: str, *, topic: str | None = None) -> Any:
        """A std_msgs/Header for ``stamp_ns`` (ROS1 headers get a per-topic ``seq``)."""
        stamp_ns = int(stamp_ns)
        Time = self._type("builtin_interfaces/msg/Time")
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        Header = self._type("std_msgs/msg/Header")
        if self.is_ros1:
            return Header(seq=self.counts.get(topic or "", 0), stamp=stamp, frame_id=frame_id)
        return Header(stamp=stamp, frame_id=frame_id)

    def pose_message(self, T: np.ndarray) -> Any:
        """geometry_msgs/Pose of a 4x4 transform (for building messages such as nav_msgs/Path)."""
        return self._rigid(T, "geometry_msgs/msg/Pose", "geometry_msgs/msg/Point", "position", "orientation")

    def _transform(self, T: np.ndarray) -> Any:
        return self._rigid(T, "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "translation", "rotation")

    def _rigid(self, T: np.ndarray, msgtype: str, point_type: str, point: str, rotation: str) -> Any:
        """A Pose or Transform message of a 4x4 transform."""
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise BagError(f"transform must be a 4x4 matrix, got shape {T.shape}")
        q = quat_xyzw_from_matrix(T[:3, :3])
        xyz = self._type(point_type)(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3]))
        rot = self._type("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
        return self._type(msgtype)(**{point: xyz, rotation: rot})

    def _vector3(self, v: Sequence[float] | np.ndarray | None) -> Any:
        Vector3 = self._type("geometry_msgs/msg/Vector3")
        v = np.zeros(3) if v is None else np.asarray(v, dtype=np.float64).reshape(3)
        return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    # ------------------------------------------------------------------ public writers
    def write_depth(self, topic: str, stamp_ns: int, depth_m: np.ndarray, *, frame_id: str, encoding: str = "16UC1",
                    row_padding: int = 0, big_endian: bool = False) -> None:
        """Write a depth image as sensor_msgs/Image.

        Args:
            depth_m: float32 (H, W) metres along optical z, NaN invalid.
            encoding: ``16UC1``/``mono16`` (millimetres, 0 invalid, values beyond 65.535 m
                invalid) or ``32FC1`` (metres, NaN invalid).
            row_padding: extra zero bytes after each row (``step = W * bpp + row_padding``).
            big_endian: store the pixels big-endian and set ``is_bigendian``.
        """
        depth = _check_depth(depth_m)
        if encoding in ("16UC1", "mono16"):
            pix = depth_to_mm(depth)
        elif encoding == "32FC1":
            pix = depth.astype(np.float32)
        else:
            raise BagError(f"unknown depth encoding {encoding!r}; use one of {', '.join(DEPTH_ENCODINGS)}")
        if row_padding < 0:
            raise BagError(f"row_padding must be >= 0 bytes, got {row_padding}")
        height, width = pix.shape
        pix = pix.astype(pix.dtype.newbyteorder(">" if big_endian else "<"))
        rows = pix.view(np.uint8).reshape(height, width * pix.itemsize)
        if row_padding:
            rows = np.concatenate([rows, np.zeros((height, row_padding), np.uint8)], axis=1)
        Image = self._type("sensor_msgs/msg/Image")
        msg = Image(header=self.header(stamp_ns, frame_id, topic=topic), height=height, width=width, encoding=encoding,
                    is_bigendian=int(big_endian), step=width * pix.itemsize + row_padding,
                    data=np.ascontiguousarray(rows).reshape(-1))
        self.write_raw(topic, "sensor_msgs/msg/Image", msg, stamp_ns)

    def write_compressed_depth(self, topic: str, stamp_ns: int, depth_m: np.ndarray, *, frame_id: str,
                               encoding: str = "16UC1") -> None:
        """Write sensor_msgs/CompressedImage in compressed_depth_image_transport's PNG format.

        ``data`` = 12-byte header (int32 format = 0 INV_DEPTH, float32 depthParam[2], little
        endian) + a 16-bit PNG. ``16UC1``: PNG of millimetres (0 invalid), params zero.
        ``32FC1``: inverse depth, ``A = q(q+1)``, ``B = 1 - A/depth_max`` (the transport's defaults
        q = 100, depth_max = 10 m), stored ``A/depth + B`` (0 invalid or beyond ``depth_max``); decode
        ``depth = A/(value - B)``.
        """
        depth = _check_depth(depth_m)
        if encoding == "16UC1":
            pix = depth_to_mm(depth)
            params = (0.0, 0.0)
        elif encoding == "32FC1":
            pix, params = encode_inverse_depth(depth)
        else:
            raise BagError(f"unknown compressedDepth encoding {encoding!r}; use 16UC1 or 32FC1")
        header = struct.pack("<iff", _INV_DEPTH, float(params[0]), float(params[1]))
        CompressedImage = self._type("sensor_msgs/msg/CompressedImage")
        payload = header + png_uint16(pix)
        msg = CompressedImage(header=self.header(stamp_ns, frame_id, topic=topic),
                              format=f"{encoding}; compressedDepth png", data=np.frombuffer(payload, dtype=np.uint8))
        self.write_raw(topic, "sensor_msgs/msg/CompressedImage", msg, stamp_ns)

    def write_camera_info(self, topic: str, stamp_ns: int, K: np.ndarray, width: int, height: int, *,
                          frame_id: str) -> None:
        """Write sensor_msgs/CameraInfo: plumb_bob, distortion zeros, R = I, P = [K|0]."""
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        D = np.zeros(5)
        P = np.zeros((3, 4))
        P[:, :3] = K
        CameraInfo = self._type("sensor_msgs/msg/CameraInfo")
        RegionOfInterest = self._type("sensor_msgs/msg/RegionOfInterest")
        fields = {"d": D, "k": K.reshape(-1), "r": np.eye(3).reshape(-1), "p": P.reshape(-1)}
        if self.is_ros1:  # ROS1 spells the matrices in capitals
            fields = {name.upper(): value for name, value in fields.items()}
        roi = RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = CameraInfo(header=self.header(stamp_ns, frame_id, topic=topic), height=int(height), width=int(width),
                         distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **fields)
        self.write_raw(topic, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)

    def write_odometry(self, topic: str, stamp_ns: int, T_parent_child: np.ndarray, *, frame_id: str,
                       child_frame_id: str, linear_velocity: Sequence[float] | np.ndarray | None = None,
                       angular_velocity: Sequence[float] | np.ndarray | None = None) -> None:
        """Write nav_msgs/Odometry; velocities are in the child (body) frame, as REP 105 says."""
        Odometry = self._type("nav_msgs/msg/Odometry")
        PoseWithCovariance = self._type("geometry_msgs/msg/PoseWithCovariance")
        TwistWithCovariance = self._type("geometry_msgs/msg/TwistWithCovariance")
        Twist = self._type("geometry_msgs/msg/Twist")
        twist = Twist(linear=self._vector3(linear_velocity), angular=self._vector3(angular_velocity))
        msg = Odometry(header=self.header(stamp_ns, frame_id, topic=topic), child_frame_id=child_frame_id,
                       pose=PoseWithCovariance(pose=self.pose_message(T_parent_child), covariance=np.zeros(36)),
                       twist=TwistWithCovariance(twist=twist, covariance=np.zeros(36)))
        self.write_raw(topic, "nav_msgs/msg/Odometry", msg, stamp_ns)

    def _tf_message(self, transforms: Sequence[tuple[Any, ...]], stamp_ns: int, topic: str) -> Any:
        TransformStamped = self._type("geometry_msgs/msg/TransformStamped")
        TFMessage = self._type("tf2_msgs/msg/TFMessage")
        items = []
        for T, parent, child, *stamp in transforms:
            items.append(TransformStamped(header=self.header(stamp[0] if stamp else stamp_ns, parent, topic=topic),
                                          child_frame_id=child, transform=self._transform(T)))
        return TFMessage(transforms=items)

    def write_tf(self, stamp_ns: int, transforms: Sequence[tuple[Any, ...]], *, topic: str = _TF_TOPIC) -> None:
        """Write tf2_msgs/TFMessage on /tf: ``(T_parent_child, parent, child[, stamp_ns])`` tuples (without a
        stamp, the message's)."""
        self.write_raw(topic, "tf2_msgs/msg/TFMessage", self._tf_message(transforms, stamp_ns, topic), stamp_ns)

    def write_tf_static(self, stamp_ns: int, transforms: Sequence[tuple[Any, ...]]) -> None:
        """Write tf2_msgs/TFMessage on /tf_static (latched in ROS1, transient-local QoS in ROS2)."""
        self.write_tf(stamp_ns, transforms, topic=_TF_STATIC_TOPIC)


# ---------------------------------------------------------------------- helpers
def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """float32 metres (NaN invalid) → uint16 millimetres (0 invalid; <=0 or > 65.535 m invalid)."""
    with np.errstate(invalid="ignore"):
        mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
        ok = np.isfinite(mm) & (mm > 0) & (mm <= 65535)
    return np.where(ok, mm, 0).astype(np.uint16)


def encode_inverse_depth(depth_m: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """compressed_depth_image_transport's 32FC1 inverse-depth quantisation (its defaults: q = 100,
    depth_max = 10 m) → (uint16, (A, B)), in float32 as the transport computes, so decoding round-trips."""
    A32, B32 = np.float32(100.0 * 101.0), np.float32(1.0 - 100.0 * 101.0 / 10.0)
    d = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        value = A32 / d + B32
        ok = np.isfinite(d) & (d > 0) & (d < 10.0) & (value >= 0.5) & (value <= 65535)
    return np.where(ok, np.rint(value), 0).astype(np.uint16), (float(A32), float(B32))


def png_uint16(pix: np.ndarray) -> bytes:
    """16-bit greyscale PNG bytes of a uint16 image (Pillow mode ``I;16``)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pix, dtype=np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def _check_depth(depth_m: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth_m)
    if depth.ndim != 2 or depth.size == 0:
        raise BagError(f"depth image must be a non-empty (H, W) array, got shape {depth.shape}")
    return depth


def _qos_profiles(latched: bool) -> list[Any]:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    durability = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
    return [Qos(history=QosHistory.KEEP_LAST, depth=1 if latched else 10, reliability=QosReliability.RELIABLE,
                durability=durability, deadline=zero, lifespan=zero, liveliness=QosLiveliness.AUTOMATIC,
                liveliness_lease_duration=zero, avoid_ros_namespace_conventions=False)]


def _qos_yaml(latched: bool) -> str:
    """The ``offered_qos_profiles`` channel metadata rosbag2's MCAP storage writes (Humble style)."""
    from rosbags.rosbag2.metadata import dump_qos_v8

    return dump_qos_v8(_qos_profiles(latched))
