"""Simulate a UAV depth recording: world → flight → depth frames → bag + exact ground truth."""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from mapkit.bags import FORMATS, BagRecorder, output_path
from mapkit.sim._camera import NOISE_MODELS, CameraModel, apply_realsense_noise, camera_extrinsics, render_depth
from mapkit.sim._errors import SimError
from mapkit.sim._flight import Flight, _poses, plan_flight
from mapkit.sim._procedural import WORLD_KINDS, make_world
from mapkit.sim._world import World

DEPTH_TOPIC = "/camera/depth/image_rect_raw"
CAMERA_INFO_TOPIC = "/camera/depth/camera_info"
ODOM_TOPIC = "/odom"
WORLD_FRAME = "world"
BODY_FRAME = "base_link"
CAMERA_LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_depth_optical_frame"
DEPTH_ENCODING_CHOICES: tuple[str, ...] = ("16UC1", "32FC1", "compressedDepth")
ODOM_PER_FRAME = 4  # odometry at 4x the depth rate; every depth stamp is an odometry stamp


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated recording (same config + seed → same bytes)."""

    world: str = "forest"
    """World generator: forest, office or garage."""
    seed: int = 0
    """Seed for the world, the flight and the noise."""
    format: str = "mcap"
    """Output: mcap (bare .mcap, ROS2 CDR), ros2 (rosbag2 dir, sqlite3) or ros1 (.bag)."""
    duration: float = 10.0
    """Seconds of recording."""
    rate: float = 30.0
    """Depth frame rate, Hz (odometry and /tf at 4x)."""
    width: int = 640
    """Depth image width, pixels."""
    height: int = 480
    """Depth image height, pixels."""
    fx: float | None = None
    """Focal length, pixels; None → 387 * width / 640 (D435)."""
    min_range: float = 0.2
    """Nearest valid depth, metres."""
    max_range: float = 10.0
    """Farthest valid depth, metres."""
    noise: str = "none"
    """Depth noise: none (exact) or realsense (σ = 0.0015 z², holes, edge dropouts)."""
    depth_encoding: str = "16UC1"
    """16UC1 (mm), 32FC1 (m) or compressedDepth (PNG, 16UC1 inside)."""
    size: tuple[float, float, float] | None = None
    """World extent (x, y, z) metres; None → the world's default."""
    density: float | None = None
    """World obstacle density (see mapkit.sim.make_world); None → default."""
    speed: float = 1.5
    """Cruise speed, m/s (1..3)."""
    margin: float = 0.4
    """Smallest clearance of the body centre to any obstacle, metres."""
    camera_offset: tuple[float, float, float] = (0.08, 0.0, 0.02)
    """camera_link position in base_link (FLU), metres."""
    camera_tilt_deg: float = 0.0
    """Camera pitch down, degrees."""
    start_ns: int = 1_700_000_000_000_000_000
    """Stamp of the first frame, integer nanoseconds since the epoch."""
    compression: bool = True
    """Compress chunks (mcap zstd, ros1 lz4)."""
    overwrite: bool = False
    """Replace existing outputs (only once the new ones are complete)."""

    def camera(self) -> CameraModel:
        return CameraModel(width=self.width, height=self.height, fx=self.fx, min_range=self.min_range,
                           max_range=self.max_range)

    def validate(self) -> None:
        if self.world not in WORLD_KINDS:
            raise SimError(f"unknown world {self.world!r}; use one of {', '.join(WORLD_KINDS)}")
        if self.format not in FORMATS:
            raise SimError(f"unknown format {self.format!r}; use one of {', '.join(FORMATS)}")
        if self.noise not in NOISE_MODELS:
            raise SimError(f"unknown noise model {self.noise!r}; use one of {', '.join(NOISE_MODELS)}")
        if self.depth_encoding not in DEPTH_ENCODING_CHOICES:
            raise SimError(f"unknown depth encoding {self.depth_encoding!r}; use one of {', '.join(DEPTH_ENCODING_CHOICES)}")
        if not (0.5 <= self.rate <= 1000.0):
            raise SimError(f"rate {self.rate} Hz out of range; use 0.5..1000 Hz (e.g. rate = 30)")
        if not (0.0 < self.duration <= 3600.0):
            raise SimError(f"duration {self.duration} s out of range; use 0 < duration <= 3600 s")
        self.camera()  # checks the resolution and range


