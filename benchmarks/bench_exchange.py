"""Foxglove / Rerun export speed (goals: the sample forest workspace ≤ 5 s; the ESDF channel of a 256³ map ≤ 2 s).

    .venv/bin/python benchmarks/bench_exchange.py [--workspace demo_ws/forest] [--grid 256]

Workspace: the demo's forest (`make demo` builds `demo_ws/forest`: 300 frames, cloud, map.zarr);
skipped with a note when it is missing. Rows: `export_foxglove` and `export_rerun` of it (flight,
cloud, map; no plans), with file sizes. ESDF channel: one 256³ VoxelGrid (distance + observed)
encoded and written to an MCAP with foxglove-sdk. Peer: the `mcap` package writing the same bytes as
one raw message (what the channel costs beyond copying its payload).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def _workspace_rows(ws: Path, tmp: Path) -> None:
    from mapkit.exchange import FoxgloveConfig, export_foxglove, export_rerun

    for name, export, out in (("foxglove", export_foxglove, tmp / "forest.mcap"), ("rerun", export_rerun, tmp / "forest.rrd")):
        t0 = time.perf_counter()
        s = export(ws, out, FoxgloveConfig(overwrite=True))
        print(f"{ws.name} workspace → {name:8s} {time.perf_counter() - t0:6.2f} s   {s.bytes / 1e6:6.1f} MB   (goal ≤ 5 s)")


def _voxel_grid_row(tmp: Path, n: int) -> None:
    import foxglove
    from foxglove.channels import VoxelGridChannel
    from foxglove.messages import Vector3, VoxelGrid
    from mcap.writer import Writer

    from mapkit.exchange._foxglove import _fields, _pose

    cells = np.zeros((n, n, n), dtype=[("distance", "<f4"), ("observed", "u1")])
    cells["distance"] = np.random.default_rng(0).normal(size=(n, n, n)).astype(np.float32)
    cells["observed"] = 1
    t0 = time.perf_counter()
    context = foxglove.Context()
    channel = VoxelGridChannel("/map/esdf", context=context)
    writer = foxglove.open_mcap(tmp / "grid.mcap", context=context, allow_overwrite=True)
    channel.log(VoxelGrid(pose=_pose(np.eye(4)), row_count=n, column_count=n, cell_size=Vector3(x=0.1, y=0.1, z=0.1),
                          slice_stride=5 * n * n, row_stride=5 * n, cell_stride=5,
                          fields=_fields(("distance", 0, "Float32"), ("observed", 4, "Uint8")), data=cells.tobytes()))
    writer.close()
    ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open(tmp / "raw.mcap", "wb") as f:
        raw = Writer(f)
        raw.start()
        schema = raw.register_schema("raw", "", b"")
        ch = raw.register_channel("/raw", "application/octet-stream", schema)
        raw.add_message(ch, log_time=0, publish_time=0, data=cells.tobytes())
        raw.finish()
    peer = time.perf_counter() - t0
    print(f"{n}³ VoxelGrid channel  {ours:6.2f} s   {(tmp / 'grid.mcap').stat().st_size / 1e6:6.1f} MB   (goal ≤ 2 s); "
          f"peer mcap raw write {peer:.2f} s → ratio {ours / peer:.2f}×")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=REPO / "demo_ws" / "forest",
                        help="the workspace exported in the first rows (default: the demo's forest)")
    parser.add_argument("--grid", type=int, default=256, help="edge of the ESDF channel's cubic grid (voxels)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        ws = args.workspace
        if (ws / "frames.zarr").exists():
            _workspace_rows(ws, tmp)
        else:
            print(f"forest workspace: {ws} missing; run `make demo` first")
        _voxel_grid_row(tmp, args.grid)


if __name__ == "__main__":
    main()
