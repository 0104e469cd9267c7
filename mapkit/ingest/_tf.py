"""A small offline tf buffer: static and time-varying edges, lookups through any chain of frames."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mapkit.geometry import interpolate_transform, invert_transform, transform_from_pose
from mapkit.ingest._errors import IngestError

# Why a frame has no pose at a stamp (these names appear in summaries and frames.zarr attrs).
NO_POSE = "outside_pose_coverage"
POSE_GAP = "pose_gap"


class NoPose(Exception):
    """A moving edge has no pose at the asked stamp; ``reason`` is NO_POSE (outside its samples) or
    POSE_GAP (inside a gap longer than allowed). The frame is dropped and counted by reason."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class EdgeSeries:
    """T_parent_child sampled over time; interpolated linearly (translation) and by slerp. Arrays grow by
    doubling; a late sample (tf publishers interleave) is inserted in place."""

    def __init__(self, parent: str, child: str, origin: str) -> None:
        self.parent, self.child, self.origin = parent, child, origin
        self._t = np.empty(64, dtype=np.int64)
        self._trans = np.empty((64, 3))
        self._quats = np.empty((64, 4))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, stamp: int, translation: NDArray[np.float64], q_xyzw: NDArray[np.float64]) -> None:
        norm = float(np.linalg.norm(q_xyzw))
        if not np.isfinite(norm) or norm < 1e-6 or not np.all(np.isfinite(translation)):
            raise IngestError(f"{self.origin}: transform {self.parent} -> {self.child} at stamp {stamp} ns has "
                              f"translation {translation.tolist()} and quaternion {q_xyzw.tolist()}; not a valid pose")
        q = q_xyzw / norm
        n = self._n
        if n and stamp <= self._t[n - 1]:
            i = int(np.searchsorted(self._t[:n], stamp))
            if self._t[i] == stamp:  # a repeated stamp: the later message wins
                self._trans[i], self._quats[i] = translation, self._hemisphere(q, i)
                return
            self._t = np.insert(self._t[:n], i, stamp)
            self._trans = np.insert(self._trans[:n], i, translation, axis=0)
            self._quats = np.insert(self._quats[:n], i, self._hemisphere(q, i), axis=0)
            self._n = n + 1
            return
        if n == len(self._t):
            self._t = np.concatenate([self._t, np.empty_like(self._t)])
            self._trans = np.concatenate([self._trans, np.empty_like(self._trans)])
            self._quats = np.concatenate([self._quats, np.empty_like(self._quats)])
        self._t[n], self._trans[n], self._quats[n] = stamp, translation, self._hemisphere(q, n)
        self._n = n + 1

    def _hemisphere(self, q: NDArray[np.float64], i: int) -> NDArray[np.float64]:
        # Neighbouring quaternions in one hemisphere, so slerp takes the short way.
        return -q if i > 0 and float(np.dot(self._quats[i - 1], q)) < 0 else q

    @property
    def span(self) -> tuple[int, int]:
        return int(self._t[0]), int(self._t[self._n - 1])

    @property
    def last_stamp(self) -> int | None:
        return int(self._t[self._n - 1]) if self._n else None

    def at(self, stamp: int, max_gap_ns: int) -> NDArray[np.float64]:
        """T_parent_child at `stamp`; raises :class:`NoPose` (NO_POSE / POSE_GAP) when it has none."""
        n = self._n
        t = self._t
        if n == 0 or stamp < t[0] or stamp > t[n - 1]:
            raise NoPose(NO_POSE)
        i = int(np.searchsorted(t[:n], stamp, side="right"))
        if t[i - 1] == stamp:
            return transform_from_pose(self._trans[i - 1], self._quats[i - 1])
        gap = int(t[i] - t[i - 1])
        if gap > max_gap_ns:
            raise NoPose(POSE_GAP)
        s = (stamp - int(t[i - 1])) / gap
        return interpolate_transform(self._trans[i - 1], self._quats[i - 1], self._trans[i], self._quats[i], s)


