"""Workspace directories and atomic store writes (a killed command never leaves a valid-looking store)."""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from mapkit.errors import MapkitError

FRAMES = "frames.zarr"


class WorkspaceError(MapkitError):
    """A workspace path or store that cannot be used."""


def check_writable(target: Path, *, overwrite: bool, option: str = "--overwrite") -> None:
    """Fail before any work when `target` exists and may not be replaced."""
    if target.exists() and not overwrite:
        raise WorkspaceError(f"{str(target)!r} already exists; pass {option} to replace it")


@contextmanager
def atomic_output(target: Path, *, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary sibling path to write; it replaces `target` only when the block succeeds.

    On any exception the temporary is removed and `target` is untouched.
    """
    check_writable(target, overwrite=overwrite)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.partial-{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    old = target.with_name(f".{target.name}.old-{os.getpid()}")
    if target.exists():
        os.replace(target, old)
    os.replace(tmp, target)
    _remove(old)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
