"""report.md (tables shaped like the paper's Tables I–III) and the PNGs of `mapkit eval`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapkit._formats import EpisodeRecord
from mapkit.evaluation._ablation import ablation, ablation_lines
from mapkit.evaluation._paths import load_paths
from mapkit.evaluation._stack import LABEL_SEPARATOR, split_label
from mapkit.sim import World

PAPER_SUCCESS = {  # % office / garage / forest / overall, from the paper
    "MP": (86.7, 96.7, 48.3, 77.2), "iPlanner": (75.0, 78.3, 63.3, 72.2), "paper (TAN)": (96.7, 91.7, 76.7, 88.3),
}
PAPER_EFFORT_LATENCY = {  # m²/s⁷ mean ± std, latency ms
    "MP": ("97.65 ± 32.52", "29.13"), "EGO": ("32.97 ± 7.83", "20.08"), "iPlanner": ("58.24 ± 11.95", "7.51"),
    "paper (TAN)": ("21.16 ± 4.86", "13.16"),
}
PAPER_TIME_ALLOCATION = {"uniform": ("601.50", "13.13"), "poly5": ("22.93", "11.78"),
                         "gradient": ("26.99", "118.19"), "TAN": ("21.16", "13.16")}
METHOD_COLOURS = {"learned": "tab:blue", "learned+uniform": "tab:cyan", "learned+poly5": "tab:olive",
                  "learned+gradient": "tab:purple", "iplanner-style": "tab:orange", "straight": "tab:gray",
                  "untrained": "tab:brown", "straight-keypoints": "tab:pink",
                  "oracle": "tab:green"}
OUTCOME_COLOURS = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f}"


def _pm(s: dict, mean: str = ".2f", std: str = ".2f") -> str:
    return "–" if s.get("mean") is None else f"{s['mean']:{mean}} ± {s['std']:{std}}"


def _effort(s: dict) -> str:
    return _pm(s, ".4g", ".3g")


def _median(s: dict, fmt: str = "{:.4g}") -> str:
    return "–" if s.get("median") is None else fmt.format(s["median"])


def _lat(lat: dict) -> str:
    return "–" if lat.get("mean_ms") is None else f"{lat['mean_ms']:.2f} ± {lat['std_ms']:.2f}"


def write_report(out: Path, doc: dict, latency: dict, worlds: dict[str, World], allocation: dict | None = None) -> list[Path]:
    """Write report.md, paths_<world>.png per world, effort_latency.png and speed_profiles.png into
    ``out``; ``doc``: results.json's content; ``allocation``: the time allocation's own latency per
    method (Table III)."""
    episodes = [EpisodeRecord.from_dict(e) for e in doc["episodes"]]
    files = []
    for kind, world in worlds.items():
        files.append(_paths_figure(out / f"paths_{kind}.png", doc, episodes, kind, world))
    files.append(_bars_figure(out / "effort_latency.png", doc, latency))
    files.append(_speed_figure(out / "speed_profiles.png", doc, episodes))
    files.append(_markdown(out / "report.md", doc, episodes, latency, [f.name for f in files], allocation or {}))
    return files


def _markdown(path: Path, doc: dict, episodes: list[EpisodeRecord], latency: dict, figures: list[str],
              allocation: dict) -> Path:
    """Write report.md: set-up, Tables I–III, per-world table, figures and versions."""
    methods = doc["methods"]
    L = _setup_lines(doc)
    L += _success_table(doc)
    L += _ablation_section(doc, episodes)
    L += _effort_table(doc, latency)
    for other, paper in (("iplanner-style", "paper: 30.9 % lower than iPlanner"),
                         ("learned+gradient", "paper: TAN 21.16 vs gradient descent 26.99"),
                         ("oracle", "target: at most 2×")):
        if "learned" in methods and other in methods:
            L += [_effort_comparison(doc, episodes, "learned", other, paper), ""]
    L += _tracking_table(doc)
    L += _allocation_table(doc, latency, allocation)
    L += _per_world_table(doc, latency)
    L += _detour_table(doc, episodes)
    L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    L += [f"Versions: {', '.join(f'{k} {v}' for k, v in doc['versions'].items())}.", ""]
    path.write_text("\n".join(L))
    return path


def _ablation_section(doc: dict, episodes: list[EpisodeRecord]) -> list[str]:
    """What the network adds (every run, learned against untrained and straight key-points under each
    stack): only when the evaluation flew an ablation."""
    methods = doc["methods"]
    if not any(LABEL_SEPARATOR in m or split_label(m).method in ("untrained", "straight-keypoints") for m in methods):
        return []
    return ["## Ablation — what the network adds", "", *ablation_lines(ablation(episodes, methods)), ""]


def _setup_lines(doc: dict) -> list[str]:
    """The title and what was run: model, worlds and pairs, the closed loop's settings."""
    cfg, loop = doc["config"], doc["config"]["loop"]
    pilot = loop["pilot"]
    model = doc["model"]
    n_pairs = {k: len(v["pairs"]) for k, v in doc["worlds"].items()}
    L = ["# mapkit eval report", ""]
    if model:
        L.append(f"Model `{model['path']}` (sha256 `{model['sha256'][:16]}…`, input "
                 f"{model['planner_config']['input_size'][0]}×{model['planner_config']['input_size'][1]}).")
    L += [
        f"Worlds {', '.join(f'{k} ({n} pairs)' for k, n in n_pairs.items())}, generated with seed {doc['seed']} "
        f"(pairs seeded likewise); start–goal ≥ {cfg['min_distance']} m apart with {cfg['pair_clearance']} m clearance, "
        f"goals hidden from the start where possible.",
        f"Closed loop: depth {doc['camera']['width']}×{doc['camera']['height']} at {loop['depth_rate']:g} Hz, replan every "
        f"{pilot['replan_interval']} s, local goal clipped to {pilot['horizon']} m, success within {loop['goal_radius']} m "
        f"of the goal, collision when the body centre comes closer than {loop['robot_radius']} m to the world "
        f"(exact distance, {loop['control_rate']:g} Hz samples), time limit max({loop['timeout_min']:g} s, "
        f"{loop['timeout_factor']:g} × distance / {loop['cruise_speed']:g} m/s). Plans with η ≥ 0.5 are "
        f"not executed. Executed effort is ∫‖snap‖² dt (m²/s⁷) of the "
        f"flown trajectory (reference tracked by a 4th-order loop with poles at −{loop['tracking_bandwidth']:g} rad/s); "
        f"per-plan effort is each executed plan's own whole ∫‖snap‖² dt (the paper's quantity), averaged over a "
        f"flight; both over successful flights. Peaks are the flown vehicle's largest speed, acceleration and jerk. "
        f"Latency: wall clock, one CPU thread ({doc['versions']['torch']}).",
        "",
    ]
    return L


