"""EsdfMap: a map.zarr (or in-memory grids) with trilinear distance/gradient queries in numpy and torch."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from mapkit._stores import Location, StoreError
from mapkit.esdf import _checks
from mapkit.esdf._damage import damaged_chunks, describe
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._store import FIELDS, KIND

if TYPE_CHECKING:  # pragma: no cover
    import torch

Outside = Literal["nan", "clamp"]
OUTSIDE_POLICIES: tuple[str, ...] = ("nan", "clamp")
_TOL = 1e-6  # voxels: points this close outside the centre box count as on its border (float noise)
_SNAP = 1e-9  # voxels: continuous coordinates this close to an integer are taken as that voxel centre
_FIX = "re-run `mapkit esdf --overwrite` to rebuild it"


class EsdfMap:
    """A signed distance map: grids [nx, ny, nz] indexed [x, y, z], voxel [i, j, k] centred at
    ``origin + voxel_size * (i, j, k)`` (metres, frame :attr:`frame_id`).

    :meth:`open` a map.zarr lazily, or wrap in-memory arrays with the constructor. :meth:`query` /
    :meth:`query_torch` interpolate trilinearly between voxel centres, so they are defined on
    :attr:`bounds`; outside it ``outside="nan"`` (default) gives NaN, ``outside="clamp"`` the value at
    the nearest point of the box (gradient zero along the axes where the point lies outside).
    """

    def __init__(
        self,
        *,
        esdf: Any,
        voxel_size: float,
        origin: Any,
        esdf_raw: Any = None,
        observed: Any = None,
        frame_id: str = "world",
        sigma: float = 0.0,
        unknown_policy: str = "free",
        attrs: dict[str, Any] | None = None,
        path: Path | str | None = None,
    ) -> None:
        self.voxel_size = _checks.positive("voxel_size", voxel_size)
        o = np.asarray(origin, dtype=np.float64).reshape(-1)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise EsdfError(f"origin={origin!r} must be 3 finite numbers (world position of voxel [0,0,0]'s centre)")
        self.origin: np.ndarray = o
        """float64 (3,): world position (metres) of the centre of voxel [0, 0, 0]."""
        self.shape: tuple[int, int, int] = _checks.grid_shape("esdf", tuple(esdf.shape))
        for name, arr in (("esdf_raw", esdf_raw), ("observed", observed)):
            if arr is not None and tuple(arr.shape) != self.shape:
                raise EsdfError(f"{name} has shape {tuple(arr.shape)} but esdf has {self.shape}; all grids must match")
        self.esdf = esdf
        """float32 [nx, ny, nz] smoothed signed distance (zarr array until loaded)."""
        self.esdf_raw = esdf_raw
        """float32 [nx, ny, nz] signed distance before smoothing, or None."""
        self.observed = observed
        """uint8 [nx, ny, nz], 1 where a depth ray observed the voxel, or None."""
        self.frame_id = frame_id
        self.sigma = float(sigma)
        self.unknown_policy = unknown_policy
        self.attrs: dict[str, Any] = dict(attrs or {})
        self.path = path
        self._dense: dict[str, np.ndarray] = {}
        self._torch: dict[tuple[str, str, Any], torch.Tensor] = {}

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, path: str | Path | Location) -> EsdfMap:
        """Open a map.zarr (local path or fsspec URL) lazily. Raises :class:`EsdfError` if it is missing,
        incomplete, corrupt or not a mapkit map."""
        import zarr

        try:
            loc = Location.of(path)
            state = loc.state()
            loc.require_complete("mapkit esdf --overwrite")
        except StoreError as exc:
            raise EsdfError(str(exc)) from None
        p: Path | str = loc.local if loc.local is not None else loc.url
        if state == "missing":
            raise EsdfError(f"no map at {str(p)!r}; create it with `mapkit esdf` (or check the workspace path)")
        if state != "complete" or (loc.local is not None and not (loc.local / "zarr.json").is_file()):
            raise EsdfError(f"{str(p)!r} is not a zarr v3 store (no zarr.json); {_FIX}")
        try:
            root = zarr.open_group(loc.zarr_store(read_only=True), mode="r", zarr_format=3)
            attrs: dict[str, Any] = dict(root.attrs)  # JSON from the store, checked below and by the constructor
        except Exception as exc:  # noqa: BLE001 - zarr raises many kinds for damaged metadata
            raise EsdfError(f"{str(p)!r} cannot be read as a zarr group ({type(exc).__name__}: {exc}); it is corrupt or incomplete; {_FIX}") from None
        kind = attrs.get("kind")
        if kind != KIND:
            raise EsdfError(
                f"{str(p)!r} is a zarr store but not a mapkit map (kind={kind!r}, expected {KIND!r}); "
                f"point to the map.zarr written by `mapkit esdf`, or {_FIX}"
            )
        missing = [k for k in ("voxel_size", "origin", "frame_id", "sigma") if k not in attrs]
        if missing:
            raise EsdfError(f"map {str(p)!r} lacks the attribute(s) {', '.join(missing)}; {_FIX}")
        arrays: dict[str, Any] = {}
        for name in FIELDS:
            try:
                arrays[name] = root[name]
            except Exception:  # noqa: BLE001 - zarr raises many kinds for a missing or damaged array
                raise EsdfError(f"map {str(p)!r} has no readable {name!r} array; it is incomplete; {_FIX}") from None
        expect = {"esdf": np.float32, "esdf_raw": np.float32, "observed": np.uint8}
        for name, arr in arrays.items():
            if getattr(arr, "ndim", None) != 3 or np.dtype(arr.dtype) != expect[name]:
                raise EsdfError(
                    f"map {str(p)!r}: {name!r} is {getattr(arr, 'dtype', '?')} with shape {getattr(arr, 'shape', '?')}, "
                    f"expected 3-D {np.dtype(expect[name]).name}; {_FIX}"
                )
        try:  # the constructor checks the attributes and that the grids' shapes match
            return cls(
                esdf=arrays["esdf"], esdf_raw=arrays["esdf_raw"], observed=arrays["observed"],
                voxel_size=attrs["voxel_size"], origin=attrs["origin"], frame_id=str(attrs["frame_id"]),
                sigma=float(attrs["sigma"]), unknown_policy=str(attrs.get("unknown_policy", "")), attrs=attrs, path=p,
            )
        except EsdfError as exc:
            raise EsdfError(f"map {str(p)!r} is inconsistent: {exc}; {_FIX}") from None

    # ------------------------------------------------------------------ geometry
    @property
    def bounds(self) -> np.ndarray:
        """float64 (2, 3): [min, max] world coordinates of the voxel centres (where queries are defined).
        The voxels' outer faces lie half a voxel further out."""
        lo = self.origin
        hi = self.origin + self.voxel_size * (np.asarray(self.shape, dtype=np.float64) - 1)
        return np.stack([lo, hi])

    def coords(self, axis: str) -> np.ndarray:
        """float64 [n]: voxel-centre coordinates along "x", "y" or "z"."""
        a = _axis_index(axis)
        centres: np.ndarray = self.origin[a] + self.voxel_size * np.arange(self.shape[a], dtype=np.float64)
        return centres

    # ------------------------------------------------------------------ data
    def load(self) -> EsdfMap:
        """Read every grid into memory (numpy); returns self. Queries call this lazily per grid."""
        for name in FIELDS:
            if getattr(self, name) is not None:
                self._grid(name)
                setattr(self, name, self._dense[name])
        return self

    def _grid(self, name: str) -> np.ndarray:
        if name not in self._dense:
            self._dense[name] = np.ascontiguousarray(self.read(name, ...))
        return self._dense[name]

    def read(self, name: str, index: Any) -> np.ndarray:
        """``name``'s values at ``index`` (numpy indexing), from memory when loaded, else from the
        store; a damaged chunk is an :class:`EsdfError` naming the grid and the store."""
        if name in self._dense:
            return np.asarray(self._dense[name][index])
        arr = getattr(self, name)
        if arr is None:
            raise EsdfError(f"this map has no {name!r} grid")
        try:
            return np.asarray(arr[index])
        except Exception as exc:  # noqa: BLE001 - zarr/numcodecs raise many kinds for damaged chunks
            found = damaged_chunks(arr, index, missing_ok=name == "observed")
            what = f"{describe(found)}: the store is damaged" if found else f"{type(exc).__name__}: {exc}"
            raise EsdfError(f"cannot read {name!r} of map {str(self.path)!r} ({what}); {_FIX}") from None

    def check_stored(self, name: str, index: Any = ...) -> None:
        """Raise :class:`EsdfError` naming the store, the grid and the chunks when a chunk of ``name`` that
        ``index`` reads is missing or does not decode (a missing chunk reads as NaN without an error);
        nothing to check for a grid in memory."""
        found = damaged_chunks(getattr(self, name), index) if name not in self._dense else {}
        if found:
            raise EsdfError(f"cannot read {name!r} of map {str(self.path)!r} ({describe(found)}: the store is "
                            f"damaged); {_FIX}")

    # ------------------------------------------------------------------ queries
    def query(self, points: Any, *, raw: bool = False, outside: Outside = "nan") -> tuple[np.ndarray, np.ndarray]:
        """Trilinearly interpolated signed distance and its gradient at world points (N, 3) (or any
        (..., 3)), metres: distance float64 (N,) and gradient float64 (N, 3), the exact gradient of the
        trilinear interpolant (on a cell face, the cell on the upper side). ``raw`` interpolates
        ``esdf_raw`` instead of ``esdf``; ``outside`` is "nan" or "clamp" (see the class docstring).

        Example: the field of a wall at x = 1 m is linear, so interpolation gives it exactly; a point
        outside the grid gets NaN:

        >>> x = 0.5 + 0.1 * np.arange(20)  # voxel-centre x of a 20 × 10 × 10 grid
        >>> wall = np.broadcast_to(x[:, None, None] - 1.0, (20, 10, 10)).astype(np.float32)
        >>> m = EsdfMap(esdf=wall, voxel_size=0.1, origin=(0.5, 0.0, 0.0))
        >>> distance, gradient = m.query([[1.23, 0.45, 0.5], [9.0, 0.0, 0.0]])
        >>> distance.round(6), gradient.round(6) + 0.0
        (array([0.23,  nan]), array([[ 1.,  0.,  0.], [nan, nan, nan]]))
        """
        _check_outside(outside)
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise EsdfError(f"points must have shape (N, 3); got {p.shape}")
        lead = p.shape[:-1]
        p = p.reshape(-1, 3)
        grid = self._grid("esdf_raw" if raw else "esdf")
        n = np.asarray(self.shape)
        u = (p - self.origin) / self.voxel_size
        hi = (n - 1).astype(np.float64)
        uc = np.clip(u, 0.0, hi)
        near = np.rint(uc)
        uc = np.where(np.abs(uc - near) < _SNAP, near, uc)  # voxel centres hit exactly despite rounding
        i0 = np.minimum(np.floor(uc).astype(np.int64), np.maximum(n - 2, 0))
        t = uc - i0
        i1 = np.minimum(i0 + 1, n - 1)
        sx, sy = n[1] * n[2], n[2]
        flat = grid.reshape(-1)
        ix = (i0[:, 0] * sx, i1[:, 0] * sx)
        iy = (i0[:, 1] * sy, i1[:, 1] * sy)
        iz = (i0[:, 2], i1[:, 2])
        c = [[[flat[ix[a] + iy[b] + iz[cc]].astype(np.float64) for cc in (0, 1)] for b in (0, 1)] for a in (0, 1)]
        tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
        # interpolate along z, then y, then x, keeping the partial derivatives
        sx_, sy_, sz_ = 1.0 - tx, 1.0 - ty, 1.0 - tz
        # (1-t)*a + t*b (not a + t*(b-a)) so that a voxel centre returns the stored value exactly
        cz = [[sz_ * c[a][b][0] + tz * c[a][b][1] for b in (0, 1)] for a in (0, 1)]
        dz = [[c[a][b][1] - c[a][b][0] for b in (0, 1)] for a in (0, 1)]
        cy = [sy_ * cz[a][0] + ty * cz[a][1] for a in (0, 1)]
        dy_ = [cz[a][1] - cz[a][0] for a in (0, 1)]
        dz_y = [sy_ * dz[a][0] + ty * dz[a][1] for a in (0, 1)]
        value = sx_ * cy[0] + tx * cy[1]
        gx = cy[1] - cy[0]
        gy = sx_ * dy_[0] + tx * dy_[1]
        gz = sx_ * dz_y[0] + tx * dz_y[1]
        grad = np.stack([gx, gy, gz], axis=-1) / self.voxel_size
        if outside == "clamp":
            grad[(u < 0.0) | (u > hi)] = 0.0
        else:
            out = np.any((u < -_TOL) | (u > hi + _TOL), axis=-1)
            value[out] = np.nan
            grad[out] = np.nan
        return value.reshape(lead), grad.reshape((*lead, 3))

    def query_torch(self, points: torch.Tensor, *, raw: bool = False, outside: Outside = "nan") -> torch.Tensor:
        """Differentiable trilinear signed distance (...) at float32 or float64 world points (..., 3) on any
        device (the grid is copied there once and cached). ``raw`` and ``outside`` as in :meth:`query`."""
        import torch

        _check_outside(outside)
        if not isinstance(points, torch.Tensor):
            raise EsdfError(f"points must be a torch.Tensor (..., 3); got {type(points).__name__}; use query() for numpy")
        if points.shape[-1:] != (3,):
            raise EsdfError(f"points must have shape (..., 3); got {tuple(points.shape)}")
        if points.dtype not in (torch.float32, torch.float64):
            raise EsdfError(f"points must be float32 or float64; got {points.dtype}")
        dtype, device = points.dtype, points.device
        name = "esdf_raw" if raw else "esdf"
        key = (name, str(device), dtype)
        if key not in self._torch:
            self._torch[key] = torch.as_tensor(self._grid(name).reshape(-1)).to(device=device, dtype=dtype)
        flat = self._torch[key]
        lead = points.shape[:-1]
        p = points.reshape(-1, 3)
        n = torch.tensor(self.shape, device=device)
        origin = torch.as_tensor(self.origin, dtype=dtype, device=device)
        hi = (n - 1).to(dtype)
        u = (p - origin) / self.voxel_size
        uc = torch.clamp(u, min=torch.zeros_like(hi), max=hi)
        with torch.no_grad():
            near = torch.round(uc)
            shift = torch.where((uc - near).abs() < _SNAP, near - uc, torch.zeros_like(uc))
        uc = uc + shift  # snaps the value to voxel centres, leaves the gradient alone
        i0 = torch.minimum(torch.floor(uc.detach()).long(), torch.clamp(n - 2, min=0))
        t = uc - i0.to(dtype)
        i1 = torch.minimum(i0 + 1, n - 1)
        sx, sy = self.shape[1] * self.shape[2], self.shape[2]
        ix = (i0[:, 0] * sx, i1[:, 0] * sx)
        iy = (i0[:, 1] * sy, i1[:, 1] * sy)
        iz = (i0[:, 2], i1[:, 2])
        tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
        cy = []
        for a in (0, 1):
            cz = [flat[ix[a] + iy[b] + iz[0]] * (1 - tz) + flat[ix[a] + iy[b] + iz[1]] * tz for b in (0, 1)]
            cy.append(cz[0] * (1 - ty) + cz[1] * ty)
        value = cy[0] * (1 - tx) + cy[1] * tx
        if outside == "nan":
            out = ((u < -_TOL) | (u > hi + _TOL)).any(dim=-1)
            value = torch.where(out, torch.full_like(value, float("nan")), value)
        return value.reshape(lead)

    def __repr__(self) -> str:
        src = f" from {str(self.path)!r}" if self.path else ""
        return (
            f"EsdfMap(shape={self.shape}, voxel_size={self.voxel_size}, origin={self.origin.tolist()}, "
            f"frame_id={self.frame_id!r}, sigma={self.sigma}{src})"
        )


def _axis_index(axis: str) -> int:
    if axis not in ("x", "y", "z"):
        raise EsdfError(f"axis={axis!r} must be 'x', 'y' or 'z'")
    return "xyz".index(axis)


def _check_outside(outside: str) -> None:
    if outside not in OUTSIDE_POLICIES:
        raise EsdfError(f"outside={outside!r} must be one of {', '.join(map(repr, OUTSIDE_POLICIES))}")
