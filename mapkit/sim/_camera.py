"""A RealSense-D435-like depth camera: intrinsics, mounting, exact rendering and a noise model.

Integer (u, v) is the centre of a pixel (``u = fx*x/z + cx``); rendered depth is the optical z of the
first hit through the pixel centre, NaN outside [min_range, max_range].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapkit.sim._errors import SimError
from mapkit.sim._world import World, ray_entry

NOISE_MODELS: tuple[str, ...] = ("none", "realsense")

# Optical axes expressed in the FLU camera_link: z_opt = x_link, x_opt = -y_link, y_opt = -z_link.
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

# D435 depth stream at 640x480: fx = fy ≈ 387 px (≈ 87° x 58° field of view).
D435_FX_640 = 387.0


@dataclass(frozen=True)
class CameraModel:
    """Pinhole depth camera with pixel-centre convention."""

    width: int = 640
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    fx: float | None = None
    """Focal length in pixels; None → 387 * width / 640 (a D435 scaled to the resolution)."""
    fy: float | None = None
    """Focal length in pixels; None → same as fx."""
    min_range: float = 0.2
    """Nearest valid depth (metres); closer → NaN."""
    max_range: float = 10.0
    """Farthest valid depth (metres); farther → NaN."""

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 8 or v > 4096:
                raise SimError(f"bad resolution {name}={v!r}; use an integer 8..4096 (e.g. width = 640, height = 480)")
        if not (0.0 < self.min_range < self.max_range) or not math.isfinite(self.max_range):
            raise SimError(f"bad depth range {self.min_range}..{self.max_range} m; need 0 < min_range < max_range")
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise SimError(f"bad focal length {name}={v!r}; use a positive number of pixels")

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 intrinsics; cx = (W-1)/2, cy = (H-1)/2 (pixel-centre convention)."""
        fx = self.fx if self.fx is not None else D435_FX_640 * self.width / 640.0
        fy = self.fy if self.fy is not None else fx
        return np.array([[fx, 0.0, (self.width - 1) / 2.0], [0.0, fy, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])

    def rays(self) -> np.ndarray:
        """(H*W, 3) ray directions in the optical frame with z = 1, row-major (v, u)."""
        K = self.K
        u = (np.arange(self.width, dtype=np.float64) - K[0, 2]) / K[0, 0]
        v = (np.arange(self.height, dtype=np.float64) - K[1, 2]) / K[1, 1]
        uu, vv = np.meshgrid(u, v, indexing="xy")
        return np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1)


