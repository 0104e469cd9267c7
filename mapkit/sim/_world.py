"""Worlds made of analytic primitives (float64, metres, world frame ENU z-up) with an exact signed
distance and analytic ray casting.

The world's signed distance is the minimum over primitives: exact in free space and on surfaces;
inside obstacles the sign is right and ``|d|`` is a lower bound of the depth (overlapping primitives,
e.g. a trunk standing in the ground, make it conservative). :meth:`World.mesh` is a tessellated copy
for display.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.sim._errors import SimError

_CHUNK = 16384  # points per SDF block: bounds the (points x primitives) temporaries


# ---------------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Box:
    """Solid box: ``center`` (3,), ``half_extents`` (3,) along its own axes, rotated by ``yaw``
    (radians, about +z)."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    yaw: float = 0.0

    kind = "box"

    def aabb(self) -> np.ndarray:
        c, s = abs(math.cos(self.yaw)), abs(math.sin(self.yaw))
        hx, hy, hz = self.half_extents
        ext = np.array([c * hx + s * hy, s * hx + c * hy, hz])
        return np.stack([np.asarray(self.center) - ext, np.asarray(self.center) + ext])


@dataclass(frozen=True)
class Cylinder:
    """Solid finite cylinder of ``radius`` around the segment ``a``–``b`` (flat end caps)."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float

    kind = "cylinder"

    def aabb(self) -> np.ndarray:
        a, b = np.asarray(self.a), np.asarray(self.b)
        u = (b - a) / np.linalg.norm(b - a)
        # A disc of radius r with normal u extends r*sqrt(1-u_i^2) along axis i.
        ext = self.radius * np.sqrt(np.clip(1.0 - u * u, 0.0, 1.0))
        return np.stack([np.minimum(a, b) - ext, np.maximum(a, b) + ext])


@dataclass(frozen=True)
class Capsule:
    """Points within ``radius`` of the segment ``a``–``b`` (cylinder with hemispherical ends)."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float

    kind = "capsule"

    def aabb(self) -> np.ndarray:
        a, b = np.asarray(self.a), np.asarray(self.b)
        return np.stack([np.minimum(a, b) - self.radius, np.maximum(a, b) + self.radius])


@dataclass(frozen=True)
class HalfSpace:
    """Solid half space ``{p : normal·p < offset}``; ``normal`` (unit) points into free space.

    Floor at z=0: ``normal=(0,0,1), offset=0``; ceiling at z=h: ``normal=(0,0,-1), offset=-h``.
    """

    normal: tuple[float, float, float]
    offset: float

    kind = "halfspace"

    def aabb(self) -> None:
        return None


Primitive = Box | Cylinder | Capsule | HalfSpace


def _t3(x: Iterable[float]) -> tuple[float, float, float]:
    v = tuple(float(e) for e in x)
    if len(v) != 3:
        raise SimError(f"expected 3 coordinates, got {v!r}")
    return v


def primitive_to_dict(prim: Primitive) -> dict[str, Any]:
    """The primitive as JSON data: ``type`` then its fields in order (tuples as lists)."""
    return {"type": prim.kind, **{f.name: list(v) if isinstance(v := getattr(prim, f.name), tuple) else v
                                  for f in fields(prim)}}


def primitive_from_dict(d: dict[str, Any]) -> Primitive:
    """Inverse of :func:`primitive_to_dict`."""
    kind = d.get("type")
    if kind == "box":
        return Box(_t3(d["center"]), _t3(d["half_extents"]), float(d.get("yaw", 0.0)))
    if kind == "halfspace":
        return HalfSpace(_t3(d["normal"]), float(d["offset"]))
    if kind in ("cylinder", "capsule"):
        return (Cylinder if kind == "cylinder" else Capsule)(_t3(d["a"]), _t3(d["b"]), float(d["radius"]))
    raise SimError(f"unknown primitive type {kind!r} in world file; expected box, cylinder, capsule or halfspace")


