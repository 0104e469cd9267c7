"""Batch roots at fsspec URLs (``s3://bucket/flights``): each step runs in a local scratch workspace on
its worker and publishes what it made to ``ROOT/<name>/`` at the URL.

Open3D's fusion and the ESDF read and write local files, and a step may run on any worker of a
cluster, so a task first brings the products of the steps it reads from the URL into scratch
(``$TMPDIR/mapkit-batch/<root digest>/<name>/``; kept between steps, so a worker that ran the step
before downloads nothing), runs the same library call as with a local root, then publishes its
product at the URL the way readers expect a finished one:

- stores (frames.zarr, map.zarr, tuples.zarr) with their root ``zarr.json`` last
  (:func:`mapkit._stores.copy_store`);
- the fuse step's files (cloud.ply, tsdf.npz, mesh.ply) one PUT each, after deleting the old
  ``fuse.json`` and before writing the new one: fuse.json, which lists the files with their sizes, is
  the completion marker of the set.

The step's marker (``.batch/<step>.json``) is written after its product, as with a local root. The
scratch workspace of a recording is removed when its last step has run.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import uuid
from pathlib import Path

from mapkit._stores import Location, copy_store, download_tree, remove_file, store_errors
from mapkit.batch._config import BatchError, Step
from mapkit.esdf import MAP
from mapkit.export import TUPLES
from mapkit.fusion import FUSE_META
from mapkit.workspace import FRAMES

STORES: dict[Step, str] = {"ingest": FRAMES, "esdf": MAP, "export": TUPLES}
"""The store each step but fuse publishes."""
READS: dict[Step, tuple[Step, ...]] = {"ingest": (), "fuse": ("ingest",), "esdf": ("ingest", "fuse"),
                                       "export": ("ingest", "esdf")}
"""The steps whose products a step reads from its workspace."""


def scratch_for(workspace_url: str) -> Path:
    """This worker's local scratch workspace for a workspace URL."""
    digest = hashlib.sha256(workspace_url.rstrip("/").encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / "mapkit-batch" / digest / workspace_url.rstrip("/").rsplit("/", 1)[-1]


def read_bytes(workspace_url: str, rel: str) -> bytes | None:
    """The file ``rel`` under the workspace URL, None when it is not there."""
    loc = Location.of(workspace_url) / rel
    with store_errors(loc):
        loc.fs.invalidate_cache(loc.parent.path)
        try:
            return bytes(loc.fs.cat_file(loc.path))
        except FileNotFoundError:
            return None


def write_bytes(workspace_url: str, rel: str, data: bytes) -> None:
    """One PUT: object stores show it whole or not at all."""
    loc = Location.of(workspace_url) / rel
    with store_errors(loc):
        loc.fs.makedirs(loc.parent.path, exist_ok=True)
        loc.fs.pipe_file(loc.path, data)


def remove(workspace_url: str, rel: str) -> None:
    """Delete the file ``rel`` under the workspace URL if it is there."""
    remove_file(Location.of(workspace_url) / rel)


def fused_complete(workspace_url: str) -> bool:
    """The files fuse.json lists are at the URL with the sizes it gives."""
    meta = read_bytes(workspace_url, FUSE_META)
    if meta is None:
        return False
    ws = Location.of(workspace_url)
    with store_errors(ws):
        for name, size in json.loads(meta).get("outputs", {}).items():
            try:
                if ws.fs.size((ws / name).path) != size:
                    return False
            except FileNotFoundError:
                return False
    return True


def stage_in(workspace_url: str, step: Step, products: dict[Step, str]) -> Path:
    """The scratch workspace, holding the current product of every step ``step`` reads (``products``:
    step → the product file's relative name). A product whose file already has the URL's bytes is
    not downloaded again."""
    scratch = scratch_for(workspace_url)
    scratch.mkdir(parents=True, exist_ok=True)
    for before in READS[step]:
        rel = products[before]
        wanted = read_bytes(workspace_url, rel)
        here = scratch / rel
        if wanted is None:
            raise BatchError(f"{workspace_url} has no {rel}: the {before} step has not run there; "
                             f"add {before} to --steps")
        if here.is_file() and here.read_bytes() == wanted:
            continue
        if before == "fuse":
            _download_fused(workspace_url, scratch, wanted)
        else:
            _download_store(workspace_url, STORES[before], scratch)
    return scratch


def _download_store(workspace_url: str, name: str, scratch: Path) -> None:
    tmp = scratch / f".{name}.{uuid.uuid4().hex[:8]}.tmp"
    download_tree(Location.of(workspace_url) / name, tmp)
    shutil.rmtree(scratch / name, ignore_errors=True)
    tmp.rename(scratch / name)


def _download_fused(workspace_url: str, scratch: Path, meta: bytes) -> None:
    (scratch / FUSE_META).unlink(missing_ok=True)  # written last: the set is complete only with it
    ws = Location.of(workspace_url)
    for name in json.loads(meta).get("outputs", {}):
        tmp = scratch / f".{name}.{uuid.uuid4().hex[:8]}.tmp"
        with store_errors(ws):
            ws.fs.get_file((ws / name).path, str(tmp))
        tmp.replace(scratch / name)
    (scratch / FUSE_META).write_bytes(meta)


def stage_out(workspace_url: str, step: Step, scratch: Path) -> None:
    """Publish the step's product from scratch at the URL (see the module doc for the order)."""
    if step != "fuse":
        copy_store(scratch / STORES[step], f"{workspace_url.rstrip('/')}/{STORES[step]}", overwrite=True)
        return
    meta = (scratch / FUSE_META).read_bytes()
    remove(workspace_url, FUSE_META)
    ws = Location.of(workspace_url)
    for name in json.loads(meta).get("outputs", {}):
        with store_errors(ws):
            ws.fs.put_file(str(scratch / name), (ws / name).path)
    write_bytes(workspace_url, FUSE_META, meta)


def drop_scratch(workspace_url: str) -> None:
    """Remove this worker's scratch workspace of a recording (its last step has run)."""
    shutil.rmtree(scratch_for(workspace_url), ignore_errors=True)