def camera_extrinsics(*, offset: tuple[float, float, float] = (0.08, 0.0, 0.02), tilt_deg: float = 0.0
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(T_base_cameralink, T_cameralink_optical): the link sits ``offset`` (FLU, metres) from
    base_link, pitched down by ``tilt_deg`` (positive = looking down)."""
    T_base_link = np.eye(4)
    th = math.radians(tilt_deg)
    # Pitch about +y (FLU): positive angle turns x towards -z, i.e. looks down.
    T_base_link[:3, :3] = np.array([[math.cos(th), 0.0, math.sin(th)], [0.0, 1.0, 0.0],
                                    [-math.sin(th), 0.0, math.cos(th)]])
    T_base_link[:3, 3] = offset
    T_link_optical = np.eye(4)
    T_link_optical[:3, :3] = R_LINK_OPTICAL
    return T_base_link, T_link_optical


def _aabb_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def render_depth(world: World, T_world_camera: np.ndarray, camera: CameraModel, *,
                 rays: np.ndarray | None = None) -> np.ndarray:
    """Exact depth image (H, W) float32: optical z of the first hit, NaN outside the range. Each
    primitive is cast (float64, analytic) only on the pixels its bounding box projects to."""
    T = np.asarray(T_world_camera, dtype=np.float64)
    R, o = T[:3, :3], T[:3, 3]
    d_cam = camera.rays() if rays is None else rays
    d_world = d_cam @ R.T
    W, H = camera.width, camera.height
    K = camera.K
    depth: np.ndarray = np.full(H * W, np.inf)  # flat while rays are cast, (H, W) at the end
    # A hit at depth <= max_range lies within this distance of the camera.
    reach = camera.max_range * float(np.sqrt((d_cam ** 2).sum(axis=1)).max())
    R_cw = R.T
    candidates = []
    for prim in world.primitives:
        box = prim.aabb()
        if box is None:  # half spaces cover the whole image
            depth = np.minimum(depth, ray_entry(o, d_world, prim))
            continue
        lo, hi = box
        dist = float(np.linalg.norm(np.maximum(np.maximum(lo - o, o - hi), 0.0)))
        if dist <= reach:
            candidates.append((dist, prim, lo, hi))
    # Near primitives first: their hits let farther ones skip pixels already closer.
    candidates.sort(key=lambda c: c[0])
    for _, prim, lo, hi in candidates:
        pc = (_aabb_corners(lo, hi) - o) @ R_cw.T  # corners in the optical frame
        z_near = float(pc[:, 2].min())  # optical z is linear: no point of the box is nearer
        if float(pc[:, 2].max()) <= 0.0 or z_near > camera.max_range:
            continue  # entirely behind the camera or beyond the range
        if z_near > 1e-6:
            u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
            v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
            # The box's projection is the hull of its corners' projections: test those pixels.
            u0, u1 = max(int(math.floor(u.min())), 0), min(int(math.ceil(u.max())), W - 1)
            v0, v1 = max(int(math.floor(v.min())), 0), min(int(math.ceil(v.max())), H - 1)
            if u0 > u1 or v0 > v1:
                continue
            idx = (np.arange(v0, v1 + 1)[:, None] * W + np.arange(u0, u1 + 1)[None, :]).ravel()
            idx = idx[depth[idx] > z_near]
        else:
            idx = np.flatnonzero(depth > max(z_near, 0.0))
        if len(idx):
            depth[idx] = np.minimum(depth[idx], ray_entry(o, d_world[idx], prim))
    depth = depth.reshape(H, W)
    valid = (depth >= camera.min_range) & (depth <= camera.max_range)
    return np.where(valid, depth, np.nan).astype(np.float32)


def apply_realsense_noise(depth: np.ndarray, camera: CameraModel, rng: np.random.Generator) -> np.ndarray:
    """Structured-light-like noise: Gaussian with σ = 0.0015·z² (metres), a few random holes (elliptic
    blobs, 6 a frame on average), and dropouts of half the pixels at depth discontinuities. Returns a
    new float32 image."""
    sigma_z2, blobs_per_frame, edge_dropout = 0.0015, 6.0, 0.5
    out = depth.astype(np.float64).copy()
    H, W = out.shape
    valid = np.isfinite(out)
    out[valid] += rng.normal(0.0, 1.0, size=int(valid.sum())) * sigma_z2 * out[valid] ** 2
    # Edge dropouts: stereo matching fails where depth jumps (> 4 % between neighbours).
    z = np.where(valid, out, np.inf)
    jump = np.zeros((H, W), dtype=bool)
    with np.errstate(invalid="ignore"):
        dv = np.abs(np.diff(z, axis=0)) > 0.04 * np.minimum(z[1:], z[:-1])
        du = np.abs(np.diff(z, axis=1)) > 0.04 * np.minimum(z[:, 1:], z[:, :-1])
    jump[1:] |= dv
    jump[:-1] |= dv
    jump[:, 1:] |= du
    jump[:, :-1] |= du
    drop = jump & (rng.random((H, W)) < edge_dropout)
    # Holes: small random ellipses, size scaled with the resolution.
    n_blobs = rng.poisson(blobs_per_frame)
    scale = W / 640.0
    vv, uu = np.mgrid[0:H, 0:W]
    for _ in range(int(n_blobs)):
        cu, cv = rng.uniform(0, W), rng.uniform(0, H)
        ru, rv = rng.uniform(1.5, 8.0, size=2) * scale + 0.5
        u0, u1 = int(max(cu - ru - 1, 0)), int(min(cu + ru + 2, W))
        v0, v1 = int(max(cv - rv - 1, 0)), int(min(cv + rv + 2, H))
        sub = ((uu[v0:v1, u0:u1] - cu) / ru) ** 2 + ((vv[v0:v1, u0:u1] - cv) / rv) ** 2 <= 1.0
        drop[v0:v1, u0:u1] |= sub
    out[drop] = np.nan
    out[~((out >= camera.min_range) & (out <= camera.max_range))] = np.nan
    return out.astype(np.float32)
