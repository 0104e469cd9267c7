"""Stores at fsspec URLs: the cost of publishing with the root zarr.json last instead of a rename.

Ingests the same 640x480 recording (bench_ingest's generator) in one run into
  local    a local workspace (write a hidden sibling, rename: today's path, the peer)
  file://  the same disk through a file:// URL (treated as local: rename)
  memory:// fsspec's in-memory filesystem (hidden prefix, copy, root zarr.json last)
and copies the local frames.zarr to memory:// with copy_store. Prints seconds and frames/s per
target and the ratio against the local ingest. No goal in the issue; the figure goes in docs/stores.md.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _timed(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=2, help="best of N per target")
    args = parser.parse_args()

    import fsspec
    from bench_ingest import make_recording

    from mapkit._stores import copy_store
    from mapkit.ingest import ingest

    tmp = Path(tempfile.mkdtemp(prefix="bench_stores_"))
    try:
        bag = make_recording(tmp / "flight.mcap", args.frames)
        mem = fsspec.filesystem("memory")
        targets = {"local": lambda i: tmp / f"local{i}", "file://": lambda i: f"file://{tmp}/file{i}",
                   "memory://": lambda i: f"memory://bench-{uuid.uuid4().hex[:8]}/ws{i}"}
        best: dict[str, float] = {}
        for name, where in targets.items():
            times = []
            for i in range(args.repeats):
                workspace = where(i)
                times.append(_timed(lambda: ingest([bag], workspace, progress=False)))  # noqa: B023 - called at once
            best[name] = min(times)
        best["copy_store local→memory://"] = min(
            _timed(lambda: copy_store(tmp / "local0" / "frames.zarr", f"memory://bench-{uuid.uuid4().hex[:8]}/frames.zarr"))
            for _ in range(args.repeats))
        for path in mem.ls("/", detail=False):
            if path.lstrip("/").startswith("bench-"):
                mem.rm(path, recursive=True)
        print(f"ingest of {args.frames} frames 640x480 (best of {args.repeats}):")
        for name, seconds in best.items():
            print(f"  {name:28s} {seconds:6.2f} s  {args.frames / seconds:7.1f} frames/s  "
                  f"x{seconds / best['local']:.2f} of local")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