@dataclass
class SimResult:
    """What :func:`simulate` wrote, with the exact ground truth."""

    stamps_ns: np.ndarray
    """(N,) int64 depth stamps, ns."""
    T_world_body: np.ndarray
    """(N, 4, 4) float64 base_link poses at the depth stamps."""
    T_world_camera: np.ndarray
    """(N, 4, 4) float64 optical-frame poses at the depth stamps."""
    K: np.ndarray
    """(3, 3) float64 intrinsics (pixel-centre convention)."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    world: World
    """The world flown through (exact signed distance)."""
    bag_path: Path
    """The recording: OUT.mcap, OUT/ (rosbag2) or OUT.bag."""
    world_json: Path
    """<stem>.world.json: primitives, World.from_json restores it exactly."""
    world_ply: Path
    """<stem>.world.ply: tessellated mesh for display."""
    flight_npz: Path
    """<stem>.flight.npz: stamps_ns, T_world_body, T_world_camera, K, width, height."""
    path_length: float = 0.0
    """Metres flown during the recording."""
    duration: float = 0.0
    """Seconds from the first to the last depth frame."""
    counts: dict[str, int] = field(default_factory=dict)
    """Messages written per topic."""

    @property
    def paths(self) -> list[Path]:
        return [self.bag_path, self.world_json, self.world_ply, self.flight_npz]


class RenderedFlight(NamedTuple):
    """Return of :func:`render_flight`; unpacks as a tuple."""

    world: World
    stamps_ns: np.ndarray
    T_world_body: np.ndarray
    T_world_camera: np.ndarray
    K: np.ndarray
    depths: Iterator[np.ndarray]


def ground_truth_paths(bag: Path, format: str) -> tuple[Path, Path, Path]:
    """(<stem>.world.json, <stem>.world.ply, <stem>.flight.npz) beside a recording."""
    stem = bag.name[: -len(bag.suffix)] if format in ("mcap", "ros1") else bag.name
    return (bag.with_name(stem + ".world.json"), bag.with_name(stem + ".world.ply"),
            bag.with_name(stem + ".flight.npz"))


@dataclass
class _Plan:
    world: World
    trajectory: Flight
    odom_stamps: np.ndarray
    t_odom: np.ndarray
    T_base_link: np.ndarray
    T_link_optical: np.ndarray
    camera: CameraModel

    @property
    def depth_stamps(self) -> np.ndarray:
        return self.odom_stamps[::ODOM_PER_FRAME]


def _plan(config: SimConfig) -> _Plan:
    config.validate()
    world = make_world(config.world, seed=config.seed, size=config.size, density=config.density)
    n_frames = max(1, int(math.floor(config.duration * config.rate + 1e-9)))
    n_odom = n_frames * ODOM_PER_FRAME
    odom_rate = ODOM_PER_FRAME * config.rate
    # Integer-nanosecond stamps; depth stamps are every 4th odometry stamp by construction, and
    # equal start + round(i * 1e9 / rate).
    offsets = np.array([int(round(j * 1e9 / odom_rate)) for j in range(n_odom)], dtype=np.int64)
    odom_stamps = np.int64(config.start_ns) + offsets
    t_odom = offsets.astype(np.float64) * 1e-9
    traj = plan_flight(world, duration=float(t_odom[-1]) + 0.05, speed=config.speed, margin=config.margin,
                       seed=config.seed)
    T_base_link, T_link_optical = camera_extrinsics(offset=config.camera_offset, tilt_deg=config.camera_tilt_deg)
    return _Plan(world, traj, odom_stamps, t_odom, T_base_link, T_link_optical, config.camera())


def _depth_frames(plan: _Plan, config: SimConfig, T_world_camera: np.ndarray) -> Iterator[np.ndarray]:
    rays = plan.camera.rays()
    for i, T in enumerate(T_world_camera):
        depth = render_depth(plan.world, T, plan.camera, rays=rays)
        if config.noise == "realsense":
            # One generator per frame: frame i's noise does not depend on which frames ran before.
            rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), 11, i]))
            depth = apply_realsense_noise(depth, plan.camera, rng)
        yield depth


def render_flight(config: SimConfig) -> RenderedFlight:
    """Plan the flight of ``config``: its ground truth and a lazy iterator of the float32 (H, W) depth
    images :func:`simulate` writes (NaN invalid), one per stamp."""
    plan = _plan(config)
    t = plan.t_odom[::ODOM_PER_FRAME]
    T_world_body = plan.trajectory.T_world_body(t)
    T_world_camera = T_world_body @ plan.T_base_link @ plan.T_link_optical
    return RenderedFlight(plan.world, plan.depth_stamps.copy(), T_world_body, T_world_camera, plan.camera.K,
                          _depth_frames(plan, config, T_world_camera))


def simulate(config: SimConfig, out: str | os.PathLike[str], *, progress: bool = True) -> SimResult:
    """Simulate and write a recording plus ground truth beside it.

    Args:
        out: output path, with or without suffix (see mapkit.bags.output_path).
        progress: show a tqdm bar over frames on stderr.
    Raises:
        SimError: bad config, existing output without ``overwrite``, or no feasible flight.
    """
    config.validate()  # before looking at the outputs: a bad config is the first thing to fix
    bag = output_path(out, config.format)
    truth = ground_truth_paths(bag, config.format)
    for p in (bag, *truth):
        if p.exists() and not config.overwrite:
            raise SimError(f"output {p} exists; pass --overwrite or choose another -o")
    if not bag.parent.is_dir():
        raise SimError(f"output directory {bag.parent} does not exist; create it first")
    plan = _plan(config)
    odom = _odometry(plan)
    T_world_body = odom.T_world_body[::ODOM_PER_FRAME]
    T_world_camera = T_world_body @ plan.T_base_link @ plan.T_link_optical
    counts = _write_recording(bag, truth, plan, config, odom, T_world_body, T_world_camera, progress=progress)
    cam = plan.camera
    positions = T_world_body[:, :3, 3]
    return SimResult(
        stamps_ns=plan.depth_stamps.copy(), T_world_body=T_world_body, T_world_camera=T_world_camera, K=cam.K,
        width=cam.width, height=cam.height, world=plan.world, bag_path=bag, world_json=truth[0],
        world_ply=truth[1], flight_npz=truth[2],
        path_length=float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()),
        duration=float((plan.depth_stamps[-1] - plan.depth_stamps[0]) * 1e-9), counts=counts,
    )


class _Odometry(NamedTuple):
    """The flight at the odometry stamps."""

    T_world_body: np.ndarray
    """(M, 4, 4) body poses."""
    v_body: np.ndarray
    """(M, 3) m/s, body frame (REP 105)."""
    yaw_rate: np.ndarray
    """(M,) rad/s."""


def _odometry(plan: _Plan) -> _Odometry:
    """Poses, body-frame velocities and yaw rates of the planned flight at the odometry stamps."""
    p_odom, v_world, yaw, yaw_rate = plan.trajectory.sample(plan.t_odom)
    T_world_body_odom = _poses(p_odom, yaw)
    # Twist in the body frame (REP 105): v_body = R_world_body^T v_world; level flight → ω = (0,0,ψ').
    v_body = np.einsum("nji,nj->ni", T_world_body_odom[:, :3, :3], v_world)
    return _Odometry(T_world_body_odom, v_body, yaw_rate)


def _write_recording(bag: Path, truth: tuple[Path, Path, Path], plan: _Plan, config: SimConfig, odom: _Odometry,
                     T_world_body: np.ndarray, T_world_camera: np.ndarray, *, progress: bool) -> dict[str, int]:
    """Write the bag and the ground truth beside it, all or nothing → messages written per topic."""
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{bag.name}.", suffix=".truth.partial", dir=bag.parent))
    try:
        tmp_truth = [tmpdir / p.name for p in truth]
        _write_truth(tmp_truth, plan, T_world_body, T_world_camera)
        frames = _depth_frames(plan, config, T_world_camera)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(T_world_camera), unit="frame", desc="simulate", dynamic_ncols=True)
        with BagRecorder(bag, config.format, compression=config.compression, overwrite=config.overwrite) as rec:
            _write_messages(rec, plan, config, odom, frames, bar)
            if bar is not None:
                bar.close()
            # Ground truth goes into place just before the bag is renamed (all or nothing).
            for src, dst in zip(tmp_truth, truth, strict=True):
                os.replace(src, dst)
    except BaseException:
        for dst in truth:  # a failed run leaves no ground truth for a recording that is not there
            if dst.exists() and not bag.exists():
                dst.unlink()
        raise
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return dict(rec.counts)


def _write_truth(paths: list[Path], plan: _Plan, T_world_body: np.ndarray, T_world_camera: np.ndarray) -> None:
    """<stem>.world.json, <stem>.world.ply and <stem>.flight.npz at ``paths``."""
    import open3d as o3d

    plan.world.to_json(paths[0])
    o3d.io.write_triangle_mesh(paths[1], plan.world.mesh(), write_ascii=False, compressed=True)
    cam = plan.camera
    np.savez(paths[2], stamps_ns=plan.depth_stamps, T_world_body=T_world_body, T_world_camera=T_world_camera,
             K=cam.K, width=cam.width, height=cam.height)


def _write_messages(rec: BagRecorder, plan: _Plan, config: SimConfig, odom: _Odometry,
                    frames: Iterator[np.ndarray], bar: Any) -> None:
    """tf_static once, then odometry and /tf at every odometry stamp, depth and camera info at every 4th."""
    cam = plan.camera
    start = int(plan.odom_stamps[0])
    rec.write_tf_static(start, [(plan.T_base_link, BODY_FRAME, CAMERA_LINK_FRAME, start),
                                (plan.T_link_optical, CAMERA_LINK_FRAME, OPTICAL_FRAME, start)])
    for j, stamp in enumerate(plan.odom_stamps):
        stamp = int(stamp)
        T = odom.T_world_body[j]
        rec.write_odometry(ODOM_TOPIC, stamp, T, frame_id=WORLD_FRAME, child_frame_id=BODY_FRAME,
                           linear_velocity=odom.v_body[j], angular_velocity=(0.0, 0.0, odom.yaw_rate[j]))
        rec.write_tf(stamp, [(T, WORLD_FRAME, BODY_FRAME, stamp)])
        if j % ODOM_PER_FRAME:
            continue
        depth = next(frames)
        if config.depth_encoding == "compressedDepth":
            rec.write_compressed_depth(DEPTH_TOPIC + "/compressedDepth", stamp, depth, frame_id=OPTICAL_FRAME,
                                       encoding="16UC1")
        else:
            rec.write_depth(DEPTH_TOPIC, stamp, depth, frame_id=OPTICAL_FRAME, encoding=config.depth_encoding)
        rec.write_camera_info(CAMERA_INFO_TOPIC, stamp, cam.K, cam.width, cam.height, frame_id=OPTICAL_FRAME)
        if bar is not None:
            bar.update(1)
