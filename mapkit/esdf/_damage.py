"""Which stored chunks of a map.zarr grid are damaged: missing (zarr reads a missing chunk as the fill
value, NaN for the distances, without a word) or not decodable (truncated, overwritten)."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

_MISSING = "missing (deleted, or never written)"


def damaged_chunks(arr: Any, index: Any = ..., *, missing_ok: bool = False, limit: int = 3) -> dict[str, str]:
    """Up to `limit` damaged chunks of the zarr array `arr` among those a read of ``arr[index]`` touches:
    chunk key (``c/0/1/0``) → what is wrong (``missing (…)``, or ``undecodable (…)``: truncated or
    overwritten). `missing_ok`: a missing chunk is sound (zarr leaves out chunks that hold only the fill
    value, as ``observed``'s unobserved blocks). Empty when every one is sound, or when `arr` is not a zarr
    array (a grid in memory)."""
    if not hasattr(arr, "store_path") or not hasattr(arr, "metadata"):
        return {}
    from zarr.core.sync import sync

    shape, chunks = tuple(int(n) for n in arr.shape), tuple(int(c) for c in arr.chunks)
    found: dict[str, str] = {}
    for coords in _chunks_read(shape, chunks, index):
        key = str(arr.metadata.encode_chunk_key(coords))
        region = tuple(slice(c * k, min((c + 1) * k, n)) for c, k, n in zip(coords, chunks, shape, strict=True))
        try:
            if not missing_ok and not sync((arr.store_path / key).exists()):
                found[key] = _MISSING
            else:
                arr[region]
        except Exception as exc:  # noqa: BLE001 - zarr/numcodecs raise many kinds for a damaged chunk
            found[key] = f"undecodable ({type(exc).__name__}: {' '.join(str(exc).split())})"
        if len(found) >= limit:
            break
    return found


def describe(found: dict[str, str]) -> str:
    """One line for :func:`damaged_chunks`' answer, chunks with the same damage together:
    ``chunks c/0/0/0, c/0/1/0 are missing (deleted, or never written)``."""
    by_damage: dict[str, list[str]] = {}
    for key, what in found.items():
        by_damage.setdefault(what, []).append(key)
    return "; ".join(f"chunk {keys[0]} is {what}" if len(keys) == 1 else f"chunks {', '.join(keys)} are {what}"
                     for what, keys in by_damage.items())


def _chunks_read(shape: tuple[int, ...], chunks: tuple[int, ...], index: Any) -> list[tuple[int, ...]]:
    """The chunk coordinates a numpy-style ``index`` (ints, slices, ``...``, integer arrays per axis) of a
    grid of `shape` in `chunks` reads, in order."""
    items = list(index) if isinstance(index, tuple) else [index]
    if any(item is Ellipsis for item in items):
        at = next(i for i, item in enumerate(items) if item is Ellipsis)
        items[at : at + 1] = [slice(None)] * (len(shape) - len(items) + 1)
    items += [slice(None)] * (len(shape) - len(items))
    per_axis = []
    for n, c, item in zip(shape, chunks, items, strict=True):
        selected = np.atleast_1d(np.arange(n)[item])
        per_axis.append(sorted({int(i) // c for i in selected.tolist()}))
    return list(itertools.product(*per_axis))
