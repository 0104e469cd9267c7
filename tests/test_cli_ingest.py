"""`mapkit info` / `mapkit ingest` as users run them, including every bad input of the issue."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from recordings import T0, write_recording

from mapkit import __version__
from mapkit.bags import BagRecorder
from mapkit.cli.main import main


def run(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result.exit_code, result.output


def assert_one_line_error(code: int, out: str, *needles: str, usage: bool = False) -> None:
    """One ``error:`` line naming ``needles``; exit 2 for a usage error (a value the options alone rule out), else 1."""
    assert code == (2 if usage else 1), out
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in out, out
    for needle in needles:
        assert needle in errors[0], errors[0]


def test_version_and_help() -> None:
    code, out = run("--version")
    assert code == 0 and __version__ in out
    for cmd in ("info", "ingest"):
        code, out = run(cmd, "--help")
        assert code == 0 and "--depth-topic" in out


def test_info_lists_topics_and_roles(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "ros1", n=5)
    code, out = run("info", rec.path)
    assert code == 0, out
    assert "/camera/depth/image_rect_raw" in out and "nav_msgs/msg/Odometry" in out
    assert "would use" in out and "16UC1" in out and "world=world body=base_link" in out


def test_ingest_then_existing_output(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=5)
    ws = tmp_path / "ws"
    code, out = run("ingest", rec.path, "-w", ws)
    assert code == 0 and "5 frames" in out, out
    code, out = run("ingest", rec.path, "-w", ws)
    assert_one_line_error(code, out, "already exists", "--overwrite")
    code, out = run("ingest", rec.path, "-w", ws, "--overwrite", "--set", "ingest.stride=2")
    assert code == 0 and "3 frames" in out, out


def _ws_untouched(ws: Path) -> None:
    assert not ws.exists() or not any(ws.iterdir())


def test_missing_and_unknown_and_corrupt_inputs(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    code, out = run("ingest", tmp_path / "nope.bag", "-w", ws)
    assert_one_line_error(code, out, "nope.bag", "does not exist")
    junk = tmp_path / "flight.bag"
    junk.write_bytes(b"PK\x03\x04 not a bag at all" * 10)
    code, out = run("info", junk)
    assert_one_line_error(code, out, "flight.bag", "expected a ROS1 .bag")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    code, out = run("ingest", text, "-w", ws)
    assert_one_line_error(code, out, "notes.txt")
    # An MCAP named .bag: say what it is and how to fix it.
    rec = write_recording(tmp_path / "rec", "mcap", n=3)
    misnamed = tmp_path / "misnamed.bag"
    misnamed.write_bytes(rec.path.read_bytes())
    code, out = run("info", misnamed)
    assert_one_line_error(code, out, "MCAP", ".mcap")
    # Corrupted bytes in the middle of a compressed ROS1 bag.
    rec1 = write_recording(tmp_path / "r1", "ros1", n=20)
    data = bytearray(rec1.path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(64)
    broken = tmp_path / "broken.bag"
    broken.write_bytes(bytes(data))
    code, out = run("ingest", broken, "-w", ws)
    assert_one_line_error(code, out, "broken.bag")
    _ws_untouched(ws)


def test_truncated_mcap_warns_and_ingests(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=60)
    data = rec.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    result = CliRunner().invoke(main, ["ingest", str(cut), "-w", str(tmp_path / "ws")])
    assert result.exit_code == 0, result.output
    assert "warning:" in result.output and "truncated" in result.output and "recovered" in result.output


def test_no_depth_topic_lists_image_topics(tmp_path: Path) -> None:
    path = tmp_path / "rgb.mcap"
    with BagRecorder(path, "mcap") as bag:
        Image = bag.typestore.types["sensor_msgs/msg/Image"]
        for i in range(3):
            msg = Image(header=bag.header(T0 + i, "cam"), height=2, width=2, encoding="rgb8",
                        is_bigendian=0, step=6, data=np.zeros(12, np.uint8))
            bag.write_raw("/camera/color/image_raw", "sensor_msgs/msg/Image", msg, T0 + i)
        bag.write_odometry("/odom", T0, np.eye(4), frame_id="world", child_frame_id="base_link")
    code, out = run("info", path)
    assert_one_line_error(code, out, "no depth topic", "/camera/color/image_raw (rgb8)", "--depth-topic")
    code, out = run("ingest", path, "-w", tmp_path / "ws", "--depth-topic", "camera/color/image_raw")
    assert_one_line_error(code, out, "/camera/color/image_raw has encoding rgb8", "16UC1, mono16, 32FC1 or compressedDepth")
    _ws_untouched(tmp_path / "ws")


def test_no_camera_info_then_intrinsics(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "ros2", n=3, camera_info=False)
    code, out = run("ingest", rec.path, "-w", tmp_path / "ws")
    assert_one_line_error(code, out, "no camera info", "--intrinsics")
    code, out = run("ingest", rec.path, "-w", tmp_path / "ws", "--intrinsics", "50,50,31.5")
    assert_one_line_error(code, out, "fx,fy,cx,cy", usage=True)
    code, out = run("ingest", rec.path, "-w", tmp_path / "ws", "--intrinsics", "50,50,31.5,23.5")
    assert code == 0, out


def test_no_pose_overlapping_depth(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=4, pose_offset_s=-50.0)
    code, out = run("ingest", rec.path, "-w", tmp_path / "ws")
    assert_one_line_error(code, out, "no pose overlaps the depth stamps", "outside_pose_coverage: 4")
    _ws_untouched(tmp_path / "ws")


def test_non_monotonic_stamps(tmp_path: Path) -> None:
    path = tmp_path / "jump.mcap"
    rec = write_recording(tmp_path / "ok", "mcap", n=6)
    from mapkit.ingest import Source

    with Source(rec.path) as src, BagRecorder(path, "mcap") as bag:
        for raw in src.messages(list(src.summary.topics)):
            msg = src.deserialize(raw)
            if raw.topic.endswith("image_rect_raw") and msg.header.stamp.nanosec == (rec.stamps_ns[4] - T0 // 10**9 * 10**9):
                msg.header.stamp.nanosec = rec.stamps_ns[1] - (T0 // 10**9) * 10**9  # clock jumps back
            bag.write_raw(raw.topic, raw.msgtype, msg, raw.log_time_ns)
    code, out = run("ingest", path, "-w", tmp_path / "ws")
    assert_one_line_error(code, out, "goes backwards at message 4", "--set ingest.drop_nonmonotonic=true")
    _ws_untouched(tmp_path / "ws")
    code, out = run("ingest", path, "-w", tmp_path / "ws", "--set", "ingest.drop_nonmonotonic=true")
    assert code == 0 and "non_monotonic_stamp 1" in out, out


def test_zero_sized_image(tmp_path: Path) -> None:
    path = tmp_path / "zero.mcap"
    with BagRecorder(path, "mcap") as bag:
        Image = bag.typestore.types["sensor_msgs/msg/Image"]
        bag.write_odometry("/odom", T0, np.eye(4), frame_id="world", child_frame_id="cam")
        bag.write_odometry("/odom", T0 + 10**9, np.eye(4), frame_id="world", child_frame_id="cam")
        msg = Image(header=bag.header(T0 + 10, "cam"), height=0, width=0, encoding="16UC1",
                    is_bigendian=0, step=0, data=np.zeros(0, np.uint8))
        bag.write_raw("/depth", "sensor_msgs/msg/Image", msg, T0 + 10)
    code, out = run("ingest", path, "-w", tmp_path / "ws", "--intrinsics", "50,50,1,1")
    assert_one_line_error(code, out, "0x0 image")
    _ws_untouched(tmp_path / "ws")


@pytest.mark.parametrize("option,value,needle,usage", [
    ("--set", "ingest.stride=0", "stride 0", True),
    ("--set", "ingest.max_pose_gap=-1", "max_pose_gap -1", True),
    ("--set", "ingest.extrinsic=1,2,3", "extrinsic '1,2,3'", True),
    ("--pose-topic", "/nope", "no such topic", False),
])
def test_bad_options(tmp_path: Path, option: str, value: str, needle: str, usage: bool) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=2)
    code, out = run("ingest", rec.path, "-w", tmp_path / "ws", option, value)
    assert_one_line_error(code, out, needle, usage=usage)


def test_the_same_recording_twice_is_refused_and_overlapping_flights_are_kept_apart(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "a", "mcap", n=4)
    other = write_recording(tmp_path / "b", "mcap", n=4)  # same clock: overlaps rec in time
    twice = tmp_path / "sub" / ".." / rec.path.name
    (tmp_path / "sub").mkdir()
    code, out = run("ingest", rec.path, twice, "-w", tmp_path / "ws")
    assert_one_line_error(code, out, "is the same recording as", "give each recording once")
    _ws_untouched(tmp_path / "ws")
    code, out = run("ingest", rec.path, other.path, "-w", tmp_path / "ws2")
    assert code == 0 and "overlap in time" in out and "separate flights" in out, out
    from mapkit.export import body_velocities
    from mapkit.ingest import open_frames_store

    store = open_frames_store(tmp_path / "ws2")
    assert store.source_index.tolist() == [0] * 4 + [1] * 4
    v = body_velocities(store.stamp_ns, store.T_world_body, store.source_index)
    np.testing.assert_allclose(v[:4], v[4:])  # the same flight twice: each differenced on its own
    assert np.isfinite(v).all()


def test_damaged_ros_recordings_say_what_is_damaged_and_how_to_repair(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "a", "ros1", n=20)
    data = bytearray(rec.path.read_bytes())
    for i in range(len(data) // 3, len(data) // 3 + 200):  # inside the chunk holding the images
        data[i] ^= 0x5A
    (tmp_path / "corrupt.bag").write_bytes(bytes(data))
    code, out = run("ingest", tmp_path / "corrupt.bag", "-w", tmp_path / "w1")
    assert_one_line_error(code, out, "is damaged")
    assert "no depth topic" not in out
    (tmp_path / "cut.bag").write_bytes(rec.path.read_bytes()[: int(len(data) * 0.8)])
    code, out = run("ingest", tmp_path / "cut.bag", "-w", tmp_path / "w2")
    assert_one_line_error(code, out, "rosbag reindex")
    ros2 = write_recording(tmp_path / "r2", "ros2", n=5)
    meta = ros2.path / "metadata.yaml"
    meta.write_text(meta.read_text()[:200] + "\n  : - [ bad")
    code, out = run("ingest", ros2.path, "-w", tmp_path / "w3")
    assert_one_line_error(code, out, "metadata.yaml does not parse")
    assert len(out.strip().splitlines()) == 1
