"""`mapkit dataset`: many simulated worlds, each flown, recorded and run through ingest → fuse → esdf
→ export into a workspace; training never sees the simulator's exact signed distance."""

from __future__ import annotations

import json
import os
import shutil
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from mapkit._dask import available_cpus
from mapkit._version import __version__
from mapkit.errors import MapkitError
from mapkit.export import ExportConfig
from mapkit.sim import DEFAULT_DENSITIES, DEFAULT_SIZES, MIN_SIZES, WORLD_KINDS

MANIFEST = "dataset.json"
DONE = "dataset_item.json"  # written last in each world's workspace: the world is complete


class DatasetError(MapkitError):
    """A dataset request that cannot be carried out; the message names the option and the fix."""


@dataclass(frozen=True)
class CameraVariant:
    """One depth camera the dataset may fly (drawn per world)."""

    width: int
    height: int
    fx_scale: float = 1.0
    """Focal length relative to the D435's (387 px at 640 px width, scaled to ``width``)."""


def parse_cameras(text: str) -> tuple[CameraVariant, ...]:
    """Cameras from ``WxH[:FX_SCALE],...`` (the ``cameras`` setting), e.g. ``640x360`` for the paper preset's
    D435 or the default ``160x120,212x120:1.1,192x144:0.9``; a malformed entry is a one-line error."""
    out = []
    for entry in (e.strip() for e in text.split(",") if e.strip()):
        size, _, scale = entry.partition(":")
        w, _, h = size.lower().partition("x")
        try:
            out.append(CameraVariant(int(w), int(h), float(scale) if scale else 1.0))
        except ValueError:
            raise DatasetError(f"cameras entry {entry!r} is not WIDTHxHEIGHT[:FX_SCALE] (e.g. 640x360 or 212x120:1.1)") from None
    if not out:
        raise DatasetError(f"cameras {text!r} names no camera; e.g. 160x120 or 640x360,848x480")
    return tuple(out)


@dataclass
class DatasetConfig:
    """What `mapkit dataset` generates. Per-world parameters are drawn from these ranges with a
    generator seeded by (``seed``, world index), so the same config gives the same worlds."""

    worlds: int = 24
    """Number of worlds (each one flight, one workspace)."""
    kinds: tuple[str, ...] = WORLD_KINDS
    """World kinds, used in turn."""
    seed: int = 1000
    """World i has simulator seed ``seed + i``. Keep it far from the seeds you evaluate with
    (`mapkit eval` refuses a seed that made a training world)."""
    duration: float = 40.0
    """Seconds of flight per world."""
    rate: float = 5.0
    """Depth frames per second (at ~2 m/s, one frame per ~0.4 m: near-duplicate frames add time,
    not information)."""
    speed: tuple[float, float] = (1.0, 2.5)
    """Cruise speed range, m/s."""
    density_scale: tuple[float, float] = (0.8, 1.8)
    """Obstacle density relative to each world's default (denser worlds teach more avoidance)."""
    size_scale: tuple[float, float] = (0.55, 0.8)
    """Horizontal world extent relative to each kind's default (smaller worlds fuse faster and
    keep the obstacles close to the flight)."""
    tilt_deg: tuple[float, float] = (0.0, 15.0)
    """Camera pitch-down range, degrees."""
    cameras: tuple[CameraVariant, ...] = (
        CameraVariant(160, 120), CameraVariant(212, 120, 1.1), CameraVariant(192, 144, 0.9),
    )
    """Cameras drawn per world. World 0 always flies the first one with no tilt: `mapkit eval`
    renders the camera of the first training workspace. The network resizes every image to its input
    size; for the paper preset (360x640) a 640x360 camera keeps the detail it was built for."""
    noise_fraction: float = 0.5
    """Share of worlds recorded with RealSense-like depth noise (the rest exact)."""
    fuse_voxel: float = 0.05
    """TSDF voxel, metres."""
    esdf_voxel: float = 0.1
    """ESDF voxel, metres."""
    export: ExportConfig = field(default_factory=lambda: ExportConfig(stride=1))
    """Goal sampling of every world's tuples (the goal mix)."""
    workers: int = 0
    """Worlds processed at once (processes); 0 = one per available CPU core."""

    def validate(self) -> None:
        if self.worlds < 1:
            raise DatasetError(f"--worlds {self.worlds} must be at least 1")
        bad = [k for k in self.kinds if k not in WORLD_KINDS]
        if bad or not self.kinds:
            raise DatasetError(f"kinds {','.join(self.kinds)}: choose from {', '.join(WORLD_KINDS)}")
        for name in ("duration", "rate", "fuse_voxel", "esdf_voxel"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise DatasetError(f"{name} {v} must be a positive finite number")
        for name, lo_min, hi_max in (("speed", 1.0, 3.0), ("density_scale", 0.1, 5.0), ("size_scale", 0.3, 2.0),
                                     ("tilt_deg", 0.0, 45.0)):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo_min <= lo <= hi <= hi_max):
                raise DatasetError(f"{name} {lo} {hi}: need {lo_min} <= min <= max <= {hi_max}")
        for cam in self.cameras:
            if not (16 <= cam.width <= 4096 and 16 <= cam.height <= 4096 and np.isfinite(cam.fx_scale)
                    and 0.25 <= cam.fx_scale <= 4.0):
                raise DatasetError(f"cameras {cam.width}x{cam.height}:{cam.fx_scale}: need 16..4096 pixels a side "
                                   f"and a focal-length scale in 0.25..4")
        if not self.cameras:
            raise DatasetError("cameras names no camera; e.g. 160x120 or 640x360")
        if not 0 <= self.noise_fraction <= 1:
            raise DatasetError(f"noise_fraction {self.noise_fraction} must be in [0, 1]")
        if self.workers < 0:
            raise DatasetError(f"--workers {self.workers} must be >= 0 (0 = one per core)")
        self.export.validate()


