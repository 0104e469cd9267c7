"""map.zarr: writing it, whole or chunk by chunk (layout: docs/data_contracts.md).

The store is written under a temporary sibling name and renamed into place when complete, or at an
fsspec URL published with its root ``zarr.json`` last, so a killed run never leaves a map that opens.
"""

from __future__ import annotations

import contextlib
import json
import warnings
from collections.abc import Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from mapkit._stores import Location, StoreError, check_store_writable, publish_store
from mapkit._version import __version__
from mapkit.esdf import _checks
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._ngff import multiscales, write_levels
from mapkit.workspace import WorkspaceError

KIND = "mapkit.map"
CHUNK = 64
FIELDS = ("esdf", "esdf_raw", "observed")
DIMS = ["x", "y", "z"]
DISTANCE_CONVENTION = (
    "signed Euclidean distance in metres, positive in free space, negative inside obstacles; the surface "
    "lies half-way between occupied and free voxel centres"
)
UNKNOWN_POLICIES = ("free", "occupied")
_WRITE_SLAB = 64  # x-planes per write in write_map (bounded extra memory)


def _compressor() -> Any:
    from zarr.codecs import BloscCodec

    # Maps are written once and read many times, so size wins: zstd-3 + byte shuffle is about 2/3 of
    # lz4's size on smooth float fields.
    return BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


