"""The hand CDR readers agree with rosbags' deserialiser field by field, and decline what they can't read."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from mapkit.ingest._fastcdr import parse_image, parse_odometry

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types


def header(sec: int, nanosec: int, frame: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame)


@pytest.mark.parametrize("frame,child", [("", ""), ("w", "b"), ("world", "base_link"), ("odom_frame_x", "c")])
def test_odometry_matches_rosbags(frame: str, child: str) -> None:
    rng = np.random.default_rng(len(frame) + len(child))
    p, q = rng.normal(size=3), rng.normal(size=4)
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    msg = T["nav_msgs/msg/Odometry"](
        header=header(1_700_000_000, 123_456_789, frame), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=rng.normal(size=36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=1, y=2, z=3),
                                               angular=T["geometry_msgs/msg/Vector3"](x=4, y=5, z=6)),
            covariance=np.zeros(36)),
    )
    raw = STORE.serialize_cdr(msg, "nav_msgs/msg/Odometry")
    stamp, f, c, t, quat = parse_odometry(raw)
    assert stamp == 1_700_000_000_123_456_789 and f == frame and c == child
    np.testing.assert_array_equal(t, p)
    np.testing.assert_array_equal(quat, q)
    assert parse_odometry(raw[:20]) is None  # truncated: fall back to rosbags (which reports it)


@pytest.mark.parametrize("frame,encoding,width", [("c", "16UC1", 3), ("camera_depth_optical_frame", "32FC1", 5), ("", "mono16", 1)])
def test_image_matches_rosbags(frame: str, encoding: str, width: int) -> None:
    data = np.arange(2 * width * 4, dtype=np.uint8)
    msg = T["sensor_msgs/msg/Image"](header=header(5, 6, frame), height=2, width=width, encoding=encoding,
                                     is_bigendian=1, step=width * 4, data=data)
    raw = STORE.serialize_cdr(msg, "sensor_msgs/msg/Image")
    ref = STORE.deserialize_cdr(raw, "sensor_msgs/msg/Image")
    fast = parse_image(raw)
    assert fast is not None
    assert (fast.header.stamp.sec, fast.header.stamp.nanosec, fast.header.frame_id) == (5, 6, frame)
    assert (fast.height, fast.width, fast.encoding, fast.is_bigendian, fast.step) == (
        ref.height, ref.width, ref.encoding, ref.is_bigendian, ref.step)
    np.testing.assert_array_equal(np.frombuffer(fast.data, np.uint8), ref.data)
    assert parse_image(b"\x00\x00\x00\x00" + raw[4:]) is None  # big-endian CDR: not handled here
