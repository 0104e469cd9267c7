"""Batch roots at fsspec URLs (``s3://bucket/flights``): a task brings the products it reads into this
worker's scratch workspace (``$TMPDIR/mapkit-batch/<root digest>/<name>/``, kept between steps), runs the
step there and publishes its product at ``ROOT/<name>/`` (:mod:`mapkit._staging`), before its marker.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from pathlib import Path

from mapkit import _staging
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


def _root_scratch(root_url: str) -> Path:
    digest = hashlib.sha256(root_url.rstrip("/").encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / "mapkit-batch" / digest


def scratch_for(workspace_url: str) -> Path:
    """This worker's local scratch workspace for a workspace URL (``ROOT/<name>``)."""
    root, name = workspace_url.rstrip("/").rsplit("/", 1)
    return _root_scratch(root) / name


def stage_in(workspace_url: str, step: Step, products: dict[Step, str]) -> Path:
    """The scratch workspace, holding the current product of every step ``step`` reads (``products``:
    step → the product file's relative name). A product whose file already has the URL's bytes is
    not downloaded again."""
    scratch = scratch_for(workspace_url)
    scratch.mkdir(parents=True, exist_ok=True)
    for before in READS[step]:
        rel = products[before]
        wanted = _staging.read_bytes(workspace_url, rel)
        here = scratch / rel
        if wanted is None:
            raise BatchError(f"{workspace_url} has no {rel}: the {before} step has not run there; "
                             f"add {before} to --steps")
        if here.is_file() and here.read_bytes() == wanted:
            continue
        if before == "fuse":
            _staging.download_file_set(workspace_url, FUSE_META, scratch)
        else:
            _staging.download_store(workspace_url, STORES[before], scratch)
    return scratch


def stage_out(workspace_url: str, step: Step, scratch: Path) -> None:
    """Publish the step's product from scratch at the URL (see the module doc for the order)."""
    if step == "fuse":
        _staging.publish_file_set(scratch, workspace_url, FUSE_META)
    else:
        _staging.publish_store(scratch, workspace_url, STORES[step])


def drop_scratch(workspace_url: str) -> None:
    """Remove this worker's scratch workspace of a recording (its last step has run)."""
    shutil.rmtree(scratch_for(workspace_url), ignore_errors=True)


def drop_root_scratch(root_url: str) -> None:
    """Remove every scratch workspace of a batch root on this worker (run on each worker at the end)."""
    shutil.rmtree(_root_scratch(root_url), ignore_errors=True)
