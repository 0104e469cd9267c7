"""Viewer responsiveness: ESDF slice updates on a 16 M-voxel map, and start-up with a 1 M-point cloud.

    .venv/bin/python benchmarks/bench_viewer.py [--grid 256] [--points 1000000] [--no-browser]

Map: 256^3 voxels of 0.1 m (16.8 M), a forest-like signed distance (floor, trees, boxes) written with
``mapkit.esdf.create_map`` / ``write_map`` (64^3 chunks, Blosc zstd), observed where a distance < 3 m.

Slice update (goal <= 100 ms), per axis, median of 4 planes:
- cold: the first plane of a 64-plane slab (the chunks it touches are read and decompressed);
- cached: another plane of a slab already read (served from the slab cache);
- "library" = ``MapSlicer.texture`` (read + colour + place); "viewer" = the whole
  ``ViewerApp.update_slice`` (library + PNG encoding + the scene update message), which is what a
  slider move costs.
Peers: zarr's own plane read ``arr[:, :, k]`` (what a lazy ``slice_plane`` does on every move:
every chunk the plane touches, decompressed each time) and reading the whole array into memory
once (``arr[...]``, after which slicing is free but start-up and memory pay for it).

Start-up (goal <= 5 s): a workspace with that map and a 1 M-point cloud.ply (binary, with normals,
as Open3D writes it): ``ViewerApp(...)`` + ``start()`` in-process; ``mapkit view`` as a user runs
it (interpreter start, imports, load, bind) until it prints the URL; and, when Chromium is
installed, until a headless Chromium has drawn the scene (CPU WebGL: slower than any real browser).
Peer row: Open3D's PLY reader.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VOXEL = 0.1
SLAB = 64  # the viewer's slab of planes read at once (MapSlicer's cache unit)
REPO = Path(__file__).resolve().parent.parent


def forest_distance(n: int, seed: int = 0) -> np.ndarray:
    """float32 [n, n, n] signed distance (m) of a floor, vertical cylinders and boxes."""
    from mapkit.esdf import signed_distance

    rng = np.random.default_rng(seed)
    occ = np.zeros((n, n, n), bool)
    occ[:, :, :4] = True
    ii = np.arange(n)
    for _ in range(60):
        cx, cy, r = rng.uniform(0, n), rng.uniform(0, n), rng.uniform(2, max(2, min(8, n / 8)))
        h = int(rng.uniform(n / 4, n))
        x0, x1 = int(max(cx - r - 1, 0)), int(min(cx + r + 2, n))
        y0, y1 = int(max(cy - r - 1, 0)), int(min(cy + r + 2, n))
        X, Y = np.meshgrid(ii[x0:x1], ii[y0:y1], indexing="ij")
        occ[x0:x1, y0:y1, :h] |= ((X - cx) ** 2 + (Y - cy) ** 2 <= r * r)[:, :, None]
    for _ in range(20):
        lo = rng.integers(0, max(1, n - 20), 3)
        size = rng.integers(4, max(5, min(20, n // 2)), 3)
        occ[lo[0]:lo[0] + size[0], lo[1]:lo[1] + size[1], lo[2]:lo[2] + size[2]] = True
    return signed_distance(occ, voxel_size=VOXEL).astype(np.float32)


def mega(count: int) -> str:
    """A point count in millions, as the rows name it ("1 M")."""
    return f"{count / 1e6:g} M"


def make_workspace(root: Path, n: int, points: int) -> Path:
    import open3d as o3d

    from mapkit.esdf import write_map

    ws = root / "ws"
    ws.mkdir(parents=True)
    t = time.perf_counter()
    d = forest_distance(n)
    write_map(ws / "map.zarr", esdf=d, esdf_raw=d, observed=d < 3.0, origin=(0.0, 0.0, -0.4), voxel_size=VOXEL,
              frame_id="world", sigma=0.0, unknown_policy="free")
    # `points` cloud points near the zero level, with normals, written the way `mapkit fuse` writes them
    rng = np.random.default_rng(1)
    near = np.argwhere(np.abs(d) <= 0.75 * VOXEL)  # voxels next to the surface (|d| = half a voxel there)
    pick = near[rng.integers(0, len(near), points)]
    pts = (pick + rng.uniform(-0.5, 0.5, pick.shape)) * VOXEL + [0.0, 0.0, -0.4]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (len(pts), 1)))
    o3d.io.write_point_cloud(str(ws / "cloud.ply"), pc, write_ascii=False)
    print(f"workspace: map.zarr {n}^3 = {n**3 / 1e6:.1f} M voxels, cloud.ply {points:,} points "
          f"({(ws / 'cloud.ply').stat().st_size / 1e6:.0f} MB), made in {time.perf_counter() - t:.0f} s")
    return ws


def median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times))


def plane_index(slab: int, n: int, offset: int = 20) -> int:
    """Voxel index of a plane ``offset`` into ``slab`` (wrapped into a grid smaller than four slabs)."""
    return (SLAB * slab + offset) % n


def slice_rows(ws: Path) -> None:
    import zarr

    from mapkit.esdf import EsdfMap
    from mapkit.viewer import ViewerApp, ViewerConfig
    from mapkit.viz import MapSlicer, texture_scale

    m = EsdfMap.open(ws / "map.zarr")
    n = m.shape[0]
    planes = {a: [m.origin["xyz".index(a)] + VOXEL * plane_index(s, n) for s in range(4)] for a in "xyz"}
    again = {a: [m.origin["xyz".index(a)] + VOXEL * plane_index(s, n, 27) for s in range(4)] for a in "xyz"}
    print(f"\nslice update, {n}^3 map (median of 4 planes, ms)        x        y        z   goal <= 100")
    lib_cold, lib_hot, read_cold, read_hot = {}, {}, {}, {}
    ppv = texture_scale((n, n))
    MapSlicer(m).texture("z", 1.0)  # first call imports matplotlib's colormaps: keep it out of the rows
    for a in "xyz":
        for fn, cold_d, hot_d in ((lambda s, x, a=a: s.texture(a, x, pixels_per_voxel=ppv), lib_cold, lib_hot),
                                  (lambda s, x, a=a: s.slice(a, x), read_cold, read_hot)):
            slicer = MapSlicer(m)
            cold, hot = [], []
            for p, q in zip(planes[a], again[a], strict=False):
                t = time.perf_counter()
                fn(slicer, p)
                cold.append(time.perf_counter() - t)
                t = time.perf_counter()
                fn(slicer, q)
                hot.append(time.perf_counter() - t)
            cold_d[a], hot_d[a] = median_ms(cold), median_ms(hot)
    import mapkit.planner  # noqa: F401 - the viewer imports it in the background at start; keep that out of the rows

    app = ViewerApp(ViewerConfig(workspace=ws, port=0, max_points=1000))
    app.start()
    view_cold, view_hot = {}, {}
    try:
        for a in "xyz":
            app.gui.slice.axis.value = a
            app.slicer.cache.clear()
            cold, hot = [], []
            for p, q in zip(planes[a], again[a], strict=False):
                app.gui.slice.position.value = p
                cold.append(app.timings["slice_ms"] / 1e3)
                app.gui.slice.position.value = q
                hot.append(app.timings["slice_ms"] / 1e3)
            view_cold[a], view_hot[a] = median_ms(cold), median_ms(hot)
    finally:
        app.stop()
    arr = zarr.open_group(ws / "map.zarr", mode="r")["esdf"]
    peer_plane = {}
    for a in "xyz":
        ts = []
        for p in planes[a]:
            k = int(round((p - m.origin["xyz".index(a)]) / VOXEL))
            idx: list = [slice(None)] * 3
            idx["xyz".index(a)] = k
            t = time.perf_counter()
            np.asarray(arr[tuple(idx)])
            ts.append(time.perf_counter() - t)
        peer_plane[a] = median_ms(ts)
    t = time.perf_counter()
    np.asarray(arr[...])
    whole = 1e3 * (time.perf_counter() - t)

    def row(label: str, d: dict[str, float]) -> None:
        print(f"  {label:<52}" + "".join(f"{d[a]:9.1f}" for a in "xyz"))

    row("viewer update, cold slab (library + PNG + message)", view_cold)
    row("viewer update, cached slab", view_hot)
    row(f"library MapSlicer.texture ({ppv} px/voxel), cold slab", lib_cold)
    row(f"library MapSlicer.texture ({ppv} px/voxel), cached slab", lib_hot)
    row("  of which the read (MapSlicer.slice), cold slab", read_cold)
    row("  of which the read (MapSlicer.slice), cached slab", read_hot)
    row("peer: zarr plane read arr[:, :, k] (every move)", peer_plane)
    print(f"  {f'peer: zarr whole-array read arr[...] (once, {4 * n**3 / 2**20:.0f} MB)':<52}{whole:9.1f} ms, then slicing is free")


def startup_rows(ws: Path, points: int, *, browser: bool = True) -> None:
    import open3d as o3d

    from mapkit.viewer import ViewerApp, ViewerConfig
    from mapkit.viz import read_ply_points

    n = zarr_edge(ws)
    print(f"\nstart-up with a {mega(points)}-point cloud.ply and the {n}^3 map (s)                 goal <= 5")
    ts = []
    for _ in range(3):
        t = time.perf_counter()
        app = ViewerApp(ViewerConfig(workspace=ws, port=0))
        app.start()
        ts.append(time.perf_counter() - t)
        load, start = app.timings["load_s"], app.timings["start_s"]
        app.stop()
    print(f"  in process: ViewerApp() + start() (median of 3)          {np.median(ts):6.2f}   (last: load {load:.2f}, build {start:.2f})")
    exe = REPO / ".venv" / "bin" / "mapkit"
    cmd = [str(exe) if exe.exists() else sys.executable, *([] if exe.exists() else ["-m", "mapkit.cli"]),
           "view", "-w", str(ws), "--port", "0"]
    cli = []
    for _ in range(2):
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            for line in proc.stdout:
                if re.search(r"mapkit view: http://", line):
                    cli.append(time.perf_counter() - t)
                    break
        finally:
            proc.send_signal(2)
            proc.communicate(timeout=60)
    print(f"  `mapkit view -w WS` until the URL is printed (median of 2)   {np.median(cli):6.2f}   (interpreter + imports included)")
    if browser:
        browser_row(ws, points)
    t = time.perf_counter()
    read_ply_points(ws / "cloud.ply")
    ours = time.perf_counter() - t
    t = time.perf_counter()
    o3d.io.read_point_cloud(str(ws / "cloud.ply"))
    peer = time.perf_counter() - t
    print(f"  cloud.ply read: ours (numpy) {ours:.2f} s; peer Open3D read_point_cloud {peer:.2f} s")
    from mapkit.viz import downsample_to

    pts = np.concatenate([read_ply_points(ws / "cloud.ply").points] * 4) + np.repeat(np.arange(4), points)[:, None] * [0.0, 0.0, 0.01]
    t = time.perf_counter()
    out, voxel = downsample_to(pts, 2 * points)
    print(f"  voxel-grid downsampling {mega(4 * points)} → {len(out) / 1e6:.2f} M points (cell {100 * voxel:.1f} cm): {time.perf_counter() - t:.2f} s")


def zarr_edge(ws: Path) -> int:
    """The edge of the workspace's cubic map (voxels)."""
    from mapkit.esdf import EsdfMap

    return int(EsdfMap.open(ws / "map.zarr").shape[0])


