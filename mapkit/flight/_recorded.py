"""A trained model as a run records it: its network (model.pt) and the depth camera it was trained with
(``camera`` in its config.json), which `mapkit eval` renders and the pilot uses when a frame gives none."""

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
    """The camera recorded in ``run_dir/config.json``; None when there is no usable one (logged at debug)."""
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
    """A :class:`RunCamera` from config.json's ``camera`` (TypeError / ValueError / KeyError otherwise)."""
    width, height = int(saved["width"]), int(saved["height"])
    K = np.asarray(saved["K"], dtype=np.float64)
    T = np.asarray(saved["T_body_camera"], dtype=np.float64)
    if width < 1 or height < 1 or K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"size {width}x{height}, K {K.shape}, T_body_camera {T.shape}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(T))):
        raise ValueError("K or T_body_camera is not finite")
    return RunCamera(width, height, K, T, str(saved.get("source", "")))


def load_network(model: str | Path) -> tuple[Any, RunCamera | None]:
    """(the network in eval mode on the CPU, its run's camera) of a run directory or ``"pretrained"``;
    :class:`~mapkit.flight.FlightError` names a missing or foreign model.pt."""
    from mapkit._saved import load_saved
    from mapkit.flight._errors import FlightError
    from mapkit.flight._pretrained import PRETRAINED, resolve_model
    from mapkit.planner import PlannerConfig, PlannerNet

    path = resolve_model(model) / "model.pt"
    if not path.exists():
        if str(model) == PRETRAINED:
            raise FlightError(f"this mapkit installation lacks the shipped model ({path}); reinstall mapkit "
                              "or pass --model RUN_DIR of a model you trained")
        raise FlightError(f"{model} has no model.pt; train one with `mapkit train` (or check the run path)")
    saved = load_saved(path, "mapkit planner", FlightError, ("planner_config", "state_dict"))
    try:
        net = PlannerNet(PlannerConfig.from_dict(saved["planner_config"]))
        net.load_state_dict(saved["state_dict"])
    except Exception as exc:  # noqa: BLE001 - a foreign state dict fails in many ways: one message
        raise FlightError(f"{path} is not a mapkit planner ({type(exc).__name__}: {exc})") from None
    return net.eval(), recorded_camera(path.parent)
