"""Property-based fuzzing of the message decoders: random and mutated bytes of CDR Image and
Odometry messages, compressedDepth headers and PNG payloads never raise anything but mapkit's own
IngestError (or give up cleanly: the fast CDR parsers return None to fall back to rosbags)."""

from __future__ import annotations

import io
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image as PILImage
from rosbags.typesys import Stores, get_typestore

from mapkit.ingest import IngestError
from mapkit.ingest._decode import decode_depth
from mapkit.ingest._fastcdr import parse_image, parse_odometry

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
STORE = get_typestore(Stores.ROS2_HUMBLE)


def _header():
    Header = STORE.types["std_msgs/msg/Header"]
    Time = STORE.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=1_700_000_000, nanosec=5), frame_id="camera")


def _image_cdr(encoding: str = "16UC1", width: int = 6, height: int = 4) -> bytes:
    Image = STORE.types["sensor_msgs/msg/Image"]
    bpp = 2 if encoding == "16UC1" else 4
    data = np.arange(width * height * bpp, dtype=np.uint8)
    msg = Image(header=_header(), height=height, width=width, encoding=encoding, is_bigendian=0,
                step=width * bpp, data=data)
    return bytes(STORE.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def _odometry_cdr() -> bytes:
    T = STORE.types
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    msg = T["nav_msgs/msg/Odometry"](
        header=_header(), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                               angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)))
    return bytes(STORE.serialize_cdr(msg, "nav_msgs/msg/Odometry"))


@st.composite
def _mutations(draw: st.DrawFn, seed: bytes) -> bytes:
    """``seed`` with random bytes overwritten, inserted, or cut off."""
    buf = bytearray(seed)
    for _ in range(draw(st.integers(1, 8))):
        how = draw(st.sampled_from(["flip", "insert", "cut"]))
        at = draw(st.integers(0, max(len(buf) - 1, 0)))
        if how == "flip" and buf:
            buf[at] = draw(st.integers(0, 255))
        elif how == "insert":
            buf[at:at] = draw(st.binary(min_size=1, max_size=8))
        else:
            del buf[at:]
    return bytes(buf)


def _decode_image_bytes(buf: bytes) -> None:
    img = parse_image(buf)
    if img is not None:
        try:
            depth = decode_depth(img, "sensor_msgs/msg/Image", topic="/depth")
        except IngestError:
            return
        assert depth.dtype == np.float32 and depth.shape == (img.height, img.width)
        assert not (depth <= 0).any()  # invalid is NaN, never a number


@FUZZ
@given(st.binary(max_size=256))
def test_random_bytes_as_an_image(buf: bytes) -> None:
    _decode_image_bytes(buf)


@FUZZ
@given(st.data(), st.sampled_from(["16UC1", "32FC1"]))
def test_mutated_images(data: st.DataObject, encoding: str) -> None:
    _decode_image_bytes(data.draw(_mutations(_image_cdr(encoding))))


@FUZZ
@given(st.one_of(st.binary(max_size=512), _mutations(_odometry_cdr())))
def test_odometry_bytes_parse_or_fall_back(buf: bytes) -> None:
    out = parse_odometry(buf)
    if out is not None:
        stamp, parent, _, t, q = out
        assert isinstance(stamp, int) and isinstance(parent, str) and t.shape == (3,) and q.shape == (4,)


def _png(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    PILImage.fromarray(array).save(out, format="PNG")
    return out.getvalue()


def _compressed(fmt: str, payload: bytes, quant=(0, 1000.0, 0.0)) -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=np.frombuffer(struct.pack("<iff", *quant) + payload, dtype=np.uint8),
                           header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0)))


def _decode_compressed(msg: SimpleNamespace) -> None:
    try:
        depth = decode_depth(msg, "sensor_msgs/msg/CompressedImage", topic="/depth/compressedDepth")
    except IngestError:
        return
    assert depth.dtype == np.float32 and depth.ndim == 2 and not (depth <= 0).any()


GOOD_PNG = _png(np.arange(48, dtype=np.uint16).reshape(6, 8) * 100)


@FUZZ
@given(st.text(max_size=40), st.binary(max_size=128),
       st.tuples(st.integers(-2**31, 2**31 - 1), st.floats(width=32), st.floats(width=32)))
def test_random_compressed_depth(fmt: str, payload: bytes, quant) -> None:
    _decode_compressed(_compressed(fmt, payload, quant))


@FUZZ
@given(st.data(), st.sampled_from(["16UC1; compressedDepth", "32FC1; compressedDepth png"]))
def test_mutated_png_payloads(data: st.DataObject, fmt: str) -> None:
    _decode_compressed(_compressed(fmt, data.draw(_mutations(GOOD_PNG))))


@pytest.mark.parametrize("array", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 3), np.uint8)],
                         ids=["8-bit grey", "rgb"])
def test_a_png_that_is_not_16_bit_is_refused(array: np.ndarray) -> None:
    with pytest.raises(IngestError, match="16-bit"):
        decode_depth(_compressed("16UC1; compressedDepth", _png(array)), "sensor_msgs/msg/CompressedImage", topic="/d")
