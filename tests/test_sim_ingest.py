"""Issue 2 'done when': simulate every world in every format, ingest, and recover the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from recordings import rotation_angle

from mapkit.ingest import open_frames
from mapkit.sim import SimConfig, render_flight, simulate


@pytest.mark.slow
@pytest.mark.parametrize("world", ["forest", "office", "garage"])
@pytest.mark.parametrize("fmt,encoding", [("mcap", "16UC1"), ("ros2", "32FC1"), ("ros1", "16UC1"), ("mcap", "compressedDepth")])
def test_simulate_then_ingest_recovers_truth(tmp_path: Path, world: str, fmt: str, encoding: str) -> None:
    config = SimConfig(world=world, seed=3, format=fmt, duration=0.5, width=64, height=48, depth_encoding=encoding)
    result = simulate(config, tmp_path / "flight", progress=False)
    truth = render_flight(config)
    stream = open_frames([result.bag_path])
    frames = list(stream)
    assert len(frames) == len(truth.stamps_ns) and not stream.dropped
    # 16UC1 quantises to millimetres (half a millimetre rounding); 32FC1 is exact.
    tol = 0.0 if encoding == "32FC1" else 0.5e-3 + 1e-6
    for frame, stamp, T_wc, T_wb, depth in zip(frames, truth.stamps_ns, truth.T_world_camera, truth.T_world_body, truth.depths, strict=True):
        assert frame.stamp_ns == stamp
        assert np.abs(frame.T_world_camera[:3, 3] - T_wc[:3, 3]).max() <= 1e-6
        assert rotation_angle(frame.T_world_camera[:3, :3].T @ T_wc[:3, :3]) <= 1e-6
        assert np.abs(frame.T_world_body - T_wb).max() <= 1e-6
        np.testing.assert_array_equal(np.isnan(frame.depth), np.isnan(depth))
        assert np.nanmax(np.abs(frame.depth - depth)) <= tol
        np.testing.assert_allclose(frame.K, truth.K)
