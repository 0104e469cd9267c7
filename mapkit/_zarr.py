"""Reading zarr stores: one helper shared by the stages that open them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import zarr


def read_whole(group: zarr.Group, name: str) -> np.ndarray:
    """Array ``name`` of ``group`` read into memory; KeyError when it is missing or a group."""
    import zarr

    array = group[name]
    if not isinstance(array, zarr.Array):
        raise KeyError(f"{name} is a group, not an array")
    return np.asarray(array[:])