def _success_table(doc: dict) -> list[str]:
    """Table I (success rate per world and overall) and the paper's figures."""
    s, methods = doc["summary"], doc["methods"]
    worlds = list(doc["worlds"])
    L = ["## Table I — success rate (%)", "",
         "| method | " + " | ".join(worlds) + " | overall | collision | timeout | goal hidden from start |",
         "|---|" + "---|" * (len(worlds) + 4)]
    for m in methods:
        row = [_pct(s[m][w]["success_rate"]) for w in worlds]
        o = s[m]["overall"]
        L.append(f"| {m} | " + " | ".join(row) + f" | **{_pct(o['success_rate'])}** | {_pct(o['collision_rate'])} | "
                 f"{_pct(o['timeout_rate'])} | {_pct(o['hidden_goal_success_rate'])} ({o['hidden_goal_episodes']}) |")
    L += ["", "Paper (its own worlds, 60 pairs each; office / garage / forest / overall): " + "; ".join(
        f"{k} {' / '.join(f'{v:g}' for v in vals)}" for k, vals in PAPER_SUCCESS.items()) + ".", ""]
    return L


def _effort_table(doc: dict, latency: dict) -> list[str]:
    """Table II (effort, peaks, latency, path ratio, clearance) and the paper's figures."""
    s, methods = doc["summary"], doc["methods"]
    L = ["## Table II — control effort and planning latency", "",
         "| method | executed effort m²/s⁷: median (mean ± std) | per-plan effort, median | flight time s, median | "
         "peak speed / acc. / jerk, median | latency ms | path length / straight | min distance m (mean, min) |",
         "|---|---|---|---|---|---|---|---|"]
    for m in methods:
        o = s[m]["overall"]
        md = o["min_distance"]
        mind = "–" if md.get("mean") is None else f"{md['mean']:.2f}, {md['min']:.2f}"
        peaks = " / ".join(_median(o.get(k, {}), "{:.2f}") for k in ("peak_speed", "peak_acceleration", "peak_jerk"))
        L.append(f"| {m} | {_median(o['control_effort'])} ({_effort(o['control_effort'])}) | "
                 f"{_median(o.get('plan_effort', {}))} | {_median(o.get('time_s', {}), '{:.1f}')} | {peaks} | {_lat(latency[m]['overall'])} | "
                 f"{_pm(o['path_length_ratio'])} | {mind} |")
    L += ["", "Paper: " + "; ".join(f"{k} {e} m²/s⁷, {t} ms" for k, (e, t) in PAPER_EFFORT_LATENCY.items()) + ".", ""]
    return L


