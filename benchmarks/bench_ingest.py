"""Ingestion speed: raw `mcap` reader vs mapkit's decode + sync, and end-to-end ingest.

Writes a 640x480 16UC1 depth MCAP (zstd chunks, odometry at 120 Hz, like `mapkit simulate`),
then measures in one run:
  raw      mcap.reader.make_reader(...).iter_messages() over the depth topic (bytes only)
  decode   mapkit.ingest.open_frames: CDR deserialise + depth decode + pose sync
  ingest   mapkit.ingest.ingest: the above + writing frames.zarr
Goals (issue 2): decode >= 80 % of raw; ingest >= 300 frames/s.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def make_recording(path: Path, n: int) -> Path:
    from mapkit.bags import BagRecorder

    T0 = 1_700_000_000_000_000_000
    K = np.array([[387.0, 0, 319.5], [0, 387.0, 239.5], [0, 0, 1]])
    v, u = np.mgrid[0:480, 0:640]
    rng = np.random.default_rng(0)
    with BagRecorder(path, "mcap") as bag:
        from recordings import T_BODY_LINK, T_LINK_OPTICAL

        bag.write_tf_static(T0, [(T_BODY_LINK, "base_link", "camera_link"),
                                 (T_LINK_OPTICAL, "camera_link", "camera_depth_optical_frame")])
        for i in range(n):
            s = T0 + int(round(i * 1e9 / 30))
            for j in range(4):
                ps = T0 + int(round((4 * i + j) * 1e9 / 120))
                T = np.eye(4)
                T[:3, 3] = [0.05 * (4 * i + j) / 4, 0.0, 1.5]
                bag.write_odometry("/odom", ps, T, frame_id="world", child_frame_id="base_link")
            # Planes and a blob with sensor-like noise and holes: compresses like real depth.
            d = (2.0 + 1.5 * (v / 480) + 0.3 * np.sin(u / 40 + i / 10)).astype(np.float32)
            d += rng.normal(0, 0.004, d.shape).astype(np.float32)
            d[(u - 320 - i) ** 2 + (v - 240) ** 2 < 60**2] = np.nan
            bag.write_camera_info("/camera/depth/camera_info", s, K, 640, 480, frame_id="camera_depth_optical_frame")
            bag.write_depth("/camera/depth/image_rect_raw", s, d, frame_id="camera_depth_optical_frame")
        T = np.eye(4)
        T[:3, 3] = [0.05 * n, 0.0, 1.5]
        bag.write_odometry("/odom", T0 + int(round(n * 1e9 / 30)), T, frame_id="world", child_frame_id="base_link")
    return path


def bench_raw(path: Path) -> float:
    from mcap.reader import make_reader

    t = time.perf_counter()
    n = 0
    with open(path, "rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/camera/depth/image_rect_raw"]):
            n += len(message.data) > 0
    return n / (time.perf_counter() - t)


def bench_decode(path: Path) -> float:
    from mapkit.ingest import open_frames

    t = time.perf_counter()
    n = sum(1 for _ in open_frames([path]))
    return n / (time.perf_counter() - t)


def bench_ingest(path: Path, ws: Path) -> tuple[float, int]:
    from mapkit.ingest import ingest

    summary = ingest([path], ws, overwrite=True, progress=False)
    return summary.frames_per_second, summary.frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = make_recording(Path(tmp) / "bench.mcap", args.frames)
        size_mb = path.stat().st_size / 1e6
        raw = dec = ing = 0.0
        for _ in range(args.repeat):  # interleaved so background load hits all three alike
            raw = max(raw, bench_raw(path))
            dec = max(dec, bench_decode(path))
            ing = max(ing, bench_ingest(path, Path(tmp) / "ws")[0])
    print(f"input: {args.frames} frames 640x480 16UC1, MCAP zstd {size_mb:.1f} MB; best of {args.repeat}")
    print(f"{'stage':<34}{'frames/s':>10}{'vs raw':>9}  goal")
    print(f"{'raw mcap reader (bytes only)':<34}{raw:>10.0f}{1.0:>9.2f}")
    print(f"{'mapkit decode + sync':<34}{dec:>10.0f}{dec / raw:>9.2f}  >= 0.80 x raw")
    print(f"{'mapkit ingest -> frames.zarr':<34}{ing:>10.0f}{ing / raw:>9.2f}  >= 300 frames/s")


if __name__ == "__main__":
    main()
