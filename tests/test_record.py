"""BagRecorder: every format opens in rosbags / mcap readers and round-trips the data."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from mapkit.bags import BagError, BagRecorder, output_path

STAMP = 1_700_000_000_123_456_789


def _depth() -> np.ndarray:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 9.0, size=(6, 7)).astype(np.float32)
    depth[0, 0] = np.nan
    depth[2, 3] = np.nan
    return depth


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [0.7, -0.2, 0.1]).as_matrix()
    T[:3, 3] = [1.5, -2.0, 3.25]
    return T


def _write_all(path: Path, fmt: str) -> Path:
    depth, T = _depth(), _pose()
    with BagRecorder(path, fmt) as rec:
        rec.write_depth("/d16", STAMP, depth, frame_id="cam")
        rec.write_depth("/d32", STAMP, depth, frame_id="cam", encoding="32FC1", row_padding=4, big_endian=True)
        rec.write_compressed_depth("/c16", STAMP, depth, frame_id="cam")
        rec.write_compressed_depth("/c32", STAMP, depth, frame_id="cam", encoding="32FC1")
        rec.write_camera_info("/info", STAMP, np.array([[387.0, 0, 3.0], [0, 387.0, 2.5], [0, 0, 1]]), 7, 6,
                              frame_id="cam")
        for i in range(3):
            rec.write_odometry("/odom", STAMP + i, T, frame_id="world", child_frame_id="base_link",
                               linear_velocity=[1.0, 0.0, 0.5], angular_velocity=[0, 0, 0.1])
        rec.write_tf(STAMP, [(T, "world", "base_link", STAMP)])
        rec.write_tf_static(STAMP, [(np.eye(4), "base_link", "camera_link")])
        rec.write_bytes("/broken", "sensor_msgs/msg/Image", b"\x00\x01", STAMP)
    return rec.path


def _read(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, stamp, raw in reader.messages():
            if conn.topic == "/broken":
                out.setdefault(conn.topic, []).append(raw)
                continue
            out.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.mark.parametrize("fmt", ["mcap", "ros2", "ros1"])
def test_round_trip(tmp_path: Path, fmt: str) -> None:
    path = _write_all(tmp_path / "rec", fmt)
    assert path == output_path(tmp_path / "rec", fmt)
    assert path.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporaries left behind
    msgs = _read(path)
    assert {k: len(v) for k, v in msgs.items()} == {
        "/d16": 1, "/d32": 1, "/c16": 1, "/c32": 1, "/info": 1, "/odom": 3, "/tf": 1, "/tf_static": 1,
        "/broken": 1,
    }
    depth = _depth()
    valid = np.isfinite(depth)

    stamp, img = msgs["/d16"][0]
    assert stamp == STAMP
    assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == STAMP
    assert img.encoding == "16UC1" and img.step == 14 and img.header.frame_id == "cam"
    mm = np.frombuffer(bytes(img.data), "<u2").reshape(6, 7)
    assert np.all(mm[~valid] == 0)
    np.testing.assert_array_equal(mm[valid], np.rint(depth[valid] * 1000))

    _, img = msgs["/d32"][0]
    assert img.is_bigendian == 1 and img.step == 7 * 4 + 4
    rows = np.frombuffer(bytes(img.data), np.uint8).reshape(6, img.step)[:, :28]
    d32 = rows.copy().view(">f4").reshape(6, 7)
    np.testing.assert_array_equal(np.isnan(d32), ~valid)
    np.testing.assert_array_equal(d32[valid], depth[valid])

    _, cimg = msgs["/c16"][0]
    assert cimg.format == "16UC1; compressedDepth png"
    data = bytes(cimg.data)
    assert struct.unpack("<iff", data[:12]) == (0, 0.0, 0.0)
    np.testing.assert_array_equal(np.array(Image.open(io.BytesIO(data[12:]))), mm)

    _, cimg = msgs["/c32"][0]
    assert cimg.format == "32FC1; compressedDepth png"
    data = bytes(cimg.data)
    fmt_id, A, B = struct.unpack("<iff", data[:12])
    assert fmt_id == 0 and A == pytest.approx(100 * 101) and B == pytest.approx(1 - 10100 / 10)
    value = np.array(Image.open(io.BytesIO(data[12:]))).astype(np.float64)
    assert np.all(value[~valid] == 0)
    decoded = A / (value[valid] - B)
    # Inverse-depth quantisation: the error grows with depth², about 1 cm at 9 m.
    np.testing.assert_allclose(decoded, depth[valid], atol=2e-3 * 9.0**2 / 9.0 + 1e-3)

    _, info = msgs["/info"][0]
    K = np.asarray(info.K if fmt == "ros1" else info.k).reshape(3, 3)
    assert K[0, 0] == 387.0 and K[1, 2] == 2.5 and info.width == 7 and info.height == 6
    assert info.distortion_model == "plumb_bob"

    T = _pose()
    stamps = [s for s, _ in msgs["/odom"]]
    assert stamps == [STAMP, STAMP + 1, STAMP + 2]
    _, odom = msgs["/odom"][0]
    assert odom.header.frame_id == "world" and odom.child_frame_id == "base_link"
    p, q = odom.pose.pose.position, odom.pose.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], T[:3, 3], atol=0)
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    assert odom.twist.twist.linear.z == 0.5 and odom.twist.twist.angular.z == 0.1

    _, tf = msgs["/tf"][0]
    tr = tf.transforms[0]
    assert tr.header.frame_id == "world" and tr.child_frame_id == "base_link"
    assert tr.transform.translation.z == 3.25
    _, tfs = msgs["/tf_static"][0]
    assert tfs.transforms[0].child_frame_id == "camera_link"
    assert msgs["/broken"][0] == b"\x00\x01"


def test_bare_mcap_opens_in_mcap_reader(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    path = _write_all(tmp_path / "rec.mcap", "mcap")
    assert path.name == "rec.mcap"
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {ch.topic: ch for ch in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        assert counts[topics["/odom"].id] == 3
        assert all(ch.message_encoding == "cdr" for ch in topics.values())
        assert "durability: 1" in topics["/tf_static"].metadata["offered_qos_profiles"]  # transient local
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}


def test_existing_output_and_failure_leave_no_partial(tmp_path: Path) -> None:
    path = _write_all(tmp_path / "rec", "mcap")
    before = path.read_bytes()
    with pytest.raises(BagError, match="exists"):
        BagRecorder(tmp_path / "rec", "mcap")
    with pytest.raises(RuntimeError), BagRecorder(tmp_path / "rec", "mcap", overwrite=True) as rec:
        rec.write_depth("/d", STAMP, _depth(), frame_id="cam")
        raise RuntimeError("boom")
    assert path.read_bytes() == before  # the old output survives a failed overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap"]
    with pytest.raises(RuntimeError), BagRecorder(tmp_path / "other", "ros2") as rec:
        rec.write_depth("/d", STAMP, _depth(), frame_id="cam")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap"]


def test_bad_inputs(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="unknown bag format"):
        BagRecorder(tmp_path / "x", "rosbag3")
    with BagRecorder(tmp_path / "x", "mcap") as rec:
        with pytest.raises(BagError, match="encoding"):
            rec.write_depth("/d", STAMP, _depth(), frame_id="cam", encoding="8UC1")
        with pytest.raises(BagError, match="shape"):
            rec.write_depth("/d", STAMP, np.zeros(5, np.float32), frame_id="cam")
