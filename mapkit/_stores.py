"""Where stores live: a local path or an fsspec URL, and how a store is published at either (docs/stores.md).

Locally a store is written as a hidden sibling and renamed into place. Other filesystems have no atomic
folder rename: the store is written under a hidden prefix and copied to its name with its root
``zarr.json`` LAST, so that document is the completion marker readers check (:meth:`Location.state`).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from mapkit.workspace import WorkspaceError, atomic_output, check_writable

ZARR_JSON = "zarr.json"
"""A zarr v3 group's metadata document; on non-local filesystems it is published last (the marker)."""
State = Literal["complete", "incomplete", "missing"]
log = logging.getLogger(__name__)


class StoreError(WorkspaceError):
    """A store URL that cannot be used: unknown protocol, no credentials, missing bucket, incomplete store."""


def is_url(where: str | Path) -> bool:
    """True for ``PROTOCOL://...`` text (fsspec URLs); False for local paths."""
    return isinstance(where, str) and "://" in where


@dataclass(frozen=True)
class Location:
    """A store or folder: a local path, or a path on an fsspec filesystem; build with :meth:`of`, join
    names with ``/``; ``str()`` gives what the user wrote."""

    url: str
    """The path or URL as given (children joined with "/")."""
    fs: Any = field(repr=False, compare=False)
    """The fsspec filesystem (configured from fsspec's config and `storage_options`)."""
    path: str
    """The path on `fs` (protocol stripped)."""
    local: Path | None
    """The local path when `fs` is the local disk (atomic rename there), else None."""
    storage_options: dict[str, Any] | None = field(default=None, compare=False)
    """Options given explicitly for `fs` (passed to zarr's store too); None: fsspec's configuration only."""

    @classmethod
    def of(cls, where: str | Path | Location, *, storage_options: dict[str, Any] | None = None) -> Location:
        """The location of a local path or fsspec URL; a :class:`StoreError` names an unusable URL."""
        if isinstance(where, Location):
            return where
        if not is_url(where):
            p = Path(where)
            return cls(str(p), None, str(p), p)
        import fsspec

        url = str(where)
        try:
            fs, path = fsspec.core.url_to_fs(url, **(storage_options or {}))
        except (ValueError, ImportError) as exc:
            raise StoreError(f"cannot use {url!r}: {exc}; give a local path or a URL whose fsspec backend is installed "
                             "(e.g. pip install s3fs for s3://, gcsfs for gs://)") from None
        from fsspec.implementations.local import LocalFileSystem

        if isinstance(fs, LocalFileSystem):
            return cls(url, fs, path, Path(path), storage_options)
        return cls(url, fs, path, None, storage_options)

    def __str__(self) -> str:
        return self.url

    def __truediv__(self, name: str) -> Location:
        if self.local is not None and not is_url(self.url):
            return Location.of(self.local / name)
        return Location(f"{self.url.rstrip('/')}/{name}", self.fs, f"{self.path.rstrip('/')}/{name}",
                        None if self.local is None else self.local / name, self.storage_options)

    @property
    def name(self) -> str:
        return self.path.rstrip("/").rsplit("/", 1)[-1]

    @property
    def parent(self) -> Location:
        cut = self.url.rstrip("/").rsplit("/", 1)[0]
        return Location.of(self.local.parent if self.local is not None and not is_url(self.url) else cut,
                           storage_options=self.storage_options)

    def sibling(self, name: str) -> Location:
        """The location called `name` next to this one."""
        return self.parent / name

    def zarr_store(self, *, read_only: bool) -> Any:
        """What to hand ``zarr.open_group``: the local path (as before), or an ``FsspecStore``."""
        if self.local is not None:
            return self.local
        from zarr.storage import FsspecStore

        with store_errors(self):
            return FsspecStore.from_url(self.url, storage_options=self.storage_options, read_only=read_only)

    def state(self) -> State:
        """"complete" (a zarr group whose root metadata is published), "incomplete" (files but no root
        ``zarr.json``: a write was interrupted or is in progress) or "missing" (nothing there)."""
        if self.local is not None:
            if not self.local.exists():
                return "missing"
            return "complete" if (self.local / ZARR_JSON).is_file() or not self.local.is_dir() else "incomplete"
        with store_errors(self):
            self.fs.invalidate_cache(self.path)
            if self.fs.exists(f"{self.path}/{ZARR_JSON}"):
                return "complete"
            return "incomplete" if self.fs.exists(self.path) else "missing"

    def exists(self) -> bool:
        """Something (complete or not) is at this location."""
        return self.state() != "missing"

    def require_complete(self, fix: str) -> None:
        """Raise :class:`StoreError` for a store on a non-local filesystem without its published root
        ``zarr.json``; `fix` is the command that makes it. (Local stores are renamed into place.)"""
        if self.local is None and self.state() == "incomplete":
            raise StoreError(
                f"store at {self.url} is incomplete (no completion marker: its root {ZARR_JSON} is published "
                f"last): a write was interrupted or is still running; re-run the command that makes it ({fix})"
            )

    def check_reachable(self) -> None:
        """Fail early with a one-line :class:`StoreError` when the filesystem refuses us: no
        credentials, an unreachable endpoint, or (object stores) a missing bucket."""
        if self.local is not None:
            return
        top = self.path.strip("/").split("/", 1)[0]
        if getattr(self.fs, "root_marker", "/") != "":
            return  # not an object store (s3fs, gcsfs, adlfs have no root marker): folders are made on write
        with store_errors(self):
            self.fs.invalidate_cache(top)
            try:
                self.fs.info(top)  # not exists(): s3fs answers False for a refused connection too
            except FileNotFoundError:
                raise StoreError(f"bucket {top!r} of {self.url} does not exist; create it or check the URL") from None