def _tracking_table(doc: dict) -> list[str]:
    """How closely the vehicle flew the pilot's references, and how hard those references asked it to fly."""
    s, methods = doc["summary"], doc["methods"]
    L = [f"## Tracking — the vehicle ({doc['config']['vehicle']}) against the pilot's reference", "",
         "| method | tracking error m: per-flight mean (mean over flights, worst) | per-flight max (mean, worst) | "
         "reference peak speed m/s (median, worst) | reference peak acceleration m/s² (median, worst) | "
         "climb m (median, worst) |",
         "|---|---|---|---|---|---|"]
    for m in methods:
        o = s[m]["overall"]

        def pair(key: str, centre: str, o: dict = o) -> str:
            stat = o.get(key, {})
            return "–" if stat.get(centre) is None else f"{stat[centre]:.3g}, {stat['max']:.3g}"

        L.append(f"| {m} | {pair('tracking_error_mean', 'mean')} | {pair('tracking_error_max', 'mean')} | "
                 f"{pair('reference_peak_speed', 'median')} | {pair('reference_peak_acceleration', 'median')} | "
                 f"{pair('climb', 'median')} |")
    L += ["", "Reference peaks are norms (what the flight stack's speed and acceleration limits bound); the climb is "
          "how far a flight rose above the higher of its start and goal.", ""]
    return L


def _allocation_table(doc: dict, latency: dict, allocation: dict) -> list[str]:
    """Table III (the time allocations on the same key-points), empty when no learned method ran."""
    s, methods = doc["summary"], doc["methods"]
    ta = [m for m in ("learned+uniform", "learned+poly5", "learned+gradient", "learned") if m in methods]
    if not ta:
        return []
    L = ["## Table III — time allocation (same key-points, total time and execution)", "",
         "| allocation | executed effort, median | per-plan effort, median | allocation ms, median | "
         "planning ms | success % | paper effort / latency |",
         "|---|---|---|---|---|---|---|"]
    for m in ta:
        name = "TAN" if m == "learned" else m.split("+")[1]
        pe, pl = PAPER_TIME_ALLOCATION[name]
        o = s[m]["overall"]
        alloc = allocation.get(m, {}).get("overall", {}).get("median_ms")
        L.append(f"| {name} | {_median(o['control_effort'])} | {_median(o.get('plan_effort', {}))} | "
                 f"{'–' if alloc is None else f'{alloc:.3g}'} | {_lat(latency[m]['overall'])} | "
                 f"{_pct(o['success_rate'])} | {pe} / {pl} |")
    L.append("")
    return L