@dataclass(frozen=True)
class WorldSpec:
    """Everything that defines one world of the dataset (recorded in its workspace)."""

    index: int
    name: str
    kind: str
    seed: int
    size: tuple[float, float, float]
    density: float
    speed: float
    tilt_deg: float
    width: int
    height: int
    fx: float
    noise: str


@dataclass
class DatasetSummary:
    root: Path
    done: list[str]
    skipped: list[str]
    failed: dict[str, str]
    frames: int
    tuples: int
    seconds: float


def world_specs(config: DatasetConfig) -> list[WorldSpec]:
    """The per-world parameters, deterministic in the config."""
    out = []
    for i in range(config.worlds):
        kind = config.kinds[i % len(config.kinds)]
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, i, 7]))
        X, Y, Z = DEFAULT_SIZES[kind]
        s = float(rng.uniform(*config.size_scale))
        cam = config.cameras[0] if i == 0 else config.cameras[int(rng.integers(len(config.cameras)))]
        tilt = 0.0 if i == 0 else float(rng.uniform(*config.tilt_deg))
        density = DEFAULT_DENSITIES[kind] * float(rng.uniform(*config.density_scale))
        if kind == "garage":
            density = min(density, 0.95)  # a fraction of occupied bays
        out.append(WorldSpec(
            index=i, name=f"{i:03d}-{kind}-s{config.seed + i}", kind=kind, seed=config.seed + i,
            size=(round(max(X * s, 12.0, MIN_SIZES[kind][0]), 2), round(max(Y * s, 10.0, MIN_SIZES[kind][1]), 2), Z),
            density=round(density, 4),
            speed=round(float(rng.uniform(*config.speed)), 2), tilt_deg=round(tilt, 1),
            width=cam.width, height=cam.height, fx=round(387.0 * cam.width / 640.0 * cam.fx_scale, 2),
            noise="realsense" if rng.random() < config.noise_fraction else "none",
        ))
    return out


