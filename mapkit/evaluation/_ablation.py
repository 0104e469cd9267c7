"""What the network adds: every run (method × flight stack) side by side, and paired differences
over the start–goal pairs with 95 % bootstrap intervals (pairs resampled within each world).
``untrained`` flown at several initial weights is compared pooled: per pair, the mean over them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mapkit._choices import FlightStack
from mapkit._formats import EpisodeRecord
from mapkit.evaluation._stack import LABEL_SEPARATOR, Run, split_label

BOOTSTRAP_RESAMPLES = 10_000
PairKey = tuple[str, int]
"""(world, pair index): one start–goal pair."""
Paired = Literal["control_effort", "time_s"]
"""The measured quantities compared as ratios on the pairs both runs reached."""


@dataclass(frozen=True)
class RunSummary:
    """One run's flights: its outcomes and the medians of its successful flights."""

    label: str
    """The run's name in results.json (``NAME@STACK``, ``untrained#SEED@STACK``), or a pool's (``untrained@STACK``)."""
    method: str
    stack: FlightStack | None
    """The flight stack it flew under (None: a method no stack changes)."""
    flights: int
    success: int
    collisions: int
    timeouts: int
    effort_median: float | None
    """Median executed ∫‖snap‖² dt (m²/s⁷) and flight time (s) of the successful flights."""
    time_median: float | None
    success_by_world: dict[str, float]
    """World kind → share of its flights that reached the goal."""
    inits: int = 1
    """Initial weights pooled in this row."""

    @property
    def success_rate(self) -> float:
        return self.success / self.flights if self.flights else float("nan")


@dataclass(frozen=True)
class Interval:
    """A paired statistic of run ``a`` against run ``b`` with its 95 % bootstrap interval."""

    a: str
    b: str
    estimate: float
    low: float
    high: float
    pairs: int

    def __str__(self) -> str:
        return f"{self.estimate:+.1f} [{self.low:+.1f}, {self.high:+.1f}]"


@dataclass(frozen=True)
class Ablation:
    """Every run, and each learned run against its untrained and straight-key-point twins."""

    runs: list[RunSummary]
    success_difference: list[Interval]
    """Percentage points of success, learned − other, over every pair both flew."""
    effort_ratio: list[Interval]
    """Geometric mean over the pairs both reached of learned / other executed effort."""
    time_ratio: list[Interval]
    """Likewise for the flight time to the goal."""


def pooled_labels(labels: Sequence[str]) -> dict[str, list[str]]:
    """Each run's comparison name → the labels it pools, in order (``untrained#SEED@none`` under ``untrained@none``)."""
    out: dict[str, list[str]] = {}
    for label in labels:
        out.setdefault(split_label(label).pooled, []).append(label)
    return out


def summarise_runs(episodes: list[EpisodeRecord], labels: list[str]) -> list[RunSummary]:
    """One :class:`RunSummary` per label, in order, each pool of initial weights followed by its pooled row."""
    out = []
    for name, members in pooled_labels(labels).items():
        out += [_summary(episodes, [label], label) for label in members]
        if len(members) > 1:
            out.append(_summary(episodes, members, name))
    return out


def _summary(episodes: list[EpisodeRecord], members: list[str], label: str) -> RunSummary:
    """The flights of the runs ``members`` as one row named ``label``."""
    eps = [e for e in episodes if e.method in members]
    ok = [e for e in eps if e.outcome == "success"]
    efforts = [e.control_effort for e in ok if e.control_effort is not None]
    times = [e.time_s for e in ok if e.time_s is not None]
    run = split_label(label)
    worlds = dict.fromkeys(e.world for e in eps)
    by_world = {w: float(np.mean([e.outcome == "success" for e in eps if e.world == w])) for w in worlds}
    return RunSummary(
        label=label, method=run.method, stack=run.stack, flights=len(eps), success=len(ok),
        collisions=sum(e.outcome == "collision" for e in eps), timeouts=sum(e.outcome == "timeout" for e in eps),
        effort_median=float(np.median(efforts)) if efforts else None,
        time_median=float(np.median(times)) if times else None, success_by_world=by_world, inits=len(members))


def _by_pair(episodes: list[EpisodeRecord], labels: str | Sequence[str]) -> dict[PairKey, list[EpisodeRecord]]:
    """(world, pair) → the flights of ``labels`` from it, for the pairs every one of them flew."""
    names = [labels] if isinstance(labels, str) else list(labels)
    each = [{(e.world, e.pair): e for e in episodes if e.method == name} for name in names]
    common = set(each[0]).intersection(*each[1:])
    return {k: [flights[k] for flights in each] for k in common}


def _interval(a: str, b: str | Sequence[str], keys: list[PairKey], values: list[float], resamples: int, seed: int,
              scale: Callable[[float], float]) -> Interval | None:
    """The mean of ``values`` (one per pair of ``keys``) with the 2.5th and 97.5th percentiles of the mean
    over resamples within each world, each through ``scale``; None without pairs."""
    if not keys:
        return None
    v, worlds = np.array(values), np.array([k[0] for k in keys])
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(worlds == w) for w in np.unique(worlds)]
    draws = np.concatenate([g[rng.integers(0, len(g), size=(resamples, len(g)))] for g in groups], axis=1)
    low, high = np.percentile(v[draws].mean(axis=1), [2.5, 97.5])
    name = b if isinstance(b, str) else split_label(b[0]).pooled
    return Interval(a, name, scale(float(v.mean())), scale(float(low)), scale(float(high)), len(keys))