def _per_world_table(doc: dict, latency: dict) -> list[str]:
    """Outcome rates, effort and latency per method and world."""
    s, methods = doc["summary"], doc["methods"]
    L = ["## Per world", "", "| method | world | success % | collision % | timeout % | effort m²/s⁷ | latency ms |",
         "|---|---|---|---|---|---|---|"]
    for m in methods:
        for w in doc["worlds"]:
            o = s[m][w]
            L.append(f"| {m} | {w} | {_pct(o['success_rate'])} | {_pct(o['collision_rate'])} | "
                     f"{_pct(o['timeout_rate'])} | {_effort(o['control_effort'])} | {_lat(latency[m][w])} |")
    return L


@dataclass(frozen=True)
class EffortComparison:
    """Executed effort of method ``a`` against ``b`` on the pairs both reached."""

    pairs: int
    """Pairs both methods reached."""
    median_a: float
    median_b: float
    """Median executed effort of each over those pairs, m²/s⁷."""
    time_a: float
    time_b: float
    """Median flight time of each over those pairs, s."""
    equal_time_ratio: float
    """Median over those pairs of a's effort / b's effort re-timed to a's flight time: ``b``'s flown
    path, flown through in the time ``a`` took, costs ``effort_b · (time_b / time_a)⁷``
    (:func:`effort_at_time`). The raw ratio mixes the paths' smoothness with their speed: flown in
    half the time the same path costs 128×."""


def effort_at_time(effort: float, time_s: float, new_time_s: float) -> float:
    """∫‖snap‖² dt of a trajectory ``p(t)``, t ∈ [0, ``time_s``], flown along the same path in
    ``new_time_s`` instead: ``q(t) = p(t · time_s / new_time_s)`` has snap scaled by (time_s / new_time_s)⁴
    over a duration scaled by new_time_s / time_s, so its effort is ``effort · (time_s / new_time_s)⁷``."""
    if time_s <= 0 or new_time_s <= 0:
        raise ValueError(f"flight times must be > 0 s, got {time_s} and {new_time_s}")
    return effort * (time_s / new_time_s) ** 7


def compare_effort(episodes: list[EpisodeRecord], a: str, b: str) -> EffortComparison | None:
    """Effort of ``a`` against ``b`` on the pairs both reached (None when there are none)."""
    ok: dict[tuple[str, int], dict[str, tuple[float, float]]] = {}  # pair → method → (effort, time)
    for e in episodes:
        if e.method in (a, b) and e.outcome == "success" and e.control_effort is not None and e.time_s:
            ok.setdefault((e.world, e.pair), {})[e.method] = (e.control_effort, e.time_s)
    both = np.array([[*v[a], *v[b]] for v in ok.values() if len(v) == 2]).reshape(-1, 4)
    if not len(both):
        return None
    ea, ta, eb, tb = both.T
    ratios = [x / effort_at_time(y, t_b, t_a) for x, t_a, y, t_b in both[eb > 0]]  # a zero effort has no ratio
    return EffortComparison(
        pairs=len(both), median_a=float(np.median(ea)), median_b=float(np.median(eb)),
        time_a=float(np.median(ta)), time_b=float(np.median(tb)),
        equal_time_ratio=float(np.median(ratios)) if ratios else float("nan"))


DETOUR_EDGES = (1.1, 1.3, 1.6, 2.0)
"""Bin edges of :func:`success_by_detour`: the reference's route length over the straight distance."""


@dataclass(frozen=True)
class OutcomeCounts:
    """How many flights of one method ended each way."""

    success: int = 0
    collision: int = 0
    timeout: int = 0

    @classmethod
    def of(cls, outcomes: list[str]) -> OutcomeCounts:
        return cls(*(outcomes.count(name) for name in ("success", "collision", "timeout")))

    @property
    def flights(self) -> int:
        return self.success + self.collision + self.timeout


