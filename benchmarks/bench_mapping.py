"""Map building: fusion speed (640x480 at 5 cm) and ESDF accuracy against the simulator's exact SDF.

Speed: a simulated forest flight at 640x480 is ingested, then fused from frames.zarr; printed are
the end-to-end rate (read + decode + integrate) and Open3D's integrate-only rate beside it.

Accuracy (issue 3 §3): simulated flights (noise off) → fuse at 5 cm → esdf at 10 cm, sigma 0,
compared with World.signed_distance at voxel centres, in observed free voxels within 2 m of an
observed surface (the nearest true surface was seen: the fused cloud lies about as far away): mean |error|, RMS, share off by more than one voxel; the fused cloud's mean
distance to the true surface; the error in unobserved space; sign flips prevented by smoothing.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def speed(tmp: Path, frames: int) -> None:
    from mapkit.fusion import FuseConfig, fuse_store
    from mapkit.ingest import ingest, open_frames_store
    from mapkit.sim import SimConfig, simulate

    config = SimConfig(world="forest", seed=5, duration=frames / 30.0, width=640, height=480)
    t = time.perf_counter()
    result = simulate(config, tmp / "speed", progress=False)
    sim_s = time.perf_counter() - t
    ingest([result.bag_path], tmp / "ws_speed", progress=False)
    store = open_frames_store(tmp / "ws_speed")
    best = None
    for _ in range(2):
        s = fuse_store(store, tmp / "ws_speed", FuseConfig(voxel=0.05), overwrite=True, progress=False)
        best = s if best is None or s.seconds < best.seconds else best
    assert best is not None
    print(f"fusion speed: {best.frames_used} frames 640x480 at 5 cm (simulated in {sim_s:.0f} s), best of 2")
    print(f"  end to end (read frames.zarr + decode + integrate + extract + save): {best.frames_per_second:7.1f} frames/s   goal >= 150")
    print(f"  Open3D integrate only (compute blocks + integrate):                 {best.integrate_frames_per_second:7.1f} frames/s")


def accuracy(tmp: Path, world_kind: str, frames: int, width: int) -> dict[str, float]:
    import open3d as o3d

    from mapkit.esdf import EsdfConfig, EsdfMap, build_esdf
    from mapkit.fusion import FuseConfig, fuse
    from mapkit.sim import SimConfig, simulate

    config = SimConfig(world=world_kind, seed=11, duration=frames / 30.0, width=width, height=width * 3 // 4)
    result = simulate(config, tmp / world_kind, progress=False)
    ws = tmp / f"ws_{world_kind}"
    fuse([result.bag_path], ws, FuseConfig(voxel=0.05), progress=False)
    cloud = np.asarray(o3d.io.read_point_cloud(str(ws / "cloud.ply")).points)
    cloud_err = np.abs(result.world.signed_distance(cloud)).mean() / 0.05
    build_esdf(ws, EsdfConfig(voxel=0.1, sigma=0.0), progress=False)
    raw = EsdfMap.open(ws / "map.zarr")
    esdf = np.asarray(raw.esdf[:])
    observed = np.asarray(raw.observed[:]).astype(bool)
    xs, ys, zs = (raw.origin[a] + raw.voxel_size * np.arange(raw.shape[a]) for a in range(3))
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    truth = result.world.signed_distance(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)).reshape(esdf.shape)
    v = raw.voxel_size
    near = observed & (truth > 0) & (truth <= 2.0)
    # "within 2 m of an observed surface": the nearest true surface must have been seen, i.e. the
    # fused cloud lies about as far away as the true surface (unseen walls cannot be in the map).
    from scipy.spatial import cKDTree

    ijk = np.argwhere(near)
    d_cloud, _ = cKDTree(cloud).query(raw.origin + v * ijk, distance_upper_bound=2.5)
    seen = np.abs(d_cloud - truth[tuple(ijk.T)]) < 0.5 * v
    near[tuple(ijk[~seen].T)] = False
    err = (esdf - truth)[near] / v
    unobs = ~observed & (np.abs(truth) <= 2.0)
    build_esdf(ws, EsdfConfig(voxel=0.1, sigma=0.1), overwrite=True, progress=False)

    smoothed = EsdfMap.open(ws / "map.zarr")
    sm, rw = np.asarray(smoothed.esdf[:]), np.asarray(smoothed.esdf_raw[:])
    flips = int(np.sum((np.sign(sm) != np.sign(rw)) & (np.abs(rw) > v)))
    return {
        "voxels": int(near.sum()),
        "mean": float(np.abs(err).mean()),
        "rms": float(np.sqrt(np.mean(err**2))),
        "over1": float(100 * np.mean(np.abs(err) > 1.0)),
        "cloud": float(cloud_err),
        "unobserved": float(np.abs((esdf - truth)[unobs]).mean() / v) if unobs.any() else float("nan"),
        "flips": flips,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--speed-frames", type=int, default=150)
    parser.add_argument("--accuracy-frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--worlds", nargs="+", default=["forest", "office", "garage"])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        speed(Path(tmp), args.speed_frames)
        print(f"\nESDF accuracy (noise off, fuse 5 cm, esdf 10 cm, sigma 0; errors in voxels; {args.accuracy_frames} frames {args.width} px wide)")
        print(f"{'world':<8}{'voxels':>9}{'mean|e|':>9}{'RMS':>7}{'>1vox %':>9}{'cloud':>7}{'unobs':>7}{'flips':>7}")
        for kind in args.worlds:
            r = accuracy(Path(tmp), kind, args.accuracy_frames, args.width)
            print(f"{kind:<8}{r['voxels']:>9}{r['mean']:>9.3f}{r['rms']:>7.3f}{r['over1']:>9.3f}{r['cloud']:>7.3f}{r['unobserved']:>7.2f}{r['flips']:>7}")
        print("goals: mean|e| <= 0.3, RMS <= 0.35, >1 voxel <= 0.2 %, cloud <= 0.25 TSDF voxel, flips (|raw| > 1 voxel) = 0")


if __name__ == "__main__":
    main()
