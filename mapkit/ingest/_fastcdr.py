"""Direct reads of the two hot ROS2 message types (sensor_msgs/Image, nav_msgs/Odometry) from CDR,
faster than rosbags' generic deserialiser (about 70 µs per Odometry). Anything unexpected (big-endian
encapsulation, a truncated buffer) returns None: the caller falls back to rosbags, which reports errors.
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_7D = struct.Struct("<7d")


class _Stamp(NamedTuple):
    sec: int
    nanosec: int


class _Header(NamedTuple):
    stamp: _Stamp
    frame_id: str


class Image(NamedTuple):
    """The fields of sensor_msgs/Image that depth decoding reads."""

    header: _Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview


def _align(pos: int, n: int) -> int:
    # CDR aligns to the type size, counted from the end of the 4-byte encapsulation header.
    return 4 + (-(-(pos - 4) // n)) * n


def _string(buf: Any, pos: int) -> tuple[str, int]:
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(buf, pos)
    text = bytes(buf[pos + 4 : pos + 4 + n - 1]).decode() if n else ""
    return text, pos + 4 + n


def _header(buf: Any) -> tuple[_Header, int]:
    sec, nanosec = _STAMP.unpack_from(buf, 4)
    frame_id, pos = _string(buf, 12)
    return _Header(_Stamp(sec, nanosec), frame_id), pos


def _little_endian_cdr(buf: Any) -> bool:
    return len(buf) >= 12 and buf[0] == 0 and buf[1] == 1


def parse_image(buf: Any) -> Image | None:
    """sensor_msgs/Image from little-endian CDR, the pixel data as a view (no copy)."""
    if not _little_endian_cdr(buf):
        return None
    try:
        header, pos = _header(buf)
        pos = _align(pos, 4)
        height, width = struct.unpack_from("<II", buf, pos)
        encoding, pos = _string(buf, pos + 8)
        is_bigendian = buf[pos]
        pos = _align(pos + 1, 4)
        step, n = struct.unpack_from("<II", buf, pos)
        data = memoryview(buf)[pos + 8 : pos + 8 + n]
    except (struct.error, UnicodeDecodeError, IndexError):
        return None
    if len(data) != n:
        return None
    return Image(header, height, width, encoding, is_bigendian, step, data)


def parse_odometry(buf: Any) -> tuple[int, str, str, NDArray[np.float64], NDArray[np.float64]] | None:
    """(stamp ns, frame_id, child_frame_id, position, quaternion xyzw) of a nav_msgs/Odometry."""
    if not _little_endian_cdr(buf):
        return None
    try:
        header, pos = _header(buf)
        child, pos = _string(buf, pos)
        values = _7D.unpack_from(buf, _align(pos, 8))
    except (struct.error, UnicodeDecodeError, IndexError):
        return None
    stamp = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
    return stamp, header.frame_id, child, np.array(values[:3]), np.array(values[3:])