@dataclass(frozen=True)
class DetourBin:
    """The pairs whose reference route was ``low``–``high`` times their straight distance (both None:
    the pairs the reference did not fly to the goal), with each method's outcomes on them."""

    low: float | None
    high: float | None
    pairs: int
    counts: dict[str, OutcomeCounts]
    """Method → its outcomes on these pairs."""


def success_by_detour(episodes: list[EpisodeRecord], reference: str = "oracle",
                      edges: tuple[float, ...] = DETOUR_EDGES) -> list[DetourBin]:
    """Every method's outcomes by how far ``reference``'s successful route strays from the straight line
    (its path length / the start–goal distance; below 1 where it stopped within the goal radius). A
    planner that fails only where the way round is long explores badly; one that fails on near-straight
    routes fails locally. Empty bins are left out; [] when ``reference`` did not fly."""
    ratio = {(e.world, e.pair): e.path_length / e.distance
             if e.outcome == "success" and e.path_length is not None and e.distance else None
             for e in episodes if e.method == reference}
    if not ratio:
        return []
    bounds = list(zip((0.0, *edges), (*edges, math.inf), strict=True))
    slots: list[dict[str, list[str]]] = [{} for _ in range(len(bounds) + 1)]  # the last: reference failed
    for e in episodes:
        if (e.world, e.pair) in ratio:
            r = ratio[(e.world, e.pair)]
            k = len(bounds) if r is None else next(i for i, (_, high) in enumerate(bounds) if r < high)
            slots[k].setdefault(e.method, []).append(e.outcome)
    return [DetourBin(low=low, high=high, pairs=len(by_method[reference]),
                      counts={m: OutcomeCounts.of(o) for m, o in by_method.items()})
            for (low, high), by_method in zip([*bounds, (None, None)], slots, strict=True) if by_method]