def _translate(loc: Location, exc: BaseException) -> StoreError | None:
    """The one-line error for a filesystem failure at `loc`, or None when it is not one we know."""
    name = type(exc).__name__
    if "Credentials" in name or "NoAuth" in name:
        return StoreError(
            f"no credentials for {loc.url} ({exc}); set them where fsspec's backend looks (e.g. AWS_ACCESS_KEY_ID / "
            "AWS_SECRET_ACCESS_KEY or ~/.aws for s3://), or options in fsspec's config (FSSPEC_S3_ANON=true for a "
            "public bucket); see docs/stores.md"
        )
    if isinstance(exc, PermissionError):
        return StoreError(f"access to {loc.url} denied ({exc}); check the credentials and the bucket's policy")
    if "EndpointConnection" in name or "ConnectTimeout" in name or isinstance(exc, ConnectionError):
        return StoreError(
            f"cannot reach the storage of {loc.url} ({exc}); check the endpoint (fsspec config, e.g. "
            "FSSPEC_S3_ENDPOINT_URL) and the network"
        )
    return None


@contextmanager
def store_errors(loc: Location) -> Iterator[None]:
    """Turn credential, permission and connection failures inside the block into one-line StoreErrors."""
    try:
        yield
    except StoreError:
        raise
    except Exception as exc:
        err = _translate(loc, exc)
        if err is None:
            raise
        raise err from None


def check_store_writable(target: Location, *, overwrite: bool, option: str = "--overwrite") -> None:
    """Fail before any work when a store exists at `target` and may not be replaced (an incomplete one
    on a non-local filesystem may: it is no store)."""
    if target.local is not None:
        check_writable(target.local, overwrite=overwrite, option=option)
        return
    target.check_reachable()
    if target.state() == "complete" and not overwrite:
        raise WorkspaceError(f"{target.url!r} already exists; pass {option} to replace it")


@contextmanager
def publish_store(target: Location, *, overwrite: bool) -> Iterator[Location]:
    """Yield a temporary location to write a zarr group; it becomes `target` (by rename, or copied root
    ``zarr.json`` last) only when the block succeeds; on an exception `target` is untouched."""
    if target.local is not None:
        with atomic_output(target.local, overwrite=overwrite) as staged:
            yield Location.of(staged)
        return
    check_store_writable(target, overwrite=overwrite)
    tmp = target.sibling(f".{target.name}.partial-{uuid.uuid4().hex[:12]}")
    try:
        with store_errors(target):
            yield tmp
            _publish(tmp, target, overwrite=overwrite)
    except BaseException:
        try:
            _remove(tmp)
        except Exception as cleanup:  # noqa: BLE001 - the write's own failure is the one to report
            log.warning("could not remove %s (%s: %s); delete it by hand", tmp.url, type(cleanup).__name__, cleanup)
        raise
    _remove(tmp)


