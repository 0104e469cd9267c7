"""The self-supervised upper-level loss U = γ1 U_O + γ2 U_G + γ3 U_S + γ4 U_E + γ5 U_T and its terms.

Every term returns (B,) values; plans are in the body frame, moved to the world frame with
``T_world_body`` (B, 4, 4) before every ESDF lookup.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F

from mapkit.planner._errors import PlannerError
from mapkit.planner._model import Plan, PlannerNet, PlannerOutput
from mapkit.trajopt import Trajectory, allocate_times

if TYPE_CHECKING:  # the ESDF stage is only needed at call time (duck-typed query_torch)
    from mapkit.esdf import EsdfMap


@dataclass
class LossConfig:
    """Weights and parameters of :func:`candidate_loss`. Fixed: γ1 = 20, γ2 = 1, γ3 = 0.5, γ4 = 1, the
    score's weight 1, 10 trajectory samples per second (at least 8), and collision labels from the map's
    unsmoothed ``esdf_raw`` where it has one."""

    gamma_time: float = 10.0
    """γ5, weight of the time cost U_T (:func:`time_cost`: MSE of shares, which are ~1/K, so the raw
    term is small)."""
    score_temperature: float = 0.0
    """Metres of path cost: the score learns softmax(−cost / T) over the candidates instead of the
    single best (0), so two nearly equal detours are both right answers."""
    candidate_spread: float = 0.05
    """α: every candidate's path cost enters with weight α (the winner's with 1 + α), so candidates
    that never win still learn (several only)."""
    candidate_anchor_pull: float = 0.0
    """β, 1/m²: every candidate that does not win a sample adds β × the mean squared distance (m²) of
    its key-points from its own anchor's, divided among the M − 1 losers (several only): keeps the
    candidates apart where ``candidate_spread`` pulls them together."""
    winner_collision_penalty: float = 0.0
    """κ, metres of path cost added to every colliding candidate when choosing the winner and the
    score's target only (no gradient). 0: the cheapest path cost wins."""
    robot_radius: float = 0.3
    """Metres. The obstacle cost acts on the clearance d − robot_radius; a trajectory nearer than this
    to a surface collides (η's label)."""
    obstacle_softness: float = 1.0
    """ε, metres: width of the smooth hinge in :func:`obstacle_penalty`."""
    time_target_iters: int = 10
    """Iterations of the Mellinger & Kumar gradient allocation for the U_T target."""

    def __post_init__(self) -> None:
        if not self.robot_radius >= 0:
            raise PlannerError(f"robot_radius must be >= 0 metres, got {self.robot_radius}")
        if not self.obstacle_softness > 0:
            raise PlannerError(f"obstacle_softness must be > 0 metres, got {self.obstacle_softness}")
        if not (math.isfinite(self.score_temperature) and self.score_temperature >= 0):
            raise PlannerError(f"score_temperature must be >= 0 metres, got {self.score_temperature}")
        for name in ("candidate_spread", "candidate_anchor_pull", "winner_collision_penalty"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise PlannerError(f"{name} must be >= 0, got {getattr(self, name)}")


REMOVED_FIELDS: dict[str, Any] = {
    "detour_weight": 0.0, "detour_cap": 8.0, "eta_horizon": None, "eta_label": "map", "eta_positive_weight": 1.0,
    "collision_distance": None, "obstacle_reduction": "mean", "smoothness_on": "keypoints", "gamma_obstacle": 20.0,
    "gamma_goal": 1.0, "gamma_smooth": 0.5, "gamma_escape": 1.0, "gamma_score": 1.0, "samples_per_second": 10.0,
    "min_samples": 8, "label_from_raw": True, "time_target_tol": 1e-3,
}
"""Removed LossConfig fields a saved run's config.json may still name, with the value that trains as now."""


# ------------------------------------------------------------------------------------ helpers
def _safe_norm(x: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis with a finite gradient at zero (bias below 1e-12 m)."""
    return torch.sqrt((x * x).sum(-1) + 1e-24)


def sample_trajectory(trajectory: Trajectory, *, samples_per_second: float, min_samples: int = 2) -> torch.Tensor:
    """Positions (B, N, 3) at N instants evenly spread over each element's own duration, N =
    max(min_samples, ceil(longest total time × samples_per_second) + 1). Differentiable."""
    if not trajectory.batched:
        raise PlannerError("sample_trajectory needs a batched trajectory (B elements)")
    total = trajectory.total_time  # (B,)
    N = max(int(min_samples), int(math.ceil(float(total.detach().max()) * samples_per_second)) + 1)
    frac = torch.linspace(0.0, 1.0, N, dtype=total.dtype, device=total.device)
    return trajectory.position(total.unsqueeze(-1) * frac)


def body_to_world(points: torch.Tensor, T_world_body: torch.Tensor) -> torch.Tensor:
    """Points (B, N, 3) in the body frame → world frame with T_world_body (B, 4, 4) (float64 is cast
    to the points' dtype)."""
    if points.ndim != 3 or points.shape[-1] != 3:
        raise PlannerError(f"points must have shape (B, N, 3), got {tuple(points.shape)}")
    T = torch.as_tensor(T_world_body, device=points.device)
    if T.shape != (points.shape[0], 4, 4):
        raise PlannerError(f"T_world_body must have shape (B={points.shape[0]}, 4, 4), got {tuple(T.shape)}")
    T = T.to(points.dtype)
    return points @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]


# --------------------------------------------------------------------------------------- terms
def obstacle_penalty(distance: torch.Tensor, *, robot_radius: float, softness: float) -> torch.Tensor:
    """Elementwise obstacle cost (metres) of signed distances: the smooth hinge
    c(u) = (sqrt(u² + ε²) − u) / 2 of the clearance u = distance − robot_radius, ε = softness. Strictly
    decreasing: linear inside obstacles, ε/2 at the radius, decaying like ε² / (4u) in free space (a
    gradient everywhere)."""
    u = distance - robot_radius
    return 0.5 * (torch.sqrt(u * u + softness * softness) - u)


def obstacle_cost(
    points: torch.Tensor,
    esdf_map: EsdfMap,
    *,
    robot_radius: float = 0.3,
    softness: float = 1.0,
) -> torch.Tensor:
    """U_O (B,): the mean over world points (B, N, 3) of :func:`obstacle_penalty` of the smoothed ESDF
    (the paper sums; a mean does not grow with the duration). Outside the grid: the nearest grid point."""
    if points.ndim != 3 or points.shape[-1] != 3:
        raise PlannerError(f"points must have shape (B, N, 3) in the world frame, got {tuple(points.shape)}")
    d = esdf_map.query_torch(points, outside="clamp")
    return obstacle_penalty(d, robot_radius=robot_radius, softness=softness).mean(-1)


def goal_cost(end: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """U_G: ‖end − goal‖₂ (B,) metres, for end and goal (B, 3) in the same frame."""
    if end.shape != goal.shape or end.shape[-1] != 3:
        raise PlannerError(f"end and goal must both be (B, 3), got {tuple(end.shape)} and {tuple(goal.shape)}")
    return _safe_norm(end - goal.to(end.dtype))


def smoothness_cost(points: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """U_S (B,) metres: Σ_i | ‖p_{i+1} − p_i‖ − ‖p̂_{i+1} − p̂_i‖ | over the N points (B, N, 3) against
    N equally spaced points p̂ on the straight ``start`` → ``goal`` line (both (B, 3)): penalises
    uneven steps and detours."""
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 2:
        raise PlannerError(f"points must have shape (B, N>=2, 3), got {tuple(points.shape)}")
    B, N, _ = points.shape
    if start.shape != (B, 3) or goal.shape != (B, 3):
        raise PlannerError(f"start and goal must be (B={B}, 3), got {tuple(start.shape)} and {tuple(goal.shape)}")
    step = _safe_norm(points[:, 1:] - points[:, :-1])  # (B, N-1)
    ref = (_safe_norm(goal.to(points.dtype) - start.to(points.dtype)) / (N - 1)).unsqueeze(-1)
    return (step - ref).abs().sum(-1)


@torch.no_grad()
def collision_labels(
    points: torch.Tensor, esdf_map: EsdfMap, *, threshold: float, raw: bool = False
) -> torch.Tensor:
    """(B,) bool: some world point of (B, N, 3) has ESDF distance < ``threshold`` metres (from
    ``esdf_raw`` when ``raw`` and the map has it). Outside the grid: nearest grid point. No gradient."""
    use_raw = bool(raw and esdf_map.esdf_raw is not None)
    close = esdf_map.query_torch(points.detach(), raw=use_raw, outside="clamp") < threshold
    return close.any(dim=-1)


def escape_cost(eta: torch.Tensor, collided: torch.Tensor, *, logit: torch.Tensor | None = None) -> torch.Tensor:
    """U_E (B,): BCE of η against ``collided`` (B,) bool (no gradient). Pass ``logit`` (B,) when you
    have it: the BCE from the logit never stops learning; η alone is clamped to [1e-7, 1 − 1e-7]."""
    if eta.shape != collided.shape or eta.ndim != 1:
        raise PlannerError(f"eta and collided must both be (B,), got {tuple(eta.shape)} and {tuple(collided.shape)}")
    label = collided.detach().to(eta.dtype)
    if logit is not None:
        if logit.shape != eta.shape:
            raise PlannerError(f"logit must have the shape of eta {tuple(eta.shape)}, got {tuple(logit.shape)}")
        return F.binary_cross_entropy_with_logits(logit, label.to(logit.dtype), reduction="none")
    return F.binary_cross_entropy(eta.clamp(1e-7, 1.0 - 1e-7), label, reduction="none")


@torch.no_grad()
def time_targets(
    waypoints: torch.Tensor,
    *,
    total_time: torch.Tensor,
    start: torch.Tensor | None = None,
    end: torch.Tensor | None = None,
    min_segment: float = 0.0,
    max_iters: int = 10,
    rel_tol: float = 1e-3,
) -> torch.Tensor:
    """U_T target shares (B, M): the gradient-descent allocation of ``total_time`` (B,) over the
    waypoints (B, M+1, 3) from ``start`` to ``end`` (B, 3, 3), each segment >= ``min_segment`` s, as the
    split of the time above the minima (what the TAN predicts). Float64 inside, no gradient."""
    from mapkit.planner._timing import shares_from_durations

    w = waypoints.detach().to(torch.float64)
    tot = torch.as_tensor(total_time).detach().to(torch.float64)
    st = None if start is None else start.detach().to(torch.float64)
    en = None if end is None else end.detach().to(torch.float64)
    T = allocate_times(w, "gradient", total_time=tot, start=st, end=en, max_iters=max_iters, rel_tol=rel_tol,
                       min_duration=min_segment if min_segment > 0 else None)
    return shares_from_durations(T, min_segment).to(waypoints.dtype)


def _plan_end(plan: Plan) -> torch.Tensor:
    """(B, 3, 3) end derivatives the plan's trajectory was built with."""
    from mapkit.planner._timing import end_state

    speed = plan.end_speed if plan.end_speed is not None else torch.zeros_like(plan.total_time)
    return end_state(plan.waypoints, speed)


def time_cost(shares: torch.Tensor, target_shares: torch.Tensor) -> torch.Tensor:
    """U_T (B,): mean over the M segments of (shares − target)², both (B, M); no gradient to the target."""
    if shares.shape != target_shares.shape or shares.ndim != 2:
        raise PlannerError(
            f"shares and target_shares must both be (B, M), got {tuple(shares.shape)} and {tuple(target_shares.shape)}"
        )
    return ((shares - target_shares.detach().to(shares.dtype)) ** 2).mean(-1)


# ------------------------------------------------------------------------------ several candidates
def _per_candidate(t: torch.Tensor, M: int) -> torch.Tensor:
    """``t`` (B, ...) once per candidate: (B·M, ...), sample-major."""
    return torch.as_tensor(t).repeat_interleave(M, dim=0)


def _batch_mean(t: torch.Tensor, *, dtype: torch.dtype) -> torch.Tensor:
    """A loss term's batch mean, detached, in ``dtype``."""
    return t.detach().to(dtype).mean()


def candidate_loss(
    net: PlannerNet,
    out: PlannerOutput,
    *,
    goal: torch.Tensor,
    T_world_body: torch.Tensor,
    esdf_map: EsdfMap,
    start_velocity: torch.Tensor | None = None,
    end_speed: torch.Tensor | None = None,
    corridor: float | None = None,
    config: LossConfig | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The upper-level loss over every candidate path of ``out`` (B, M, K, 3), winner-takes-all.

    Each candidate's path cost is γ1 U_O + γ2 U_G + γ3 U_S; a sample's loss is its best candidate's
    cost plus α × the mean over candidates (``candidate_spread``), γ4 × the mean escape BCE of every
    candidate's η against its own collision label, the cross-entropy of the scores against
    the best candidate, and γ5 U_T of the best candidate's time split. With M = 1 this is the paper's
    loss U = γ1 U_O + γ2 U_G + γ3 U_S + γ4 U_E + γ5 U_T.

    Returns (total, terms): batch means of the unweighted terms of the chosen candidate ("obstacle",
    "goal", "smoothness", "collision_rate"), plus "escape", "time", "score", "winner_collision_rate",
    "score_accuracy" (chosen = best) and "total"; per sample, "collided_chosen" and "goal_chosen" (B,).
    """
    cfg = config or LossConfig()
    cand = out.candidates if out.candidates is not None else out.keypoints[:, None]
    logits = out.candidate_eta_logits if out.candidate_eta_logits is not None else out.eta_logit[:, None]
    B, M = cand.shape[:2]
    goal = torch.as_tensor(goal, dtype=cand.dtype, device=cand.device)
    plan, u_o, u_g, u_s, collided = _candidate_costs(net, cand, goal, T_world_body, esdf_map, cfg,
                                                     start_velocity=start_velocity, end_speed=end_speed,
                                                     corridor=corridor)
    path = 20.0 * u_o + u_g + 0.5 * u_s  # γ1 U_O + γ2 U_G + γ3 U_S
    rows = torch.arange(B, device=cand.device)
    ranked = path.detach() + cfg.winner_collision_penalty * collided.to(path.dtype)
    winner = ranked.argmin(dim=1)
    per = path[rows, winner]
    if M > 1:
        per = per + cfg.candidate_spread * path.mean(dim=1)
        if cfg.candidate_anchor_pull > 0:
            away = (cand - net.anchor_paths(goal)).square().sum(-1).mean(-1)  # (B, M) m²
            losers = torch.ones_like(away).scatter(1, winner[:, None], 0.0)
            per = per + cfg.candidate_anchor_pull * (away * losers).sum(dim=1) / (M - 1)
    u_e = F.binary_cross_entropy_with_logits(logits, collided.to(logits.dtype), reduction="none").mean(dim=1)
    u_score = _score_loss(out.scores, ranked, winner, like=per, config=cfg)
    u_t = _winner_time_cost(plan, rows, winner, M=M, config=cfg)
    per = per + u_e + cfg.gamma_time * u_t + u_score  # γ4 = 1, the score's weight 1
    total = per.mean()
    chosen = out.chosen if out.chosen is not None else torch.zeros(B, dtype=torch.long, device=cand.device)
    coll_chosen = collided[rows, chosen]
    f = functools.partial(_batch_mean, dtype=total.dtype)
    terms = {
        "obstacle": f(u_o[rows, chosen]), "goal": f(u_g[rows, chosen]), "smoothness": f(u_s[rows, chosen]),
        "escape": f(u_e), "time": f(u_t), "score": f(u_score), "collision_rate": f(coll_chosen),
        "winner_collision_rate": f(collided[rows, winner]), "score_accuracy": f(chosen == winner),
        "total": total.detach(), "collided_chosen": coll_chosen, "goal_chosen": u_g[rows, chosen].detach(),
    }
    return total, terms


def _candidate_costs(
    net: PlannerNet, cand: torch.Tensor, goal: torch.Tensor, T_world_body: torch.Tensor, esdf_map: EsdfMap,
    cfg: LossConfig, *, start_velocity: torch.Tensor | None, end_speed: torch.Tensor | None, corridor: float | None,
) -> tuple[Plan, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every candidate's trajectory (a :class:`Plan` of B·M, sample-major) and its (B, M) obstacle, goal
    and smoothness costs and collision labels."""
    B, M, K, _ = cand.shape
    plan = net.trajectory(cand.reshape(B * M, K, 3),
                          start_velocity=None if start_velocity is None else _per_candidate(start_velocity, M),
                          end_speed=None if end_speed is None else _per_candidate(end_speed, M), corridor=corridor)
    pts_body = sample_trajectory(plan.trajectory, samples_per_second=10.0, min_samples=8)
    pts_world = body_to_world(pts_body, _per_candidate(T_world_body, M))
    goal_m = _per_candidate(goal, M)
    u_o = obstacle_cost(pts_world, esdf_map, robot_radius=cfg.robot_radius,
                        softness=cfg.obstacle_softness).reshape(B, M)
    u_g = goal_cost(plan.waypoints[:, -1], goal_m).reshape(B, M)
    u_s = smoothness_cost(plan.waypoints, torch.zeros_like(goal_m), goal_m).reshape(B, M)
    collided = collision_labels(pts_world, esdf_map, threshold=cfg.robot_radius, raw=True).reshape(B, M)
    return plan, u_o, u_g, u_s, collided


def _score_loss(scores: torch.Tensor | None, ranked: torch.Tensor, winner: torch.Tensor, *, like: torch.Tensor,
                config: LossConfig) -> torch.Tensor:
    """(B,) cross-entropy of the scores against the best candidate (softened by ``score_temperature``
    over the ranking costs `ranked`); zeros shaped `like` without scores or with one candidate."""
    if scores is None or ranked.shape[1] == 1:
        return torch.zeros_like(like)
    if config.score_temperature > 0:
        target = torch.softmax(-ranked / config.score_temperature, dim=1)
        return F.cross_entropy(scores, target, reduction="none")
    return F.cross_entropy(scores, winner, reduction="none")


def _winner_time_cost(plan: Plan, rows: torch.Tensor, winner: torch.Tensor, *, M: int,
                      config: LossConfig) -> torch.Tensor:
    """(B,) U_T of each sample's `winner` candidate's time split in `plan` (B·M plans, sample-major)."""
    B, K = len(rows), plan.shares.shape[-1]
    wp = plan.waypoints.reshape(B, M, K + 1, 3)[rows, winner]
    shares = plan.shares.reshape(B, M, K)[rows, winner]
    target = time_targets(wp, total_time=plan.total_time.reshape(B, M)[rows, winner],
                          start=plan.start.reshape(B, M, 3, 3)[rows, winner],
                          end=_plan_end(plan).reshape(B, M, 3, 3)[rows, winner],
                          min_segment=plan.min_segment, max_iters=config.time_target_iters)
    return time_cost(shares, target)


def time_allocation_loss(
    net: PlannerNet,
    keypoints: torch.Tensor,
    *,
    start_velocity: torch.Tensor | None = None,
    end_speed: torch.Tensor | None = None,
    config: LossConfig | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """γ5 U_T alone for the deployed key-points (B, K, 3) (``mapkit train --set only=tan``: the paths'
    costs do not depend on the TAN). Returns (total, terms) with "time" and "total"."""
    from mapkit.planner._timing import plan_timing

    cfg = config or LossConfig()
    B = keypoints.shape[0]
    kp = keypoints.detach()
    start = torch.zeros(B, 3, 3, dtype=kp.dtype, device=kp.device)
    if start_velocity is not None:
        start[:, 0] = torch.as_tensor(start_velocity, dtype=kp.dtype, device=kp.device)
    speed = torch.zeros(B, dtype=kp.dtype, device=kp.device) if end_speed is None else \
        torch.as_tensor(end_speed, dtype=kp.dtype, device=kp.device)
    wp = torch.cat([torch.zeros_like(kp[:, :1]), kp], dim=1)
    timing = plan_timing(wp, start, speed, net.config, tan=net.tan)
    target = time_targets(wp, total_time=timing.total, start=start, end=timing.end,
                          min_segment=net.config.min_segment_time, max_iters=cfg.time_target_iters)
    u_t = time_cost(timing.shares, target)
    total = cfg.gamma_time * u_t.mean()
    return total, {"time": u_t.detach().mean(), "total": total.detach()}
