"""Geometry for drawing: camera frustums, polylines, flight-corridor prisms, and picking a point
with a ray (a click in the browser)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mapkit.viz._errors import VizError

_CUBE_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Points (..., 3) in frame b → frame a with the 4×4 transform ``T_a_b``."""
    T = np.asarray(T_a_b, dtype=np.float64)
    if T.shape != (4, 4):
        raise VizError(f"transform must be 4x4; got {T.shape}")
    p = np.asarray(points_b, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def frustum_segments(
    K: np.ndarray, width: int, height: int, T_world_camera: np.ndarray, *, depth: float = 0.5
) -> np.ndarray:
    """Line segments of camera frustums, world frame: float64 (F·8, 2, 3), per camera 4 segments from the
    optical centre to the image corners at `depth` metres along the optical axis, then the rectangle's
    4 edges. `K` (3, 3) puts integer pixels at pixel centres; `T_world_camera` (4, 4) or (F, 4, 4)
    are optical poses (z forward, x right, y down).
    """
    Km = np.asarray(K, dtype=np.float64)
    if Km.shape != (3, 3) or Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise VizError(f"K must be a 3x3 intrinsic matrix with fx, fy > 0; got {Km.tolist()}")
    if width < 1 or height < 1:
        raise VizError(f"image size {width}x{height} must be positive")
    if not depth > 0:
        raise VizError(f"depth={depth!r} must be > 0 metres")
    T = np.asarray(T_world_camera, dtype=np.float64)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise VizError(f"T_world_camera must be (4, 4) or (F, 4, 4); got {T.shape}")
    uv = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    rays = np.linalg.solve(Km, np.concatenate([uv, np.ones((4, 1))], axis=1).T).T  # (4, 3), z = 1
    corners_cam = rays * depth
    corners = np.einsum("fij,cj->fci", T[:, :3, :3], corners_cam) + T[:, None, :3, 3]  # (F, 4, 3)
    centre = np.broadcast_to(T[:, None, :3, 3], corners.shape)
    spokes = np.stack([centre, corners], axis=2)  # (F, 4, 2, 3)
    rim = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)
    return np.concatenate([spokes, rim], axis=1).reshape(-1, 2, 3)