def _detour_table(doc: dict, episodes: list[EpisodeRecord]) -> list[str]:
    """Success by the oracle's detour (when the oracle flew beside other methods)."""
    methods = [m for m in doc["methods"] if m != "oracle"]
    bins = success_by_detour(episodes) if methods else []
    if not bins:
        return []
    L = ["", "## Success by detour", "",
         "Pairs binned by the oracle's route length over the straight distance; success % (collisions / "
         "timeouts) of each method on them.", "",
         "| oracle route / straight | pairs | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    for b in bins:
        label = ("oracle failed" if b.low is None or b.high is None else f"< {b.high:g}" if b.low == 0
                 else f"≥ {b.low:g}" if not math.isfinite(b.high) else f"{b.low:g}–{b.high:g}")
        cells = [f"{100 * c.success / c.flights:.1f} ({c.collision} / {c.timeout})" if (c := b.counts.get(m)) else "–"
                 for m in methods]
        L.append(f"| {label} | {b.pairs} | " + " | ".join(cells) + " |")
    return L


def _rel(x: float, y: float) -> str:
    """x / y as "3.2×", or with the percentage below 2×."""
    if x / y >= 2:
        return f"{x / y:.3g}×"
    return f"{x / y:.3g}× ({100 * abs(1 - x / y):.1f} % {'lower' if x < y else 'higher'})"


def _effort_comparison(doc: dict, episodes: list[EpisodeRecord], a: str, b: str, paper: str) -> str:
    """Effort of a vs b over all their successful flights and over the pairs both reached."""
    s = doc["summary"]
    ea, eb = s[a]["overall"]["control_effort"].get("median"), s[b]["overall"]["control_effort"].get("median")
    if ea is None or not eb:
        return f"Effort {a} vs {b}: no comparison (one of them reached no goal; {paper})."
    text = f"Executed effort {a} vs {b}, medians: {_rel(ea, eb)} over each one's successful flights"
    c = compare_effort(episodes, a, b)
    if c is not None:
        text += (f"; {_rel(c.median_a, c.median_b)} on the {c.pairs} pairs both reached ({c.median_a:.4g} vs "
                 f"{c.median_b:.4g} m²/s⁷, flown in {c.time_a:.1f} vs {c.time_b:.1f} s); at equal flight time "
                 f"({b}'s path flown in {a}'s time), {c.equal_time_ratio:.3g}× (median over those pairs")
        per_world = [(w, compare_effort([e for e in episodes if e.world == w], a, b)) for w in doc["worlds"]]
        if len(per_world) > 1:
            text += "; " + ", ".join(f"{w} {cw.equal_time_ratio:.3g}×" for w, cw in per_world if cw is not None)
        text += ")"
    return text + f" ({paper})."


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _occupancy_views(world: World, z: float, res: float) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """Top view: obstacles at height z; side view: fraction of each x–z column (over y) inside."""
    lo, hi = world.bounds
    xs = np.arange(lo[0], hi[0] + 1e-9, res)
    ys = np.arange(lo[1], hi[1] + 1e-9, res)
    zs = np.arange(lo[2], hi[2] + 1e-9, res)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    top = world.signed_distance(np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])).reshape(X.shape) < 0
    ys_side = ys[:: max(1, len(ys) // 40)]
    Xs, Ys, Zs = np.meshgrid(xs, ys_side, zs, indexing="ij")
    inside = world.signed_distance(np.column_stack([Xs.ravel(), Ys.ravel(), Zs.ravel()])).reshape(Xs.shape) < 0
    side = inside.mean(axis=1)
    return top, side, (lo[0], hi[0], lo[1], hi[1]), (lo[0], hi[0], lo[2], hi[2])


def _paths_figure(path: Path, doc: dict, episodes: list[EpisodeRecord], kind: str, world: World) -> Path:
    """Top and side views of ``kind`` with every method's executed paths coloured by outcome."""
    plt = _pyplot()
    methods = doc["methods"]
    eps = [e for e in episodes if e.world == kind]
    starts = np.array([p["start"] for p in doc["worlds"][kind]["pairs"]])
    z = float(np.median(starts[:, 2])) if len(starts) else float(np.mean(world.flight_z))
    res = float(np.clip(max(world.bounds[1] - world.bounds[0]) / 200.0, 0.05, 0.25))
    top, side, ext_top, ext_side = _occupancy_views(world, z, res)
    paths = load_paths(path.parent)
    n = len(methods)
    aspect_top = (ext_top[3] - ext_top[2]) / (ext_top[1] - ext_top[0])
    aspect_side = (ext_side[3] - ext_side[2]) / (ext_side[1] - ext_side[0])
    w = 3.2
    fig, axes = plt.subplots(2, n, figsize=(w * n, w * (aspect_top + aspect_side) + 1.0), squeeze=False,
                             gridspec_kw={"height_ratios": [aspect_top, max(aspect_side, 0.15)]})
    for j, m in enumerate(methods):
        ax_t, ax_s = axes[0, j], axes[1, j]
        ax_t.imshow(top.T, origin="lower", extent=ext_top, cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest")
        ax_s.imshow(side.T, origin="lower", extent=ext_side, cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest",
                    aspect="auto")
        ok = 0
        for e in (e for e in eps if e.method == m):
            p = paths.get(f"{kind}/{e.pair:03d}/{m}")
            c = OUTCOME_COLOURS[e.outcome]
            ok += e.outcome == "success"
            if p is not None and len(p):
                ax_t.plot(p[:, 1], p[:, 2], color=c, lw=0.7, alpha=0.8)
                ax_s.plot(p[:, 1], p[:, 3], color=c, lw=0.7, alpha=0.8)
            if e.collision_point is not None:
                cp = e.collision_point
                ax_t.plot(cp[0], cp[1], "x", color="tab:red", ms=5)
                ax_s.plot(cp[0], cp[2], "x", color="tab:red", ms=5)
        if len(starts):
            goals = np.array([p["goal"] for p in doc["worlds"][kind]["pairs"]])
            ax_t.plot(starts[:, 0], starts[:, 1], "o", ms=2.5, color="black")
            ax_t.plot(goals[:, 0], goals[:, 1], "*", ms=4, color="tab:blue")
        n_ep = sum(e.method == m for e in eps)
        ax_t.set_title(f"{m}\n{ok}/{n_ep} reached", fontsize=9)
        ax_t.set_xlabel("x (m)", fontsize=7)
        ax_s.set_xlabel("x (m)", fontsize=7)
        if j == 0:
            ax_t.set_ylabel(f"top view, obstacles at z={z:.1f} m\ny (m)", fontsize=7)
            ax_s.set_ylabel("side view\nz (m)", fontsize=7)
        for ax in (ax_t, ax_s):
            ax.tick_params(labelsize=6)
    handles = [plt.Line2D([], [], color=c, label=k) for k, c in OUTCOME_COLOURS.items()]
    handles.append(plt.Line2D([], [], ls="", marker="x", color="tab:red", label="collision point"))
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"{kind} (seed {doc['seed']}): executed trajectories", fontsize=11)
    fig.tight_layout(rect=(0, 0.04, 1, 0.96))
    return _save(plt, fig, path)


def _speed_figure(path: Path, doc: dict, episodes: list[EpisodeRecord], flights: int = 3) -> Path:
    """Speed over time of the first few pairs every method reached (from the 20 Hz paths)."""
    plt = _pyplot()
    paths = load_paths(path.parent)
    methods = doc["methods"]
    reached: dict[tuple[str, int], set[str]] = {}
    for e in episodes:
        if e.outcome == "success":
            reached.setdefault((e.world, e.pair), set()).add(e.method)
    keys = [k for k, v in reached.items() if v >= set(methods)] or sorted(reached, key=lambda k: -len(reached[k]))
    keys = keys[:flights]
    fig, axes = plt.subplots(1, max(1, len(keys)), figsize=(5 * max(1, len(keys)), 3.2), squeeze=False)
    for ax, (world, pair) in zip(axes[0], keys, strict=False):
        for m in methods:
            p = paths.get(f"{world}/{pair:03d}/{m}")
            if p is None or len(p) < 3 or m not in reached[(world, pair)]:
                continue
            v = np.linalg.norm(np.diff(p[:, 1:], axis=0), axis=1) / np.diff(p[:, 0]).clip(1e-9)
            ax.plot(0.5 * (p[1:, 0] + p[:-1, 0]), v, color=METHOD_COLOURS.get(m), lw=1.0, label=m)
        ax.set_title(f"{world} pair {pair}", fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("speed (m/s)")
    if axes[0, 0].lines:
        axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    return _save(plt, fig, path)


def _bars_figure(path: Path, doc: dict, latency: dict) -> Path:
    """Bars of success rate, effort and latency per method and world."""
    plt = _pyplot()
    methods = doc["methods"]
    groups = [*doc["worlds"], "overall"]
    s = doc["summary"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    width = 0.8 / len(methods)
    x = np.arange(len(groups))
    for i, m in enumerate(methods):
        col = METHOD_COLOURS.get(m)
        succ = [100 * (s[m][g]["success_rate"] or 0) for g in groups]
        eff = [s[m][g]["control_effort"].get("median") or np.nan for g in groups]
        lat = [latency[m][g]["mean_ms"] or np.nan for g in groups]
        lat_sd = [latency[m][g]["std_ms"] or 0 for g in groups]
        off = x + (i - (len(methods) - 1) / 2) * width
        axes[0].bar(off, succ, width, color=col, label=m)
        axes[1].bar(off, eff, width, color=col)
        axes[2].bar(off, lat, width, yerr=lat_sd, color=col, capsize=2)
    axes[0].set_ylabel("success rate (%)")
    axes[1].set_ylabel("executed effort ∫‖snap‖² (m²/s⁷), median of successful flights")
    axes[1].set_yscale("log")
    axes[2].set_ylabel("planning latency (ms)")
    axes[2].set_yscale("log")
    for ax in axes:
        ax.set_xticks(x, groups)
    axes[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return _save(plt, fig, path)
