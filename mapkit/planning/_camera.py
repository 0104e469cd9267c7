"""The depth camera a run recorded: ``camera`` in its config.json (`mapkit train` writes the first
training workspace's; the shipped model's is in ``pretrained/config.json``). `mapkit eval` renders this
camera, and :meth:`mapkit.planning.Planner.plan` plans with it when it is given no calibration."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

RUN_CONFIG = "config.json"


@dataclass(frozen=True)
class RunCamera:
    """A run's recorded depth camera (optical frame: z forward, x right, y down)."""

    width: int
    """Pixels."""
    height: int
    """Pixels."""
    K: NDArray[np.float64]
    """(3, 3) intrinsics of images `width` × `height`."""
    T_body_camera: NDArray[np.float64]
    """(4, 4) optical camera → body."""
    source: str
    """Where the run read it (a frames.zarr of its training data)."""


def recorded_camera(run_dir: str | Path) -> RunCamera | None:
    """The camera recorded in ``run_dir/config.json`` (``camera``: width, height, K, T_body_camera, source);
    None when the run has no config.json, it does not parse, or it records no usable camera (the reason
    is logged at debug level)."""
    path = Path(run_dir) / RUN_CONFIG
    try:
        saved = json.loads(path.read_text()).get("camera") if path.is_file() else None
    except (OSError, ValueError, AttributeError) as exc:
        log.debug("%s does not parse (%s): no recorded camera", path, exc)
        return None
    if saved is None:
        return None
    try:
        return _camera(saved)
    except (TypeError, ValueError, KeyError) as exc:
        log.debug("the camera in %s is not usable (%s)", path, exc)
        return None


def _camera(saved: Any) -> RunCamera:
    """A :class:`RunCamera` from config.json's ``camera``; raises TypeError / ValueError / KeyError for one
    that is not a camera."""
    width, height = int(saved["width"]), int(saved["height"])
    K = np.asarray(saved["K"], dtype=np.float64)
    T = np.asarray(saved["T_body_camera"], dtype=np.float64)
    if width < 1 or height < 1 or K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"size {width}x{height}, K {K.shape}, T_body_camera {T.shape}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(T))):
        raise ValueError("K or T_body_camera is not finite")
    return RunCamera(width, height, K, T, str(saved.get("source", "")))