def polyline_segments(points: np.ndarray, colors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """A polyline (N, 3) as segments (N−1, 2, 3); per-vertex colours (N, 3) become per-end colours
    (N−1, 2, 3)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise VizError(f"points must have shape (N, 3); got {p.shape}")
    seg = np.stack([p[:-1], p[1:]], axis=1)
    if colors is None:
        return seg, None
    c = np.asarray(colors)
    if c.shape != p.shape:
        raise VizError(f"colors must have shape {p.shape} (one per point); got {c.shape}")
    return seg, np.stack([c[:-1], c[1:]], axis=1)


# ------------------------------------------------------------------------------------ corridor
def corridor_cross_section(direction: np.ndarray, half_width: float) -> np.ndarray:
    """The exact cross-section of the flight corridor of :func:`mapkit.trajopt.min_snap` around a
    segment with `direction` (3,): ``corridor=W`` bounds each axis component of the deviation from the
    segment's line by ±W, so it is the plane ⊥ u cut by the cube [−W, W]³.

    Returns float64 (P, 3), P ∈ 4..6: the polygon's vertices (offsets ⊥ u), counter-clockwise seen
    from the tip of u. A zero `direction` raises (its corridor is the cube).
    """
    W = float(half_width)
    if not W > 0:
        raise VizError(f"corridor half-width {half_width!r} must be > 0 metres")
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    n = np.linalg.norm(d)
    if not n > 1e-9:
        raise VizError("a zero-length segment has no cross-section (its corridor is the cube [-W, W]^3)")
    u = d / n
    cube = W * np.array([[1 if (i >> k) & 1 else -1 for k in range(3)] for i in range(8)], dtype=np.float64)
    f = cube @ u
    tol = 1e-12 * W
    pts = []
    for a, b in _CUBE_EDGES:
        fa, fb = f[a], f[b]
        if abs(fa) <= tol:
            pts.append(cube[a])
        if abs(fb) <= tol:
            pts.append(cube[b])
        if (fa < -tol and fb > tol) or (fa > tol and fb < -tol):
            pts.append(cube[a] + (fa / (fa - fb)) * (cube[b] - cube[a]))
    P = np.array(pts)
    P -= np.outer(P @ u, u)  # exact in-plane (removes round-off along u)
    keep: list[np.ndarray] = []
    for q in P:
        if all(np.abs(q - k).max() > 1e-9 * W for k in keep):
            keep.append(q)
    P = np.array(keep)
    e1 = P[np.argmax(np.linalg.norm(P, axis=1))]
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    order = np.argsort(np.arctan2(P @ e2, P @ e1))
    return P[order]


@dataclass(frozen=True)
class CorridorGeometry:
    """Flight-corridor prisms, one per segment, as one triangle mesh (world frame)."""

    vertices: np.ndarray
    """float64 (V, 3)."""
    faces: np.ndarray
    """int64 (F, 3), outward-facing."""
    edges: np.ndarray
    """float64 (E, 2, 3): the prisms' edges (for an outline)."""
    face_segment: np.ndarray
    """int64 (F,): which segment each triangle belongs to."""
    sections: list[np.ndarray]
    """Per segment, its cross-section polygon (P, 3) in the solving frame (offsets ⊥ the segment)."""
    num_segments: int


def corridor_prisms(
    waypoints: np.ndarray, half_width: float | np.ndarray, *, T_world_frame: np.ndarray | None = None
) -> CorridorGeometry:
    """The corridor :func:`mapkit.trajopt.min_snap` enforces with ``corridor=half_width`` (W, metres,
    scalar or (M,)): around every segment a → b of `waypoints` (M+1, 3) (unit direction u), the prism
    a − W·u + t(b − a + 2W·u) + x, t ∈ [0, 1], x in :func:`corridor_cross_section`; a zero-length
    segment gets the cube of side 2W around a. `waypoints` are in the frame the trajectory is solved
    in; `T_world_frame` (4, 4) maps it to the world (identity if None).
    """
    w = np.asarray(waypoints, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or len(w) < 2:
        raise VizError(f"waypoints must have shape (M+1, 3) with M >= 1; got {w.shape}")
    M = len(w) - 1
    hw = np.broadcast_to(np.asarray(half_width, dtype=np.float64), (M,)) if np.ndim(half_width) == 0 else np.asarray(half_width, dtype=np.float64)
    if hw.shape != (M,) or not np.all(np.isfinite(hw)) or not np.all(hw > 0):
        raise VizError(f"half_width must be > 0 metres, a scalar or one per segment ({M}); got {half_width!r}")
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    edges: list[np.ndarray] = []
    face_seg: list[np.ndarray] = []
    sections: list[np.ndarray] = []
    base = 0
    for m in range(M):
        a, b = w[m], w[m + 1]
        if np.linalg.norm(b - a) > 1e-9:
            poly = corridor_cross_section(b - a, hw[m])
            u = (b - a) / np.linalg.norm(b - a)
            lo, hi = a - hw[m] * u + poly, b + hw[m] * u + poly  # CCW seen from the tip of u
        else:  # min_snap bounds |p - a| per axis: the cube around a
            W = hw[m]
            poly = W * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
            lo, hi = a + poly + [0, 0, -W], a + poly + [0, 0, W]
        P = len(poly)
        sections.append(poly)
        verts += [lo, hi]
        idx_lo, idx_hi = base + np.arange(P), base + P + np.arange(P)
        nxt = np.roll(np.arange(P), -1)
        side = np.concatenate([
            np.stack([idx_lo, idx_lo[nxt], idx_hi[nxt]], axis=1),
            np.stack([idx_lo, idx_hi[nxt], idx_hi], axis=1),
        ])
        cap_lo = np.stack([np.full(P - 2, idx_lo[0]), idx_lo[2:], idx_lo[1:-1]], axis=1)  # faces −u
        cap_hi = np.stack([np.full(P - 2, idx_hi[0]), idx_hi[1:-1], idx_hi[2:]], axis=1)  # faces +u
        f = np.concatenate([side, cap_lo, cap_hi])
        faces.append(f)
        face_seg.append(np.full(len(f), m))
        edges += [np.stack([lo, lo[nxt]], axis=1), np.stack([hi, hi[nxt]], axis=1), np.stack([lo, hi], axis=1)]
        base += 2 * P
    V = np.concatenate(verts)
    E = np.concatenate(edges)
    if T_world_frame is not None:
        V = transform_points(T_world_frame, V)
        E = transform_points(T_world_frame, E)
    return CorridorGeometry(
        vertices=V, faces=np.concatenate(faces).astype(np.int64), edges=E,
        face_segment=np.concatenate(face_seg).astype(np.int64), sections=sections, num_segments=M,
    )


# -------------------------------------------------------------------------------------- picking
def ray_plane(origin: np.ndarray, direction: np.ndarray, *, axis: str, position: float) -> np.ndarray | None:
    """Where the ray origin + t·direction (t > 0) meets the plane ``axis = position``; None if it
    never does (parallel or behind)."""
    a = "xyz".index(axis)
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    if abs(d[a]) < 1e-12:
        return None
    t = (position - o[a]) / d[a]
    if not t > 0:
        return None
    p = o + t * d
    p[a] = position
    return p


def ray_surface(esdf_map: Any, origin: np.ndarray, direction: np.ndarray, *, max_distance: float = 500.0) -> np.ndarray | None:
    """The first point where the ray (origin, direction) reaches the map's zero level (sphere
    tracing on the smoothed ESDF inside the grid's box of voxel centres); None if it leaves the
    box first."""
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    lo, hi = esdf_map.bounds
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.where(d != 0, (lo - o) / d, -np.inf)
        t1 = np.where(d != 0, (hi - o) / d, np.inf)
    inside_axis = (d != 0) | ((o >= lo) & (o <= hi))
    if not inside_axis.all():
        return None
    t_near = float(np.max(np.minimum(t0, t1)))
    t_far = float(np.min(np.maximum(t0, t1)))
    t = max(t_near, 0.0)
    if t > t_far:
        return None
    step_min = 0.25 * esdf_map.voxel_size
    t_end = min(t_far, max_distance)
    while t <= t_end:
        p = o + t * d
        dist, _ = esdf_map.query(p[None], outside="clamp")
        dist = float(dist[0])
        if dist <= 0.0:
            return p
        t += max(dist, step_min)
    return None


def pick_point(
    origin: np.ndarray,
    direction: np.ndarray,
    *,
    plane: tuple[str, float, np.ndarray] | None = None,
    esdf_map: Any = None,
    standoff: float = 0.5,
) -> tuple[np.ndarray | None, str]:
    """A 3-D goal for a click ray: (point or None, "slice" | "surface" | "none"). Tries the visible slice
    `plane` = (axis, position, corners_world (4, 3)) within its corners, then the map surface
    (:func:`ray_surface`) pulled back `standoff` metres towards the viewer."""
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    if plane is not None:
        axis, position, corners = plane
        p = ray_plane(origin, d, axis=axis, position=position)
        if p is not None:
            lo, hi = np.min(corners, axis=0), np.max(corners, axis=0)
            if np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9):
                return p, "slice"
    if esdf_map is not None:
        p = ray_surface(esdf_map, origin, d)
        if p is not None:
            return p - standoff * d, "surface"
    return None, "none"
