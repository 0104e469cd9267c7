"""Reading the executed paths of an eval folder (trajectories.npz)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def load_paths(eval_dir: str | Path) -> dict[str, np.ndarray]:
    """``"{world}/{pair:03d}/{method}"`` → (N, 4) float32 rows [t, x, y, z] (world frame, seconds,
    metres); empty when the folder has no trajectories.npz."""
    path = Path(eval_dir) / "trajectories.npz"
    if not path.exists():
        return {}
    with np.load(path) as npz:
        return {k: npz[k] for k in npz.files}
