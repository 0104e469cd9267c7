"""Start–goal pairs in a world's free space."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapkit.errors import MapkitError
from mapkit.sim import WORLD_KINDS, FreeSpaceGraph


class EvalError(MapkitError):
    """A model, world or setting `mapkit eval` cannot use."""


@dataclass
class Pair:
    """One start–goal pair, world frame."""

    index: int
    start: np.ndarray
    """(3,) metres."""
    goal: np.ndarray
    """(3,) metres."""
    line_of_sight: bool
    """True when the straight segment start→goal touches no obstacle (only used when no hidden goal
    was found for that start)."""

    @property
    def distance(self) -> float:
        return float(np.linalg.norm(self.goal - self.start))

    def to_dict(self) -> dict:
        return {"pair": self.index, "start": self.start.tolist(), "goal": self.goal.tolist(),
                "distance": self.distance, "line_of_sight": self.line_of_sight}


def sample_pairs(graph: FreeSpaceGraph, count: int, *, seed: int, min_distance: float,
                 tries_per_start: int = 64) -> list[Pair]:
    """``count`` pairs of free cell centres (clearance of ``graph``) in its connected free space,
    at least ``min_distance`` metres apart, the goal hidden from the start where possible.

    Deterministic in (world, seed). Raises :class:`EvalError` when the world cannot give them.
    """
    world = graph.world
    kind_index = WORLD_KINDS.index(world.kind) if world.kind in WORLD_KINDS else len(WORLD_KINDS)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), kind_index, 17]))
    cells = graph.free_index
    centres = graph.centres
    pairs: list[Pair] = []
    attempts = 0
    while len(pairs) < count and attempts < 20 * count + 20:
        attempts += 1
        a = centres[cells[rng.integers(len(cells))]]
        cand = centres[cells[rng.integers(len(cells), size=tries_per_start)]]
        far = cand[np.linalg.norm(cand - a[None], axis=1) >= min_distance]
        if not len(far):
            continue
        t_hit = np.array([world.raycast(a, (g - a)[None])[0] for g in far])
        hidden = far[t_hit < 1.0]
        goal, los = (hidden[0], False) if len(hidden) else (far[0], True)
        pairs.append(Pair(index=len(pairs), start=a.copy(), goal=goal.copy(), line_of_sight=los))
    if len(pairs) < count:
        raise EvalError(
            f"could sample only {len(pairs)} of {count} start-goal pairs in {world.kind} (seed {world.seed}) "
            f"with {graph.clearance} m clearance at least {min_distance} m apart; the free space is too small or "
            f"too cluttered: lower min_distance (--set min_distance=M) or --pairs, or use another --seed"
        )
    return pairs
