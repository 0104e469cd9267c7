"""One batch per root: a lock file naming its holder (pid, host), taken over only from a dead local pid.

At a URL root the lock is created with fsspec's exclusive mode ("xb": a conditional PUT on S3, which
fails when the object exists); a backend without it gets check-then-write, which two batches started
in the same instant can both pass."""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from mapkit._stores import Location, remove_file, store_errors
from mapkit.batch._config import BatchError
from mapkit.workspace import pid_alive

LOCK = ".mapkit-batch.lock"
"""Lock file in the batch root while a batch runs."""

log = logging.getLogger(__name__)


def _holder(path: Path | Location) -> dict[str, Any]:
    try:
        if isinstance(path, Location):
            path.fs.invalidate_cache(path.parent.path)
            text = path.fs.cat_file(path.path).decode()
        else:
            text = path.read_text()
        data = json.loads(text)
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}  # being written, or damaged: treated as held by an unknown process


def _try_create(path: Path | Location, record: dict[str, Any]) -> bool:
    """Create the lock file exclusively; False when it exists."""
    if isinstance(path, Location):
        return _try_create_at_url(path, record)
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(record))
    return True


def _try_create_at_url(path: Location, record: dict[str, Any]) -> bool:
    data = json.dumps(record).encode()
    with store_errors(path):
        path.fs.makedirs(path.parent.path, exist_ok=True)
        try:
            with path.fs.open(path.path, "xb") as f:
                f.write(data)
            return True
        except FileExistsError:
            return False
        except (ValueError, NotImplementedError):  # no exclusive mode in this backend
            path.fs.invalidate_cache(path.parent.path)
            if path.fs.exists(path.path):
                return False
            path.fs.pipe_file(path.path, data)
            return True


def _unlink(path: Path | Location) -> None:
    if isinstance(path, Location):
        remove_file(path)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def root_lock(root: Path | str) -> Iterator[None]:
    """Hold ``root``'s batch lock for the block. Another live holder is a BatchError naming it; a lock
    left by a dead process on this host is taken over with a warning."""
    path: Path | Location
    if isinstance(root, str):
        path = Location.of(root) / LOCK
    else:
        root.mkdir(parents=True, exist_ok=True)
        path = root / LOCK
    host = socket.gethostname()
    record = {"pid": os.getpid(), "host": host, "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    if not _try_create(path, record):
        held = _holder(path)
        pid, where = held.get("pid"), held.get("host")
        if where == host and isinstance(pid, int) and not pid_alive(pid):
            log.warning("taking over %s: its holder (pid %s on %s) is gone", path, pid, where)
            _unlink(path)
        if not _try_create(path, record):
            held = _holder(path) or held
            raise BatchError(
                f"{root} is in use by another `mapkit batch` (pid {held.get('pid', '?')} on {held.get('host', '?')}, "
                f"since {held.get('since', '?')}); wait for it to finish, or delete {path} if that process is gone"
            )
    try:
        yield
    finally:
        if _holder(path).get("pid") == os.getpid():
            _unlink(path)