def _publish(tmp: Location, target: Location, *, overwrite: bool) -> None:
    """Copy the store at `tmp` to `target`: the old one (if any) loses its root metadata first, then its
    files; the new files go over, root ``zarr.json`` last."""
    fs = tmp.fs
    fs.invalidate_cache(tmp.path)
    src_root = tmp.path.rstrip("/")
    files = sorted(fs.find(src_root))
    root_meta = f"{src_root}/{ZARR_JSON}"
    if root_meta not in files:
        raise StoreError(f"nothing was written under {tmp.url} (no root {ZARR_JSON}); {target.url} is unchanged")
    state = target.state()
    if state == "complete" and not overwrite:  # another writer published meanwhile
        raise WorkspaceError(f"{target.url!r} already exists; pass --overwrite to replace it")
    if state != "missing":
        if state == "complete":
            fs.rm_file(f"{target.path.rstrip('/')}/{ZARR_JSON}")
        fs.rm(target.path, recursive=True)
    dst_root = target.path.rstrip("/")
    rest = [f for f in files if f != root_meta]
    if rest:
        fs.copy(rest, [dst_root + f[len(src_root):] for f in rest])
    fs.copy(root_meta, f"{dst_root}/{ZARR_JSON}")
    fs.invalidate_cache(dst_root)


def _remove(loc: Location) -> None:
    """Remove a temporary prefix if anything is there (failures to reach the storage are raised)."""
    loc.fs.invalidate_cache(loc.path)
    if loc.fs.exists(loc.path):
        loc.fs.rm(loc.path, recursive=True)


def copy_store(source: str | Path | Location, target: str | Path | Location, *, overwrite: bool = False) -> Location:
    """Copy a complete store (e.g. a local map.zarr) to `target` (e.g. an s3:// URL), published the same
    way as the commands publish: readers never see half of it. Returns the target location."""
    src, dst = Location.of(source), Location.of(target)
    if src.state() != "complete":
        raise StoreError(f"{src.url} is not a complete zarr store (no root {ZARR_JSON}); make it first")
    with publish_store(dst, overwrite=overwrite) as tmp:
        for rel, data in store_files(src):
            if tmp.local is not None:
                (tmp.local / rel).parent.mkdir(parents=True, exist_ok=True)
                (tmp.local / rel).write_bytes(data)
            else:
                tmp.fs.pipe_file(f"{tmp.path.rstrip('/')}/{rel}", data)
    return dst


def store_files(loc: Location) -> Iterator[tuple[str, bytes]]:
    """(relative name, bytes) of every file under `loc`, one at a time, in the order of their path parts
    (the order ``sorted(Path.rglob(...))`` gives locally)."""
    if loc.local is not None:
        for p in sorted(q for q in loc.local.rglob("*") if q.is_file()):
            yield str(p.relative_to(loc.local)), p.read_bytes()
        return
    base = loc.path.rstrip("/")
    with store_errors(loc):
        loc.fs.invalidate_cache(base)
        names = sorted((f[len(base) + 1:] for f in loc.fs.find(base)), key=lambda rel: tuple(rel.split("/")))
        for rel in names:
            yield rel, loc.fs.cat_file(f"{base}/{rel}")


def upload_file(local: Path, target: Location) -> None:
    """Copy one local file to `target` on a non-local filesystem: one object PUT, which object stores
    make visible whole or not at all (so single files need no marker)."""
    with store_errors(target):
        target.fs.put_file(str(local), target.path)


def upload_tree(local: Path, target: Location) -> None:
    """Copy every file under the local folder `local` to the same names under `target`."""
    for path in sorted(p for p in local.rglob("*") if p.is_file()):
        upload_file(path, target / path.relative_to(local).as_posix())


def download_tree(source: Location, local: Path) -> None:
    """Copy every file under `source` (a non-local folder) to the same names under `local`."""
    base = source.path.rstrip("/")
    with store_errors(source):
        source.fs.invalidate_cache(base)
        for name in sorted(source.fs.find(base)):
            dst = local / name[len(base) + 1:]
            dst.parent.mkdir(parents=True, exist_ok=True)
            source.fs.get_file(name, str(dst))


def remove_file(target: Location) -> None:
    """Delete one file on a non-local filesystem if it is there."""
    with store_errors(target):
        target.fs.invalidate_cache(target.parent.path)
        if target.fs.exists(target.path):
            target.fs.rm_file(target.path)