def _origin(origin: Any) -> list[float]:
    try:
        o = np.asarray(origin, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise EsdfError(f"origin={origin!r} must be 3 numbers (metres, world position of voxel [0,0,0]'s centre)") from None
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise EsdfError(f"origin={origin!r} must be 3 finite numbers (metres, world position of voxel [0,0,0]'s centre)")
    return [float(v) for v in o]


def _json_attrs(name: str, value: Any) -> Any:
    try:
        return json.loads(json.dumps(value, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise EsdfError(f"{name} must be JSON-serialisable (numbers, strings, lists, dicts): {exc}") from None


class MapWriter(AbstractContextManager["MapWriter"]):
    """A map.zarr being written: fill :attr:`esdf`, :attr:`esdf_raw`, :attr:`observed` (zarr arrays
    [nx, ny, nz], chunks 64^3) then :meth:`finalize`; as a context manager it finalizes on normal exit
    and discards the partial store on an exception."""

    def __init__(self, path: Path | Location, attrs: dict[str, Any], shape: tuple[int, int, int], overwrite: bool) -> None:
        import zarr

        self.location = Location.of(path)
        """Where the map is published (a local path or an fsspec URL)."""
        self.path: Path | str = self.location.local if self.location.local is not None else self.location.url
        self.shape = shape
        self._voxel_size: float = attrs["voxel_size"]
        self._origin: list[float] = attrs["origin"]
        try:
            check_store_writable(self.location, overwrite=overwrite, option="overwrite=True (CLI: --overwrite)")
        except StoreError as exc:
            raise EsdfError(str(exc)) from None
        except WorkspaceError:
            raise EsdfError(f"{str(self.path)!r} already exists; pass overwrite=True (CLI: --overwrite) to replace it") from None
        self._ctx = publish_store(self.location, overwrite=overwrite)
        try:
            self.tmp_location: Location = self._ctx.__enter__()
        except (WorkspaceError, OSError) as exc:
            raise EsdfError(f"cannot write map {str(self.path)!r}: {exc}") from None
        self.tmp_path: Path | str = self.tmp_location.local if self.tmp_location.local is not None else self.tmp_location.url
        self._done = False
        try:
            self._store = self.tmp_location.zarr_store(read_only=False)
            root = zarr.open_group(self._store, mode="w-", zarr_format=3)
            origin = np.asarray(attrs["origin"])
            vs = attrs["voxel_size"]
            for axis, (name, n) in enumerate(zip(DIMS, shape, strict=True)):
                coord = root.create_array(name, shape=(n,), chunks=(n,), dtype="float64", dimension_names=[name])
                coord[:] = origin[axis] + vs * np.arange(n, dtype=np.float64)
                coord.attrs.update({"units": "m", "long_name": f"{name} of voxel centres ({attrs['frame_id']})"})
            chunks = tuple(min(CHUNK, n) for n in shape)
            arrays = {}
            for name, dtype, fill in (("esdf", "float32", float("nan")), ("esdf_raw", "float32", float("nan")), ("observed", "uint8", 0)):
                arrays[name] = root.create_array(
                    name, shape=shape, chunks=chunks, dtype=dtype, compressors=[_compressor()], fill_value=fill,
                    dimension_names=DIMS,
                )
            arrays["esdf"].attrs.update({"units": "m", "long_name": f"signed distance, Gaussian-smoothed (sigma={attrs['sigma']} m)"})
            arrays["esdf_raw"].attrs.update({"units": "m", "long_name": "signed distance before smoothing"})
            arrays["observed"].attrs.update({"long_name": "1 where a depth ray observed the voxel"})
            root.attrs.update(attrs)
        except BaseException:
            self.abort()
            raise
        self._root = root
        self.esdf = arrays["esdf"]
        self.esdf_raw = arrays["esdf_raw"]
        self.observed = arrays["observed"]

    def finalize(self) -> Path | str:
        """Consolidate metadata and publish the store (rename, or root metadata last at a URL); returns
        its path (or URL)."""
        import zarr

        if self._done:
            raise EsdfError(f"map {str(self.path)!r} was already finalized or aborted; create a new writer")
        try:
            levels = write_levels(self._root, self.esdf, _compressor(), CHUNK)
            self._root.attrs["ome"] = multiscales(self._voxel_size, self._origin, levels)
            with warnings.catch_warnings():
                # zarr notes that consolidated metadata is not (yet) in the v3 spec; xarray relies on it
                warnings.simplefilter("ignore")
                zarr.consolidate_metadata(self._store, zarr_format=3)
        except BaseException as exc:
            self._done = True
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._done = True
        try:
            self._ctx.__exit__(None, None, None)
        except StoreError as exc:
            raise EsdfError(f"cannot publish map {str(self.path)!r}: {exc}") from None
        return self.path

    def abort(self) -> None:
        """Discard the partial store (the previous map at `path`, if any, stays)."""
        if not self._done:
            self._done = True
            err = EsdfError("map writing aborted")
            with contextlib.suppress(EsdfError):
                self._ctx.__exit__(EsdfError, err, None)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._done:
            self.finalize()
        return None


def create_map(
    path: str | Path | Location,
    *,
    shape: Sequence[int],
    origin: Sequence[float] | np.ndarray,
    voxel_size: float,
    frame_id: str,
    sigma: float,
    unknown_policy: str,
    parameters: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> MapWriter:
    """Start a map.zarr of `shape` [nx, ny, nz] to be filled chunk by chunk (never dense in memory).

    Pass the writer's ``esdf`` / ``esdf_raw`` arrays as `out` / `out_raw` to
    :func:`signed_distance_chunked`, write ``observed``, then call ``finalize()``. `origin` is the
    world position (metres, frame `frame_id`) of the centre of voxel [0, 0, 0]; `sigma` the Gaussian
    in metres used for ``esdf``; `unknown_policy` how unobserved voxels were treated ("free" or
    "occupied"); `parameters` (JSON) whatever else made the map. Fails before writing anything if
    `path` exists and `overwrite` is False.
    """
    shp = _checks.grid_shape("shape", tuple(int(s) for s in shape))
    vs = _checks.positive("voxel_size", voxel_size)
    sg = _checks.non_negative("sigma", sigma)
    if not isinstance(frame_id, str) or not frame_id:
        raise EsdfError(f"frame_id={frame_id!r} must be a non-empty string naming the world frame (e.g. 'world')")
    if unknown_policy not in UNKNOWN_POLICIES:
        raise EsdfError(f"unknown_policy={unknown_policy!r} is not one of {', '.join(map(repr, UNKNOWN_POLICIES))}")
    attrs = {
        "kind": KIND,
        "mapkit_version": __version__,
        "voxel_size": vs,
        "origin": _origin(origin),
        "shape": list(shp),
        "frame_id": frame_id,
        "sigma": sg,
        "unknown_policy": unknown_policy,
        "units": "m",
        "distance_convention": DISTANCE_CONVENTION,
        "parameters": _json_attrs("parameters", parameters or {}),
    }
    return MapWriter(Location.of(path), attrs, shp, overwrite)


def write_map(
    path: str | Path | Location,
    *,
    esdf: np.ndarray,
    esdf_raw: np.ndarray,
    observed: np.ndarray,
    origin: Sequence[float] | np.ndarray,
    voxel_size: float,
    frame_id: str,
    sigma: float,
    unknown_policy: str,
    parameters: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path | str:
    """Write a complete map.zarr atomically from in-memory arrays; returns `path` (a URL stays a string).

    `esdf`, `esdf_raw`: float [nx, ny, nz] metres (stored float32); `observed`: bool or uint8
    [nx, ny, nz] (stored uint8 0/1). Other arguments as in :func:`create_map`.
    """
    arrays = {"esdf": np.asarray(esdf), "esdf_raw": np.asarray(esdf_raw), "observed": np.asarray(observed)}
    shape = _checks.grid_shape("esdf", arrays["esdf"].shape)
    for name, a in arrays.items():
        if a.shape != shape:
            raise EsdfError(f"{name} has shape {a.shape} but esdf has {shape}; all three grids must match")
    for name in ("esdf", "esdf_raw"):
        if not np.issubdtype(arrays[name].dtype, np.floating):
            raise EsdfError(f"{name} must be a float array of metres; got dtype {arrays[name].dtype}")
    obs = arrays["observed"]
    if obs.dtype != np.bool_ and not (np.issubdtype(obs.dtype, np.integer) and obs.size and int(obs.max()) <= 1 and int(obs.min()) >= 0):
        raise EsdfError(f"observed must be bool or 0/1 integers; got dtype {obs.dtype}; pass `observed > 0`")
    with create_map(
        path, shape=shape, origin=origin, voxel_size=voxel_size, frame_id=frame_id, sigma=sigma,
        unknown_policy=unknown_policy, parameters=parameters, overwrite=overwrite,
    ) as w:
        for x0 in range(0, shape[0], _WRITE_SLAB):
            sl = slice(x0, min(x0 + _WRITE_SLAB, shape[0]))
            w.esdf[sl] = np.asarray(arrays["esdf"][sl], dtype=np.float32)
            w.esdf_raw[sl] = np.asarray(arrays["esdf_raw"][sl], dtype=np.float32)
            w.observed[sl] = np.asarray(obs[sl], dtype=np.uint8)
        return w.finalize()