def browser_row(ws: Path, points: int) -> None:
    """`mapkit view` start → a headless Chromium (software WebGL) shows the scene, settled."""
    from mapkit.viewer import ViewerApp, ViewerConfig, find_chromium, screenshot

    if find_chromium() is None:
        print("  browser row skipped: no Chromium (apt-get install chromium)")
        return

    def drawn(image: np.ndarray) -> bool:  # the slice and the cloud cover a good part of the page
        return bool((np.abs(image.astype(int) - 255).max(axis=-1) > 60).mean() > 0.15)

    for max_points, label in ((points, f"{mega(points)} points"), (10_000, "10 k points (--max-points)")):
        t = time.perf_counter()
        with ViewerApp(ViewerConfig(workspace=ws, port=0, max_points=max_points)) as app:
            screenshot(app.url, ws.parent / "shot.png", min_wait=0.0, ready=drawn, settle=False, timeout=180)
        print(f"  ... until headless Chromium shows the scene, {label:<27}{time.perf_counter() - t:6.2f}")
    print("      (Chromium launch included; software WebGL: SwiftShader draws 1 M points in seconds per frame on")
    print("       2 cores, a GPU browser in milliseconds)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=256, help="edge of the cubic map (voxels of 0.1 m)")
    parser.add_argument("--points", type=int, default=1_000_000, help="points in cloud.ply")
    parser.add_argument("--browser", action=argparse.BooleanOptionalAction, default=True,
                        help="time a headless Chromium drawing the scene (when Chromium is installed)")
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f} (2 cores; other processes slow every row)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_viewer_"))
    try:
        ws = make_workspace(tmp, args.grid, args.points)
        slice_rows(ws)
        startup_rows(ws, args.points, browser=args.browser)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
