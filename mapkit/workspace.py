"""Workspace directories and atomic store writes (a killed command never leaves a valid-looking store)."""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from mapkit.errors import MapkitError

FRAMES = "frames.zarr"
_STAGED = re.compile(r"^\.(?P<name>.+)\.(?P<kind>partial|old)-(?P<pid>\d+)(\.[A-Za-z0-9]+)?$")
log = logging.getLogger(__name__)


class WorkspaceError(MapkitError):
    """A workspace path or store that cannot be used."""


def check_writable(target: Path, *, overwrite: bool, option: str = "--overwrite") -> None:
    """Fail before any work when `target` exists and may not be replaced."""
    if target.exists() and not overwrite:
        raise WorkspaceError(f"{str(target)!r} already exists; pass {option} to replace it")


@contextmanager
def atomic_output(target: Path, *, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary sibling path to write; it replaces `target` only when the block succeeds (on an
    exception the temporary is removed and `target` is untouched)."""
    check_writable(target, overwrite=overwrite)
    target.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(target.parent)
    tmp = target.with_name(f".{target.name}.partial-{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
    except BaseException:
        _remove(tmp, settle=True)
        raise
    old = target.with_name(f".{target.name}.old-{os.getpid()}")
    if target.exists():
        os.replace(target, old)
    os.replace(tmp, target)
    _remove(old)


def pid_alive(pid: int) -> bool:
    """True while process ``pid`` of this host exists (someone else's included)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    return True


def clean_stale(directory: Path) -> list[Path]:
    """Remove what killed mapkit commands left in ``directory`` (``.NAME.partial-PID`` outputs of
    processes that are gone) and put back ``.NAME.old-PID`` when NAME itself is missing (a kill
    between the two renames of :func:`atomic_output`); logs each. Returns the paths handled."""
    handled: list[Path] = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return handled
    for path in entries:
        m = _STAGED.match(path.name)
        if m is None or int(m["pid"]) == os.getpid() or pid_alive(int(m["pid"])):
            continue
        target = directory / m["name"]
        if m["kind"] == "old" and not target.exists():
            os.replace(path, target)
            log.warning("restored %s from %s (a command was killed while replacing it)", target, path.name)
        else:
            _remove(path)
            log.warning("removed %s, left by a killed command (process %s)", path, m["pid"])
        handled.append(path)
    return handled


def _remove(path: Path, *, settle: bool = False) -> None:
    """Remove a file or folder; ``settle``: after a failed write (see below)."""
    if path.is_dir() and not path.is_symlink() and not settle:
        shutil.rmtree(path)
    elif path.is_dir() and not path.is_symlink():
        # zarr writes a call's chunks concurrently, and its other writes may still land (re-creating
        # folders) after the first one failed on a full disk: remove until it stays gone for 0.2 s.
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            shutil.rmtree(path, ignore_errors=True)
            time.sleep(0.2)
            if not path.exists():
                return
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