class TfTree:
    """Frames linked child -> parent; each edge static (one matrix) or an EdgeSeries."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, NDArray[np.float64]]] = {}
        self.dynamic: dict[str, EdgeSeries] = {}
        self.pinned: set[str] = set()
        """Children whose edge the user or the pose topic fixed; tf messages about them are ignored."""
        self.version = 0
        """Bumped whenever an edge is added or replaced (not when samples arrive): caches key on it."""

    def set_static(self, parent: str, child: str, T_parent_child: NDArray[np.float64]) -> None:
        if child in self.pinned:
            return
        self.dynamic.pop(child, None)
        self.static[child] = (parent, T_parent_child)
        self.version += 1

    def add_dynamic(self, parent: str, child: str, stamp: int, translation: NDArray[np.float64],
                    q_xyzw: NDArray[np.float64], origin: str) -> None:
        if child in self.pinned:
            return
        series = self.dynamic.get(child)
        if series is None or series.parent != parent:
            # A frame has one parent; the newest declaration of a different parent wins.
            series = self.dynamic[child] = EdgeSeries(parent, child, origin)
            self.version += 1
        series.add(stamp, translation, q_xyzw)

    def replace_dynamic(self, series: EdgeSeries) -> None:
        """Install an edge from a pose topic; it supersedes whatever tf said about that child."""
        self.static.pop(series.child, None)
        self.dynamic[series.child] = series
        self.version += 1

    @property
    def frames(self) -> set[str]:
        names = set(self.static) | set(self.dynamic)
        names |= {p for p, _ in self.static.values()} | {s.parent for s in self.dynamic.values()}
        return names

    def parent(self, frame: str) -> str | None:
        if frame in self.static:
            return self.static[frame][0]
        if frame in self.dynamic:
            return self.dynamic[frame].parent
        return None

    def ancestors(self, frame: str) -> list[str]:
        """[frame, parent, grandparent, ..., root]."""
        chain = [frame]
        while (p := self.parent(chain[-1])) is not None:
            if p in chain:
                raise IngestError(f"tf frames form a loop: {' -> '.join(chain + [p])}")
            chain.append(p)
        return chain

    def root(self, frame: str) -> str:
        return self.ancestors(frame)[-1]

    def static_top(self, frame: str) -> str:
        """Walk up from `frame` through static edges only; the frame where motion starts."""
        while frame in self.static:
            frame = self.static[frame][0]
        return frame

    def dynamic_edges(self, a: str, b: str) -> list[EdgeSeries]:
        chain_a, chain_b = self.ancestors(a), self.ancestors(b)
        common = set(chain_a) & set(chain_b)
        edges = [f for f in chain_a + chain_b if f not in common]
        return [self.dynamic[f] for f in edges if f in self.dynamic]

    def _T_ancestor_frame(self, frame: str, ancestor: str, stamp: int, max_gap_ns: int) -> NDArray[np.float64]:
        T = np.eye(4)
        while frame != ancestor:
            if frame in self.static:
                parent, T_edge = self.static[frame]
            else:
                series = self.dynamic[frame]
                parent, T_edge = series.parent, series.at(stamp, max_gap_ns)
            T = T_edge @ T
            frame = parent
        return T

    def lookup(self, target: str, source: str, stamp: int, max_gap_ns: int) -> NDArray[np.float64]:
        """T_target_source at `stamp`; raises :class:`NoPose` when a moving edge has no pose there."""
        chain_t = self.ancestors(target)
        chain_s = self.ancestors(source)
        common = next((f for f in chain_s if f in chain_t), None)
        if common is None:
            raise IngestError(f"frames {target!r} and {source!r} are not connected by any transform")
        T_common_target = self._T_ancestor_frame(target, common, stamp, max_gap_ns)
        T_common_source = self._T_ancestor_frame(source, common, stamp, max_gap_ns)
        return invert_transform(T_common_target) @ T_common_source
