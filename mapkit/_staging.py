"""Workspaces at fsspec URLs for steps that need local files (fusion, the ESDF; ``mapkit batch`` with a
URL root): bring products into a local folder, run there, publish back. Stores go root ``zarr.json``
last; a *file set* (fuse's files, listed with sizes in fuse.json) goes old manifest deleted, files, new
manifest last, so it is complete exactly when its manifest is there and the sizes match.
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path

from mapkit._stores import ZARR_JSON, Location, copy_store, download_tree, remove_file, store_errors


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


def _listed(manifest: bytes) -> dict[str, int]:
    outputs = json.loads(manifest).get("outputs", {})
    return {str(name): int(size) for name, size in outputs.items()}


def file_set_complete(workspace_url: str, manifest: str) -> bool:
    """The files the manifest lists are at the URL with the sizes it gives."""
    meta = read_bytes(workspace_url, manifest)
    if meta is None:
        return False
    ws = Location.of(workspace_url)
    with store_errors(ws):
        for name, size in _listed(meta).items():
            try:
                if ws.fs.size((ws / name).path) != size:
                    return False
            except FileNotFoundError:
                return False
    return True


def download_store(workspace_url: str, name: str, local: Path) -> None:
    """``local/name`` becomes a copy of the store ``name`` at the URL (via a temporary folder, so a
    killed copy never leaves a store that looks whole)."""
    tmp = local / f".{name}.{uuid.uuid4().hex[:8]}.tmp"
    download_tree(Location.of(workspace_url) / name, tmp)
    shutil.rmtree(local / name, ignore_errors=True)
    tmp.rename(local / name)


def download_file_set(workspace_url: str, manifest: str, local: Path) -> None:
    """The manifest's files, then the manifest, from the URL into ``local``."""
    meta = read_bytes(workspace_url, manifest)
    if meta is None:
        raise FileNotFoundError(f"{workspace_url}/{manifest}")
    (local / manifest).unlink(missing_ok=True)  # written last: the set is complete only with it
    ws = Location.of(workspace_url)
    for name in _listed(meta):
        tmp = local / f".{name}.{uuid.uuid4().hex[:8]}.tmp"
        with store_errors(ws):
            ws.fs.get_file((ws / name).path, str(tmp))
        tmp.replace(local / name)
    (local / manifest).write_bytes(meta)


def publish_store(local: Path, workspace_url: str, name: str) -> None:
    """The local store ``local/name`` at the URL, replacing what is there, root ``zarr.json`` last."""
    copy_store(local / name, f"{workspace_url.rstrip('/')}/{name}", overwrite=True)


def publish_file_set(local: Path, workspace_url: str, manifest: str) -> None:
    """The manifest's files from ``local`` at the URL: old manifest deleted, files, new manifest last."""
    meta = (local / manifest).read_bytes()
    remove(workspace_url, manifest)
    ws = Location.of(workspace_url)
    for name in _listed(meta):
        with store_errors(ws):
            ws.fs.put_file(str(local / name), (ws / name).path)
    write_bytes(workspace_url, manifest, meta)


def store_marker(name: str) -> str:
    """The file whose presence marks the store ``name`` complete (relative to the workspace)."""
    return f"{name}/{ZARR_JSON}"


def remote(workspace: str | Path) -> str | None:
    """The workspace's URL when it lives on a non-local fsspec filesystem, else None (a local path, or
    a ``file://`` URL, which is the local disk)."""
    if isinstance(workspace, Path):
        return None
    loc = Location.of(workspace)
    return None if loc.local is not None else str(workspace).rstrip("/")