def success_difference(episodes: list[EpisodeRecord], a: str, b: str | Sequence[str], *,
                       resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> Interval | None:
    """Success of run ``a`` minus run ``b`` (or the mean of the runs ``b``, one pool) in percentage points
    over the pairs all flew, with its interval; None when they share no pair."""
    ea, eb = _by_pair(episodes, a), _by_pair(episodes, b)
    keys = sorted(ea.keys() & eb.keys())
    diff = [float(ea[k][0].outcome == "success") - float(np.mean([e.outcome == "success" for e in eb[k]])) for k in keys]
    return _interval(a, b, keys, diff, resamples, seed, lambda x: 100.0 * x)


def paired_ratio(episodes: list[EpisodeRecord], a: str, b: str | Sequence[str], quantity: Paired, *,
                 resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> Interval | None:
    """Geometric mean of ``quantity`` of ``a`` over that of ``b`` on the pairs both reached (both positive),
    with its interval; None without such pairs. With a pool ``b`` a pair counts where ``a`` and one of
    them reached the goal, with the mean log ratio over those that did."""
    ea, eb = _by_pair(episodes, a), _by_pair(episodes, b)
    keys, logs = [], []
    for k in sorted(ea.keys() & eb.keys()):
        x = getattr(ea[k][0], quantity)
        ys = [getattr(e, quantity) for e in eb[k] if e.outcome == "success"]
        ys = [y for y in ys if y and y > 0]
        if ea[k][0].outcome == "success" and x and x > 0 and ys:
            keys.append(k)
            logs.append(float(np.mean(np.log(x / np.asarray(ys)))))
    return _interval(a, b, keys, logs, resamples, seed, lambda x: float(np.exp(x)))


def ablation(episodes: list[EpisodeRecord], labels: list[str], *, resamples: int = BOOTSTRAP_RESAMPLES,
             seed: int = 0) -> Ablation:
    """Every run of ``labels``, and ``learned`` under each stack against ``untrained`` (pooled) and
    ``straight-keypoints`` under the same stack, where both flew."""
    runs = summarise_runs(episodes, labels)
    pools = pooled_labels(labels)
    pairs: list[tuple[str, list[str]]] = []
    for run in runs:
        if run.method != "learned":
            continue
        for other in ("untrained", "straight-keypoints"):
            twin = Run(other, run.stack).label
            if twin in pools:
                pairs.append((run.label, pools[twin]))
    kw = {"resamples": resamples, "seed": seed}
    return Ablation(
        runs=runs,
        success_difference=[d for a, b in pairs if (d := success_difference(episodes, a, b, **kw)) is not None],
        effort_ratio=[d for a, b in pairs if (d := paired_ratio(episodes, a, b, "control_effort", **kw)) is not None],
        time_ratio=[d for a, b in pairs if (d := paired_ratio(episodes, a, b, "time_s", **kw)) is not None])


def ablation_lines(result: Ablation) -> list[str]:
    """Markdown: the runs' table, then the paired comparisons."""
    return run_lines(result.runs) + comparison_lines(result)


def run_lines(runs: list[RunSummary]) -> list[str]:
    """Markdown table of every run's outcomes, effort and time to goal."""
    worlds = list(dict.fromkeys(w for r in runs for w in r.success_by_world))
    L = ["| method | stack | " + " | ".join(worlds) + " | success % | collisions | timeouts | effort (median, m²/s⁷) "
         "| time to goal (median, s) |", "|---|---|" + "---|" * (len(worlds) + 5)]
    for r in runs:
        effort = f"{r.effort_median:.4g}" if r.effort_median is not None else "–"
        t = f"{r.time_median:.1f}" if r.time_median is not None else "–"
        per_world = " | ".join(f"{100 * r.success_by_world[w]:.1f}" if w in r.success_by_world else "–" for w in worlds)
        name = r.label.partition(LABEL_SEPARATOR)[0]  # the method, with its seed of initial weights
        method = name if r.inits == 1 else f"{name}, {r.inits} initial weights pooled"
        L.append(f"| {method} | {r.stack or '–'} | {per_world} | **{100 * r.success_rate:.1f}** | {r.collisions} "
                 f"| {r.timeouts} | {effort} | {t} |")
    return L


def comparison_lines(result: Ablation) -> list[str]:
    """Markdown table of learned against its twins under each stack ([] without comparisons)."""
    L: list[str] = []
    if result.success_difference:
        L += ["", "| learned against | success difference, points [95 % CI] | effort ratio [95 % CI] | "
                  "time ratio [95 % CI] |", "|---|---|---|---|"]
        effort = {(d.a, d.b): d for d in result.effort_ratio}
        times = {(d.a, d.b): d for d in result.time_ratio}
        for d in result.success_difference:
            e, t = effort.get((d.a, d.b)), times.get((d.a, d.b))
            L.append(f"| {d.a} − {d.b} | {d} ({d.pairs} pairs) | {_ratio(e)} | {_ratio(t)} |")
        L += ["", "Ratios: geometric mean of learned / other over the pairs both reached (below 1: learned "
                  "spends less). Intervals: 95 % bootstrap over the pairs, resampled within each world."]
    return L


def _ratio(d: Interval | None) -> str:
    return "–" if d is None else f"{d.estimate:.3f}× [{d.low:.3f}, {d.high:.3f}] ({d.pairs} pairs)"