# Measured on the 2-core development machine (cpu fusion, 0.05 m / 0.1 m voxels): per-world
# seconds ≈ fixed + per-frame cost; bytes per depth pixel after lz4 (frames + tuples).
_SECONDS_FIXED = 10.0
_SECONDS_PER_FRAME = 0.08
_BYTES_PER_PIXEL = 5.0
_BYTES_PER_MAP_VOXEL = 2.0


def _estimate(config: DatasetConfig, specs: list[WorldSpec]) -> tuple[float, float]:
    """(bytes on disk, CPU-seconds) the dataset's worlds ``specs`` will take, from measured per-frame figures."""
    size = 0.0
    seconds = 0.0
    for spec in specs:
        frames = config.duration * config.rate
        size += frames * spec.width * spec.height * _BYTES_PER_PIXEL
        size += float(np.prod(spec.size)) / config.esdf_voxel**3 * _BYTES_PER_MAP_VOXEL
        seconds += _SECONDS_FIXED + frames * _SECONDS_PER_FRAME * (spec.width * spec.height) / (160 * 120)
    return size, seconds


def _spec_record(spec: WorldSpec, config: DatasetConfig) -> dict:
    return {"mapkit_version": __version__, "world": asdict(spec), "duration": config.duration, "rate": config.rate,
            "fuse_voxel": config.fuse_voxel, "esdf_voxel": config.esdf_voxel, "export": asdict(config.export)}


def _is_done(ws: Path, spec: WorldSpec, config: DatasetConfig) -> bool:
    try:
        done = json.loads((ws / DONE).read_text())
    except (OSError, ValueError):
        return False
    # the record only for worlds that have one: a 200000-world request is refused in seconds
    return done.get("spec") == json.loads(json.dumps(_spec_record(spec, config)))


def build_world(spec: WorldSpec, config: DatasetConfig, ws: Path) -> tuple[int, int]:
    """Simulate one world's flight and run it through ingest → fuse → esdf → export into ``ws``.
    Returns (frames, tuples). Stale partial stores from a killed run are replaced."""
    from mapkit.esdf import EsdfConfig, build_esdf
    from mapkit.export import export_tuples
    from mapkit.fusion import FuseConfig, fuse
    from mapkit.sim import SimConfig, simulate

    record = _spec_record(spec, config)
    (ws / DONE).unlink(missing_ok=True)
    rec_dir = ws / "recording"
    rec_dir.mkdir(parents=True, exist_ok=True)
    sim = SimConfig(world=spec.kind, seed=spec.seed, duration=config.duration, rate=config.rate, width=spec.width,
                    height=spec.height, fx=spec.fx, noise=spec.noise, size=spec.size, density=spec.density,
                    speed=spec.speed, camera_tilt_deg=spec.tilt_deg, overwrite=True)
    result = simulate(sim, rec_dir / "flight", progress=False)
    fuse([result.bag_path], ws, FuseConfig(voxel=config.fuse_voxel), overwrite=True, progress=False)
    build_esdf(ws, EsdfConfig(voxel=config.esdf_voxel), overwrite=True, progress=False)
    summary = export_tuples(ws, config.export, overwrite=True, progress=False)
    tmp = ws / f".{DONE}.partial"
    tmp.write_text(json.dumps({"spec": record, "frames": len(result.stamps_ns), "tuples": summary.frames,
                               "export": summary.mix_dict()}, indent=2))
    os.replace(tmp, ws / DONE)
    return len(result.stamps_ns), summary.frames


def _worker(spec: WorldSpec, config: DatasetConfig, ws: str) -> tuple[int, int]:
    import torch

    torch.set_num_threads(1)  # one process per core; each stage's numpy/open3d work stays on it
    return build_world(spec, config, Path(ws))


