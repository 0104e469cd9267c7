"""Reading mapkit's saved torch files (models, checkpoints) without ever unpickling code."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mapkit.errors import MapkitError


def load_saved(path: Path, what: str, error: type[MapkitError], keys: tuple[str, ...]) -> dict[str, Any]:
    """The dict saved at ``path``, loaded tensors-and-plain-data only (``weights_only``), with ``keys``.

    A damaged file, another format or a pickle that needs code is ``error`` naming the file and
    ``what`` it should be; torch's own advice (to load it unsafely) is never passed on."""
    import torch

    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - torch raises many kinds (UnpicklingError, RuntimeError, EOFError, ...)
        saved = None
    missing = [k for k in keys if not isinstance(saved, dict) or k not in saved]
    if missing:
        raise error(f"{path} is not a {what} (damaged, truncated, or not written by mapkit); use the file "
                    "`mapkit train` wrote, or train again")
    return saved
