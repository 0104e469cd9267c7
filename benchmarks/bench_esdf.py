"""Benchmark of mapkit.esdf: signed EDT + Gaussian smoothing against the scipy peer, on identical grids.

    .venv/bin/python benchmarks/bench_esdf.py            # full table (~2-3 min on 2 cores)
    .venv/bin/python benchmarks/bench_esdf.py --quick    # smaller large-grid runs
    .venv/bin/python benchmarks/bench_esdf.py --dask-only  # only the chunked-on-Dask section (4-7 min)

Scene: a forest-like occupancy (floor, vertical cylinders of random radius/height, random boxes;
about 5 % occupied), voxel 0.1 m, Gaussian sigma 0.2 m (2 voxels, truncated at 3 sigma).

Rows:
- ours (edt): ``signed_distance(backend="edt")`` + ``smooth`` — total and split; best of 3 after a
  warm-up run (first-touch page faults of fresh memory are counted in the 512^3 "cold" column).
- ours (scipy backend): ``signed_distance(backend="scipy")`` + ``smooth``.
- scipy peer: ``distance_transform_edt(~occ) - distance_transform_edt(occ)`` then
  ``gaussian_filter`` (the straightforward numpy/scipy way), measured in the same run.
- 512^3: in a fresh subprocess (cold = first run, warm = second), peak RSS from /proc VmHWM.
- chunked on Dask (issue 15): the same 768x768x256 zarr occupancy into a map.zarr made by
  ``create_map`` (max_dist 1.5 m, chunk 128, as ``mapkit esdf``), each run in a fresh subprocess:
  * peer: today's in-process chunked path before the Dask graph (benchmarks/peer_sequential_esdf.py:
    a loop over the chunks in this process, 2 threads per chunk, a background writer thread), the
    same chunk function as the Dask tasks;
  * ours, this process on Dask's synchronous scheduler (``signed_distance_chunked`` without a client:
    one chunk at a time, 2 threads per chunk);
  * ours, 1 worker: this process on Dask's threaded scheduler (2 chunks at once, 1 thread each) --
    what ``mapkit esdf`` runs for a grid too large for memory, or with ``--workers 1``;
  * ours, LocalCluster of 1 and of 2 single-threaded worker processes (1 thread per chunk: how the
    time scales with workers; ``mapkit esdf --workers 2`` on this machine), start-up timed apart;
  peak memory per worker from getrusage in each task; speed-ups against the peer and against 1 worker;
  then how the time grows with the grid (2 workers, three sizes).

The machine is shared: the load average at start is printed; other processes on the two cores slow
every row (ours and the peer alike).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

VOXEL = 0.1
SIGMA = 0.2
TRUNCATE = 3.0


def forest(shape: tuple[int, int, int], seed: int = 0) -> np.ndarray:
    """bool [nx, ny, nz]: floor + trees (cylinders) + boxes, in voxel units."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = shape
    occ = np.zeros(shape, bool)
    occ[:, :, : max(1, nz // 64)] = True
    ii, jj = np.arange(nx), np.arange(ny)
    for _ in range((nx * ny) // 8192 + 8):
        cx, cy = rng.uniform(0, nx), rng.uniform(0, ny)
        r = rng.uniform(1.0, min(nx, ny) / 40 + 1)
        h = int(rng.uniform(nz / 4, nz))
        x0, x1 = int(max(cx - r - 1, 0)), int(min(cx + r + 2, nx))
        y0, y1 = int(max(cy - r - 1, 0)), int(min(cy + r + 2, ny))
        X, Y = np.meshgrid(ii[x0:x1], jj[y0:y1], indexing="ij")
        occ[x0:x1, y0:y1, :h] |= ((X - cx) ** 2 + (Y - cy) ** 2 <= r * r)[:, :, None]
    for _ in range((nx * ny) // 16384 + 4):
        lo = rng.integers(0, shape, 3)
        size = rng.integers(2, min(shape) // 8 + 3, 3)
        occ[lo[0] : lo[0] + size[0], lo[1] : lo[1] + size[1], lo[2] : lo[2] + size[2]] = True
    return occ


def _peak_rss_gb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1e6
    return float("nan")


def _ours(occ: np.ndarray, backend: str = "edt") -> tuple[float, float, int]:
    from mapkit.esdf import signed_distance, smooth

    t0 = time.perf_counter()
    raw = signed_distance(occ, voxel_size=VOXEL, backend=backend)
    t1 = time.perf_counter()
    esdf, n = smooth(raw, voxel_size=VOXEL, sigma=SIGMA, truncate=TRUNCATE)
    t2 = time.perf_counter()
    del raw, esdf
    return t1 - t0, t2 - t1, n


def _peer(occ: np.ndarray) -> tuple[float, float]:
    from scipy import ndimage

    t0 = time.perf_counter()
    d = ndimage.distance_transform_edt(~occ) - ndimage.distance_transform_edt(occ)
    t1 = time.perf_counter()
    ndimage.gaussian_filter(d, SIGMA / VOXEL, truncate=TRUNCATE)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


# ------------------------------------------------------------------------------- subprocess workers
def _worker_dense(n: int) -> dict:
    occ = forest((n, n, n), seed=1)
    base = _peak_rss_gb()
    cold = _ours(occ)
    warm = _ours(occ)
    return {"cold": cold, "warm": warm, "peak_gb": _peak_rss_gb(), "base_gb": base, "occupied": float(occ.mean())}


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and its reaped children (a cluster's worker processes)."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _occupancy_zarr(path: Path, shape: tuple[int, int, int]) -> Any:
    """The forest scene as a zarr occupancy written slab by slab (nothing grid-sized in memory)."""
    import zarr

    occ_arr = zarr.open_array(path, mode="w", shape=shape, chunks=(128, 128, 128), dtype=bool, zarr_format=3)
    slab = 128
    for x0 in range(0, shape[0], slab):
        occ_arr[x0 : x0 + slab] = forest((min(slab, shape[0] - x0), *shape[1:]), seed=x0)
    return occ_arr


def _worker_chunked(shape: tuple[int, int, int], max_dist: float, mode: str, workers: int) -> dict:
    """One chunked run (mode: peer, sync or cluster) of the zarr forest into a fresh map.zarr."""
    from mapkit.esdf import create_map, signed_distance_chunked

    tmp = Path(tempfile.mkdtemp(prefix="bench_esdf_"))
    try:
        occ_arr = _occupancy_zarr(tmp / "occ.zarr", shape)
        base = _peak_rss_gb()
        cpu0 = _cpu_seconds()
        startup = 0.0
        with contextlib.ExitStack() as stack:
            client = None
            if mode == "cluster":
                from mapkit._dask import dask_client

                t = time.perf_counter()
                client, _ = stack.enter_context(dask_client(None, workers=workers))
                startup = time.perf_counter() - t
            t0 = time.perf_counter()
            with create_map(tmp / "map.zarr", shape=shape, origin=(0, 0, 0), voxel_size=VOXEL, frame_id="world",
                            sigma=SIGMA, unknown_policy="free", parameters={"max_dist": max_dist}) as w:
                kw = dict(out_raw=w.esdf_raw, voxel_size=VOXEL, max_dist=max_dist, sigma=SIGMA, chunk=128)
                if mode == "peer":
                    from peer_sequential_esdf import sequential_chunked

                    sequential_chunked(occ_arr, w.esdf, threads=2, **kw)
                    peak, n_workers = _peak_rss_gb(), 1
                else:
                    threads = 2 if mode == "sync" else 1
                    local = 2 if mode == "threads" else 1
                    s = signed_distance_chunked(occ_arr, w.esdf, threads=threads, client=client, local_workers=local,
                                                progress=False, **kw)
                    peak, n_workers = s.peak_rss_bytes / 1e9, s.workers
                w.observed[...] = 1
            seconds = time.perf_counter() - t0
        cpu = _cpu_seconds() - cpu0  # after the cluster closed: its reaped processes count as children
        size = sum(f.stat().st_size for f in (tmp / "map.zarr").rglob("*") if f.is_file())
        return {"seconds": seconds, "startup": startup, "peak_gb": peak, "base_gb": base, "workers": n_workers,
                "store_gb": size / 1e9, "cpu": cpu}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _subprocess(args: list[str]) -> dict:
    out = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"worker {args} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smaller large-grid runs")
    ap.add_argument("--dask-only", action="store_true", help="only the chunked-on-Dask section")
    ap.add_argument("--grid", type=int, default=256, help="edge of the in-process grid (voxels)")
    ap.add_argument("--large-grid", type=int, help="edge of the fresh-subprocess grid (default 512, 384 with --quick)")
    ap.add_argument("--chunked-grid", type=_grid_shape, metavar="X,Y,Z",
                    help="the Dask section's grid (default 768,768,256, 512,512,256 with --quick); its growth rows "
                         "are then half of it in x and y, and it")
    ap.add_argument("--growth", action=argparse.BooleanOptionalAction, default=True,
                    help="time the Dask section's growth with the grid size")
    ap.add_argument("--worker-dense", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--worker-chunked", type=str, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker_dense:
        print(json.dumps(_worker_dense(a.worker_dense)))
        return
    if a.worker_chunked:
        spec = json.loads(a.worker_chunked)
        print(json.dumps(_worker_chunked(tuple(spec["shape"]), spec["max_dist"], spec["mode"], spec["workers"])))
        return

    import edt
    import scipy

    import mapkit

    t_start = time.perf_counter()
    load = os.getloadavg()
    print(f"mapkit {mapkit.__version__}, numpy {np.__version__}, scipy {scipy.__version__}, edt (multi-label), "
          f"{os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"scene: forest (floor + trees + boxes), voxel {VOXEL} m, sigma {SIGMA} m ({SIGMA / VOXEL:g} voxels, truncate {TRUNCATE})")
    del edt
    if not a.dask_only:
        _dense_section(a.grid)
        _large_section(a.large_grid or (384 if a.quick else 512))
    _dask_section(a.quick, a.chunked_grid, growth=a.growth)
    print(f"\nbenchmark wall time {time.perf_counter() - t_start:.0f} s")


def _grid_shape(text: str) -> tuple[int, int, int]:
    """``X,Y,Z`` → a grid shape (argparse's type for --chunked-grid)."""
    parts = text.split(",")
    if len(parts) != 3 or not all(p.strip().isdigit() and int(p) > 0 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: expected three positive voxel counts X,Y,Z, e.g. 256,256,128")
    x, y, z = (int(p) for p in parts)
    return x, y, z


def _dense_section(n: int) -> None:
    """Ours (both backends) against the scipy peer on an n^3 grid in this process."""
    occ = forest((n, n, n))
    print(f"\n== {n}^3 = {n ** 3 / 1e6:.1f} M voxels, {occ.mean() * 100:.1f} % occupied ==")
    _ours(occ)  # warm-up: imports, thread pools, first touch of fresh memory
    runs = [_ours(occ) for _ in range(3)]
    best = min(runs, key=lambda r: r[0] + r[1])
    ours_total = best[0] + best[1]
    sc = _ours(occ, backend="scipy")
    peer_runs = [_peer(occ) for _ in range(2)]
    peer = min(peer_runs, key=lambda r: r[0] + r[1])
    peer_total = peer[0] + peer[1]
    rows = [
        ("ours, edt backend (best of 3)", best[0], best[1]),
        ("ours, scipy backend", sc[0], sc[1]),
        ("scipy peer: distance_transform_edt x2 + gaussian_filter", peer[0], peer[1]),
    ]
    print(f"{'':58s} {'signed EDT':>10s} {'Gaussian':>9s} {'total':>8s}")
    for name, e, g in rows:
        print(f"{name:58s} {e:9.3f}s {g:8.3f}s {e + g:7.3f}s")
    ratio = peer_total / ours_total
    print(f"ratio peer / ours: {ratio:.1f}x (goal >= 7x); ours total {ours_total:.3f} s (goal <= 0.8 s) -> "
          f"{'MET' if ratio >= 7 and ours_total <= 0.8 else 'NOT MET'}")
    print(f"sign flips prevented by the guard: {best[2]}")


def _large_section(n: int) -> None:
    """Cold and warm runs on an n^3 grid in a fresh subprocess, with its peak memory."""
    d = _subprocess(["--worker-dense", str(n)])
    cold, warm = d["cold"], d["warm"]
    print(f"\n== {n}^3 = {n ** 3 / 1e6:.0f} M voxels, fresh subprocess ==")
    print(f"{'':58s} {'signed EDT':>10s} {'Gaussian':>9s} {'total':>8s}")
    print(f"{'ours, cold (first run: page faults of fresh memory)':58s} {cold[0]:9.3f}s {cold[1]:8.3f}s {cold[0] + cold[1]:7.3f}s")
    print(f"{'ours, warm (second run)':58s} {warm[0]:9.3f}s {warm[1]:8.3f}s {warm[0] + warm[1]:7.3f}s")
    grid_gb = n ** 3 * (1 + 4 + 4) / 1e9
    print(f"peak RSS {d['peak_gb']:.2f} GB (before: {d['base_gb']:.2f} GB; occupancy + raw + smoothed = {grid_gb:.2f} GB); "
          f"goal <= 5 s -> {'MET' if min(cold[0] + cold[1], warm[0] + warm[1]) <= 5 else 'NOT MET'} (warm), "
          f"{'MET' if cold[0] + cold[1] <= 5 else 'NOT MET'} (cold)")


def _dask_section(quick: bool, grid: tuple[int, int, int] | None = None, *, growth: bool = True) -> None:
    """Today's in-process chunked path against the Dask graph with 1 and 2 workers, same grid, same run."""
    shape = grid or ((512, 512, 256) if quick else (768, 768, 256))
    nvox = shape[0] * shape[1] * shape[2]
    max_dist = 1.5
    print(f"\n== chunked on Dask: {shape[0]}x{shape[1]}x{shape[2]} = {nvox / 1e6:.0f} M voxels, zarr occupancy -> map.zarr "
          f"(esdf + esdf_raw, zstd), chunk 128, max_dist {max_dist} m, sigma {SIGMA} m, fresh subprocess each ==")
    runs = [("peer: today's in-process chunked loop (2 threads/chunk)", "peer", 1),
            ("ours: this process, sync scheduler (1 chunk at a time, 2 threads)", "sync", 1),
            ("ours: 1 worker = this process, threaded (2 chunks at once, 1 thread each)", "threads", 1),
            ("ours: LocalCluster, 1 worker process (1 thread/chunk)", "cluster", 1),
            ("ours: LocalCluster, 2 worker processes (1 thread/chunk)", "cluster", 2)]
    res = {}
    print(f"{'':74s} {'time':>7s} {'M vox/s':>8s} {'start-up':>9s} {'CPU':>7s} {'peak RSS/worker':>16s} {'vs peer':>8s}")
    for name, mode, workers in runs:
        r = _subprocess(["--worker-chunked", json.dumps({"shape": shape, "max_dist": max_dist, "mode": mode, "workers": workers})])
        res[(mode, workers)] = r
        ratio = res[("peer", 1)]["seconds"] / r["seconds"]
        print(f"{name:74s} {r['seconds']:6.1f}s {nvox / r['seconds'] / 1e6:8.1f} {r['startup']:8.1f}s {r['cpu']:6.1f}s "
              f"{r['peak_gb']:14.2f}GB {ratio:7.2f}x")
    peer, one, two = res[("peer", 1)]["seconds"], res[("threads", 1)]["seconds"], res[("cluster", 2)]["seconds"]
    one_proc = res[("cluster", 1)]["seconds"]
    print(f"1 worker (this process, threaded: what `mapkit esdf` runs) vs peer: {peer / one:.2f}x (goal: not slower -> "
          f"{'MET' if one <= peer * 1.05 else 'NOT MET'}); 2 worker processes vs peer: {peer / two:.2f}x (goal >= 1.7x -> "
          f"{'MET' if peer / two >= 1.7 else 'NOT MET'}); 2 vs 1 worker process at 1 thread/chunk: {one_proc / two:.2f}x")
    print(f"store {res[('threads', 1)]['store_gb']:.2f} GB. CPU = user + system seconds of the run's processes, cluster start "
          "and stop included: unlike the wall time it does not depend on what else the shared cores run. The peer "
          "already used both cores inside each chunk (EDT and Gaussian threads), so a second worker process can add "
          "only what those threads left idle.")
    if growth:
        _growth(shape, res[("cluster", 2)], quick=quick, explicit=grid is not None, max_dist=max_dist)


def _growth(shape: tuple[int, int, int], full: dict, *, quick: bool, explicit: bool, max_dist: float) -> None:
    """How the 2-worker time grows with the grid; ``full`` is the run on ``shape`` already made."""
    if explicit:
        sizes = [(max(1, shape[0] // 2), max(1, shape[1] // 2), shape[2]), shape]
    else:
        sizes = [(384, 384, 256), (512, 512, 256)] if quick else [(384, 384, 256), (768, 384, 256), shape]
    print("\n== growth with grid size (ours, 2 worker processes; start-up excluded) ==")
    print(f"{'grid':>14s} {'M voxels':>9s} {'time':>7s} {'ns/voxel':>9s}")
    for sz in sizes:
        n = sz[0] * sz[1] * sz[2]
        r = full if sz == shape else _subprocess(
            ["--worker-chunked", json.dumps({"shape": sz, "max_dist": max_dist, "mode": "cluster", "workers": 2})])
        print(f"{'x'.join(map(str, sz)):>14s} {n / 1e6:9.0f} {r['seconds']:6.1f}s {r['seconds'] / n * 1e9:9.1f}")


if __name__ == "__main__":
    main()