# ------------------------------------------------------------------ vectorised SDFs (N x M)
def _sdf_boxes(p: np.ndarray, C: np.ndarray, H: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    dx = p[:, None, 0] - C[None, :, 0]
    dy = p[:, None, 1] - C[None, :, 1]
    # Rotate into the box frame (R(yaw)^T).
    lx = np.abs(c * dx + s * dy) - H[None, :, 0]
    ly = np.abs(-s * dx + c * dy) - H[None, :, 1]
    lz = np.abs(p[:, None, 2] - C[None, :, 2]) - H[None, :, 2]
    outside = np.sqrt(np.maximum(lx, 0) ** 2 + np.maximum(ly, 0) ** 2 + np.maximum(lz, 0) ** 2)
    inside = np.minimum(np.maximum(np.maximum(lx, ly), lz), 0.0)
    return outside + inside


def _axis_coords(p: np.ndarray, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axial coordinate s (from A), radial distance rho, and length L of each segment."""
    ab = B - A
    L = np.linalg.norm(ab, axis=1)
    u = ab / np.where(L > 0, L, 1.0)[:, None]  # a zero-length capsule is a sphere: any axis works
    ap = p[:, None, :] - A[None, :, :]
    s = np.einsum("nmk,mk->nm", ap, u)
    rho2 = np.einsum("nmk,nmk->nm", ap, ap) - s * s
    return s, np.sqrt(np.maximum(rho2, 0.0)), L


def _sdf_cylinders(p: np.ndarray, A: np.ndarray, B: np.ndarray, R: np.ndarray) -> np.ndarray:
    s, rho, L = _axis_coords(p, A, B)
    dr = rho - R[None, :]
    da = np.abs(s - 0.5 * L[None, :]) - 0.5 * L[None, :]
    outside = np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(da, 0) ** 2)
    return outside + np.minimum(np.maximum(dr, da), 0.0)


def _sdf_capsules(p: np.ndarray, A: np.ndarray, B: np.ndarray, R: np.ndarray) -> np.ndarray:
    s, rho, L = _axis_coords(p, A, B)
    sc = np.clip(s, 0.0, L[None, :])
    # distance to the nearest point of the segment: sqrt(rho^2 + (s - sc)^2)
    return np.sqrt(rho * rho + (s - sc) ** 2) - R[None, :]


def _sdf_halfspaces(p: np.ndarray, Nrm: np.ndarray, off: np.ndarray) -> np.ndarray:
    return p @ Nrm.T - off[None, :]


_SDF: dict[str, Callable[..., np.ndarray]] = {"box": _sdf_boxes, "cylinder": _sdf_cylinders, "capsule": _sdf_capsules,
                                             "halfspace": _sdf_halfspaces}


# ------------------------------------------------------------------ ray entry (M rays, one primitive)
_BIG = np.inf


def _ray_box(o: np.ndarray, d: np.ndarray, box: Box) -> np.ndarray:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    rel = o - np.asarray(box.center)
    ol = (c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], rel[2])  # origin in the box frame
    dx, dy = d[:, 0], d[:, 1]
    dl = (dx, dy, d[:, 2]) if box.yaw == 0.0 else (c * dx + s * dy, -s * dx + c * dy, d[:, 2])
    tmin = np.full(len(d), -np.inf)
    tmax = np.full(len(d), np.inf)
    # Slabs per axis; a ray parallel to a slab gets +-inf (or NaN exactly on its face: a miss).
    with np.errstate(divide="ignore", invalid="ignore"):
        for dli, oli, hi in zip(dl, ol, box.half_extents, strict=True):
            inv = 1.0 / dli
            t1 = (-hi - oli) * inv
            t2 = (hi - oli) * inv
            tmin = np.maximum(tmin, np.minimum(t1, t2))
            tmax = np.minimum(tmax, np.maximum(t1, t2))
        hit = (tmax >= tmin) & (tmax >= 0.0)
    return np.where(hit, np.maximum(tmin, 0.0), _BIG)


def _quadratic_interval(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval [t0, t1] where A t^2 + B t + C <= 0 (A >= 0); empty → (inf, -inf)."""
    disc = B * B - 4.0 * A * C
    ok = disc >= 0.0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    # Numerically stable roots: q = -(B + sign(B) sqrt(disc)) / 2, roots q/A and C/q.
    q = -0.5 * (B + np.where(B >= 0.0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = q / A
        r2 = C / q
    t0 = np.minimum(r1, r2)
    t1 = np.maximum(r1, r2)
    degenerate = A <= 1e-300  # ray parallel to the axis: inside for all t or never
    t0 = np.where(degenerate, np.where(C <= 0, -np.inf, np.inf), np.where(ok, t0, np.inf))
    t1 = np.where(degenerate, np.where(C <= 0, np.inf, -np.inf), np.where(ok, t1, -np.inf))
    # q == 0 happens only when B == 0 and disc == 0 (tangent at t=0): both roots 0.
    with np.errstate(invalid="ignore"):
        bad = ~degenerate & ok & ~(np.isfinite(t0) & np.isfinite(t1))
    t0 = np.where(bad, 0.0, t0)
    t1 = np.where(bad, 0.0, t1)
    return t0, t1


def _ray_sphere(o: np.ndarray, d: np.ndarray, center: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    oc = o - center
    A = np.einsum("mk,mk->m", d, d)
    B = 2.0 * (d @ oc)
    C = np.full_like(A, oc @ oc - r * r)
    return _quadratic_interval(A, B, C)


def _ray_cylinder_interval(
    o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, r: float
) -> tuple[np.ndarray, np.ndarray]:
    ab = b - a
    L = float(np.linalg.norm(ab))
    if L == 0.0:  # zero-length capsule: only its end spheres exist
        empty = np.full(len(d), np.inf)
        return empty, -empty
    u = ab / L
    oa = o - a
    od = float(oa @ u)
    dd = d @ u
    op = oa - od * u
    dp = d - dd[:, None] * u[None, :]
    A = np.einsum("mk,mk->m", dp, dp)
    B = 2.0 * (dp @ op)
    C = np.full_like(A, op @ op - r * r)
    ts0, ts1 = _quadratic_interval(A, B, C)
    # Axial slab 0 <= od + t*dd <= L.
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - od) / dd
        tb = (L - od) / dd
    par = dd == 0.0
    inside_slab = 0.0 <= od <= L
    tz0 = np.where(par, -np.inf if inside_slab else np.inf, np.minimum(ta, tb))
    tz1 = np.where(par, np.inf if inside_slab else -np.inf, np.maximum(ta, tb))
    return np.maximum(ts0, tz0), np.minimum(ts1, tz1)


def _entry(t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    hit = (t1 >= t0) & (t1 >= 0.0)
    return np.where(hit, np.maximum(t0, 0.0), _BIG)


def ray_entry(o: np.ndarray, d: np.ndarray, prim: Primitive) -> np.ndarray:
    """Parameter t >= 0 of the first entry of rays o + t d into ``prim`` (inf: no hit)."""
    if isinstance(prim, Box):
        return _ray_box(o, d, prim)
    if isinstance(prim, Cylinder):
        return _entry(*_ray_cylinder_interval(o, d, np.asarray(prim.a), np.asarray(prim.b), prim.radius))
    if isinstance(prim, Capsule):
        # A capsule is the union of a cylinder and two balls: first entry = min of their entries.
        a, b = np.asarray(prim.a), np.asarray(prim.b)
        t = _entry(*_ray_cylinder_interval(o, d, a, b, prim.radius))
        t = np.minimum(t, _entry(*_ray_sphere(o, d, a, prim.radius)))
        return np.minimum(t, _entry(*_ray_sphere(o, d, b, prim.radius)))
    n = np.asarray(prim.normal)
    h = float(n @ o) - prim.offset  # height of the origin above the plane
    dn = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -h / dn
    if h <= 0.0:  # origin inside the solid half space
        return np.zeros(len(d))
    return np.where(dn < 0.0, t, _BIG)


# ---------------------------------------------------------------------------------- world
@dataclass
class World:
    """A static world: the union of ``primitives``; ``bounds`` (2, 3) is the min and max corner of the
    region flights stay in, ``flight_z`` the heights they may use (metres); ``kind``, ``seed`` and
    ``params`` record the generator (``custom`` when hand-made)."""

    primitives: list[Primitive]
    bounds: np.ndarray
    kind: str = "custom"
    seed: int = 0
    flight_z: tuple[float, float] = (0.5, 2.0)
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.bounds = np.asarray(self.bounds, dtype=np.float64).reshape(2, 3)
        self._packed: dict[str, tuple[np.ndarray, ...]] | None = None

    # -------------------------------------------------------------- distance
    def _pack(self) -> dict[str, tuple[np.ndarray, ...]]:
        """Per primitive kind present, its fields stacked into arrays (the SDF functions' arguments)."""
        if self._packed is None:
            packed: dict[str, tuple[np.ndarray, ...]] = {}
            for kind in _SDF:
                prims = [p for p in self.primitives if p.kind == kind]
                if prims:
                    packed[kind] = tuple(np.array([getattr(p, f.name) for p in prims]) for f in fields(prims[0]))
            self._packed = packed
        return self._packed

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (N,) float64 of world points (N, 3): > 0 free, < 0 inside, metres.

        Exact in free space and on surfaces; inside, a lower bound of the depth (see module doc).
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise SimError(f"points must have shape (N, 3), got {p.shape}")
        out = np.full(len(p), np.inf)
        packed = self._pack()
        for start in range(0, len(p), _CHUNK):
            blk = p[start:start + _CHUNK]
            best = out[start:start + _CHUNK]
            for kind, args in packed.items():
                best = np.minimum(best, _SDF[kind](blk, *args).min(axis=1))
            out[start:start + _CHUNK] = best
        return out

    # -------------------------------------------------------------- rays
    def raycast(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """First-hit parameter t (M,) of rays ``origin + t * directions`` (inf: no hit), in units of the
        ``directions`` (M, 3), which need not be unit length."""
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        t = np.full(len(d), np.inf)
        for prim in self.primitives:
            t = np.minimum(t, ray_entry(o, d, prim))
        return t

    # -------------------------------------------------------------- io
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "mapkit.sim.world/1",
            "kind": self.kind,
            "seed": self.seed,
            "bounds": self.bounds.tolist(),
            "flight_z": list(self.flight_z),
            "params": self.params,
            "primitives": [primitive_to_dict(p) for p in self.primitives],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> World:
        return cls(
            primitives=[primitive_from_dict(p) for p in d["primitives"]],
            bounds=np.asarray(d["bounds"], dtype=np.float64),
            kind=str(d.get("kind", "custom")),
            seed=int(d.get("seed", 0)),
            flight_z=tuple(d.get("flight_z", (0.5, 2.0))),
            params=dict(d.get("params", {})),
        )

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write the primitives as JSON (floats round-trip exactly)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> World:
        """Read a world written by :meth:`to_json`; ``signed_distance`` is restored exactly."""
        try:
            data = json.loads(Path(path).read_text())
        except FileNotFoundError:
            raise SimError(f"world file {path} not found; pass the .world.json written beside the recording") from None
        except json.JSONDecodeError as exc:
            raise SimError(f"world file {path} is not valid JSON ({exc.msg}); regenerate it") from None
        return cls.from_dict(data)

    # -------------------------------------------------------------- mesh
    def mesh(self, *, resolution: int = 48, color: bool = True) -> Any:
        """open3d legacy TriangleMesh of all primitives (half spaces as quads over the bounds; curved
        surfaces with ``resolution`` segments per circle), for display."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh()
        colors = {"box": (0.62, 0.6, 0.55), "cylinder": (0.45, 0.33, 0.22), "capsule": (0.5, 0.38, 0.25),
                  "halfspace": (0.4, 0.55, 0.35)}
        for prim in self.primitives:
            m = _primitive_mesh(prim, self.bounds, resolution)
            if color:
                m.paint_uniform_color(colors[prim.kind])
            mesh += m
        mesh.compute_vertex_normals()
        return mesh


def _frame_from_axis(u: np.ndarray) -> np.ndarray:
    """Rotation whose z column is the unit vector ``u``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, u)
    x /= np.linalg.norm(x)
    y = np.cross(u, x)
    return np.stack([x, y, u], axis=1)


def _primitive_mesh(prim: Primitive, bounds: np.ndarray, resolution: int) -> Any:
    import open3d as o3d

    if isinstance(prim, Box):
        h = np.asarray(prim.half_extents)
        m = o3d.geometry.TriangleMesh.create_box(*(2 * h))
        m.translate(-h)
        c, s = math.cos(prim.yaw), math.sin(prim.yaw)
        m.rotate(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), center=np.zeros(3))
        m.translate(np.asarray(prim.center))
        return m
    if isinstance(prim, (Cylinder, Capsule)):
        a, b = np.asarray(prim.a), np.asarray(prim.b)
        L = float(np.linalg.norm(b - a))
        R = _frame_from_axis((b - a) / L)
        m = o3d.geometry.TriangleMesh.create_cylinder(radius=prim.radius, height=L, resolution=resolution, split=1)
        m.rotate(R, center=np.zeros(3))
        m.translate(0.5 * (a + b))
        if isinstance(prim, Capsule):
            for end in (a, b):
                sph = o3d.geometry.TriangleMesh.create_sphere(radius=prim.radius, resolution=max(6, resolution // 4))
                sph.translate(end)
                m += sph
        return m
    # Half space: a quad well beyond the bounds (the camera sees ~13 m).
    n = np.asarray(prim.normal)
    pad = 30.0
    lo, hi = bounds[0] - pad, bounds[1] + pad
    R = _frame_from_axis(n)
    centre = 0.5 * (lo + hi)
    centre = centre - (n @ centre - prim.offset) * n
    half = 0.5 * float(np.max(hi - lo))
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * half
    verts = centre[None, :] + corners[:, :1] * R[:, 0][None, :] + corners[:, 1:] * R[:, 1][None, :]
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                  o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]])))
    return m