def build_dataset(root: str | Path, config: DatasetConfig, *, progress: bool = True, dry_run: bool = False) -> DatasetSummary:
    """Generate ``config.worlds`` workspaces under ``root`` (resumable: complete worlds with the
    same parameters are skipped; a failed world is reported and the others go on)."""
    from tqdm import tqdm

    config.validate()
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise DatasetError(f"-o {root} is a file; pass a directory")
    specs = world_specs(config)
    need_bytes, need_seconds = _estimate(config, specs)
    root.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(root).free
    todo = [s for s in specs if not _is_done(root / s.name, s, config)]
    waiting = {s.name for s in todo}
    skipped = [s.name for s in specs if s.name not in waiting]
    workers = config.workers or available_cpus()
    frac = len(todo) / max(len(specs), 1)
    msg = (f"dataset: {len(specs)} worlds ({len(specs) - len(todo)} already complete), about "
           f"{need_bytes * frac / 1e9:.2f} GB and {need_seconds * frac / workers / 60:.0f} min on {workers} worker(s)")
    print(msg, flush=True)
    if need_bytes * frac > 0.9 * free:
        raise DatasetError(f"the dataset needs about {need_bytes * frac / 1e9:.1f} GB but {root} has "
                           f"{free / 1e9:.1f} GB free; lower --worlds or duration, or choose another -o")
    _write_manifest(root, config, specs)
    if dry_run:
        return DatasetSummary(root, [], skipped, {}, 0, 0, 0.0)
    t0 = time.perf_counter()
    done: list[str] = []
    failed: dict[str, str] = {}
    frames = tuples = 0
    bar = tqdm(total=len(todo), unit="world", desc="dataset", disable=not progress, dynamic_ncols=True)
    with ProcessPoolExecutor(max_workers=workers) as pool:
        pending: dict[Future, WorldSpec] = {pool.submit(_worker, s, config, str(root / s.name)): s for s in todo}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                spec = pending.pop(fut)
                try:
                    f, n = fut.result()
                    frames, tuples = frames + f, tuples + n
                    done.append(spec.name)
                except MapkitError as exc:
                    failed[spec.name] = str(exc)
                except Exception as exc:  # noqa: BLE001 - one bad world must not stop the others
                    failed[spec.name] = f"{type(exc).__name__}: {exc}"
                bar.update(1)
                bar.set_postfix(failed=len(failed))
    bar.close()
    return DatasetSummary(root, done, skipped, failed, frames, tuples, time.perf_counter() - t0)


def _write_manifest(root: Path, config: DatasetConfig, specs: list[WorldSpec]) -> None:
    data = {"kind": "mapkit.dataset", "mapkit_version": __version__, "config": json.loads(json.dumps(asdict(config))),
            "worlds": [asdict(s) for s in specs]}
    tmp = root / f".{MANIFEST}.partial"
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, root / MANIFEST)


def dataset_workspaces(root: str | Path) -> list[Path]:
    """The complete world workspaces of a dataset directory, in world order."""
    root = Path(root)
    if not (root / MANIFEST).exists():
        raise DatasetError(f"{root} holds no {MANIFEST}; make it with `mapkit dataset -o {root}`")
    specs = json.loads((root / MANIFEST).read_text())["worlds"]
    out = [root / s["name"] for s in specs if (root / s["name"] / DONE).exists()]
    if not out:
        raise DatasetError(f"no complete world in {root}; run (or resume) `mapkit dataset -o {root}`")
    return out


def split_worlds(root: str | Path, val_worlds: int) -> tuple[list[Path], list[Path]]:
    """(training, validation) workspaces of a dataset: the last ``val_worlds`` complete worlds are
    held out whole (they cycle through the kinds); world 0, whose camera evaluation renders, always
    trains."""
    worlds = dataset_workspaces(root)
    if val_worlds < 0 or val_worlds >= len(worlds):
        raise DatasetError(f"--val-worlds {val_worlds}: {root} has {len(worlds)} complete worlds; hold out between 0 "
                           f"and {len(worlds) - 1}")
    cut = len(worlds) - val_worlds
    return worlds[:cut], worlds[cut:]
