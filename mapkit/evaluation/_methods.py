"""The methods `mapkit eval` compares, all flying the same closed loop through a :class:`~mapkit.flight.Pilot`.

- ``learned``: the trained planner as deployed (:class:`~mapkit.flight.LearnedMethod` under the flight stack);
  ``learned+uniform`` / ``+poly5`` / ``+gradient``: the same key-points with other time splits (Table III).
- ``untrained``: ``learned``'s architecture at seeded initial weights (``UNTRAINED_SEEDS``).
- ``straight-keypoints``: ``learned`` with the key-points evenly spaced on the straight line to the goal.
- ``iplanner-style``: the network's key-points through a cubic spline timed by arc length at the cruise
  speed (no dynamics, no time allocation, no slowing for turns).
- ``straight``: no perception; one minimum-snap segment to the local goal, timed by the same profile.
- ``oracle``: Dijkstra on the exact world + shortcuts, one corridor minimum-snap trajectory, planned once.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import replace

import numpy as np
import torch

from mapkit.flight import Execution, LearnedMethod, MethodPlan, Observation, Pieces, pieces_from_body
from mapkit.planner import Allocation, CameraInput, PlannerConfig, plan_timing
from mapkit.planner._model import PlannerNet
from mapkit.sim import FreeSpaceGraph, World
from mapkit.trajopt import allocate_times, min_snap

LEARNED_ALLOCATIONS: dict[str, Allocation] = {"learned": "tan", "learned+uniform": "uniform",
                                              "learned+poly5": "poly5", "learned+gradient": "gradient"}
METHODS = ("learned", "learned+uniform", "learned+poly5", "learned+gradient", "untrained", "straight-keypoints",
           "iplanner-style", "straight", "oracle")
"""Every method name, in report order."""
NEEDS_MODEL = frozenset({*LEARNED_ALLOCATIONS, "untrained", "straight-keypoints", "iplanner-style"})
"""Methods that need ``--model``."""
_FULL_STACK = Execution()
"""The default flight stack (immutable, shared)."""
ORACLE_ACCEL = 2.0
"""m/s², the oracle's trapezoidal speed profile."""


class StraightMethod:
    """One minimum-snap segment from the vehicle's state to the local goal, timed by the planner's
    speed profile; no camera."""

    name = "straight"
    needs_depth = False
    replans = True

    def __init__(self, config: PlannerConfig | None = None) -> None:
        self.config = config or PlannerConfig()

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        start = obs.start_body()
        wp = np.stack([start[0], obs.local_goal_body])
        wpt, st = torch.from_numpy(wp)[None], torch.from_numpy(np.ascontiguousarray(start[1:]))[None]  # batches of one
        es = torch.tensor([self.config.cruise_speed if obs.goal_clipped else 0.0], dtype=torch.float64)
        timing = plan_timing(wpt, st, es, self.config, allocation="uniform")
        with torch.no_grad():
            traj = min_snap(wpt, timing.durations, start=st, end=timing.end)
        latency = 1e3 * (time.perf_counter() - t0)
        return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), timing.durations[0].numpy(),
                                                  obs.T_world_body, obs.t), latency_ms=latency)


class OracleMethod:
    """Exact-map search + corridor minimum snap, planned once from the start to the goal."""

    name = "oracle"
    needs_depth = False
    replans = False

    def __init__(self, graph: FreeSpaceGraph, *, corridor: float = 0.1, v_max: float = 2.0,
                 clearance: float = 0.35) -> None:
        self.graph = graph
        self.clearance = clearance
        self.corridor = corridor
        self.v_max = v_max

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        poly = self.graph.path(obs.state_world[0], obs.goal_world)
        # The corridor bounds the deviation across each segment's line, not along it: at a sharp turn
        # the trajectory may run on past the corner. Shorter segments keep that overshoot small; the
        # first that keeps the clearance on the exact world is flown.
        for max_len in (3.0, 1.0, 0.5):
            wp_np = _split_long(poly, max_len)
            wp = torch.from_numpy(wp_np)[None]
            T = allocate_times(wp, "trapezoid", v_max=self.v_max, a_max=ORACLE_ACCEL)
            with torch.no_grad():
                traj = min_snap(wp, T, corridor=self.corridor, on_infeasible="ignore")
                t = torch.arange(0.0, float(T.sum()), 0.02, dtype=torch.float64)
                p = traj.position(t)[0].numpy()
            if bool(traj.solved.all()) and self.graph.world.signed_distance(p).min() >= self.clearance:
                break
        latency = 1e3 * (time.perf_counter() - t0)
        return MethodPlan(pieces=Pieces(t0=obs.t, durations=T[0].numpy(), coeffs=traj.coeffs[0].numpy()),
                          latency_ms=latency, keypoints_world=wp_np)


def _split_long(poly: np.ndarray, max_len: float) -> np.ndarray:
    """Insert points so no polyline segment is longer than ``max_len`` metres (keeps the corridor tight)."""
    out = [poly[0]]
    for a, b in itertools.pairwise(poly):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / max_len)))
        out.extend(a + (b - a) * k / n for k in range(1, n + 1))
    return np.array(out)


def make_methods(names: list[str], net: PlannerNet | None, world: World, graph: FreeSpaceGraph | None, *,
                 oracle_corridor: float = 0.1, robot_radius: float = 0.3, camera: CameraInput | None = None,
                 execution: Execution = _FULL_STACK, untrained: PlannerNet | None = None) -> list:
    """Instantiate the named methods (``net`` needed by the learned ones, ``untrained`` by ``untrained``,
    ``graph`` by the oracle; ``execution``: the flight stack of the learned ones)."""
    cfg = net.config if net is not None else None
    out: list[LearnedMethod | StraightMethod | OracleMethod] = []
    for name in names:
        if name in LEARNED_ALLOCATIONS:
            assert net is not None  # evaluate() refuses learned methods without a model
            out.append(LearnedMethod(name, net, allocation=LEARNED_ALLOCATIONS[name], camera=camera,
                                     execution=execution))
        elif name == "untrained":
            assert untrained is not None  # evaluate() builds it from the model's architecture
            out.append(LearnedMethod(name, untrained, camera=camera, execution=execution))
        elif name == "straight-keypoints":
            assert net is not None  # likewise: its configuration and time allocation
            out.append(LearnedMethod(name, net, camera=camera, execution=execution, keypoints="straight"))
        elif name == "iplanner-style":
            assert net is not None  # likewise
            # iPlanner's spline flies the learned plans' pace, without the turns' slowing (which came later)
            pace = replace(execution, speed=replace(execution.speed, turn_accel=None))
            out.append(LearnedMethod(name, net, spline=True, camera=camera, execution=pace))
        elif name == "straight":
            out.append(StraightMethod(cfg))
        elif name == "oracle":
            assert graph is not None  # built whenever the oracle runs
            out.append(OracleMethod(graph, corridor=oracle_corridor, v_max=cfg.cruise_speed if cfg is not None else 2.0,
                                    clearance=robot_radius + 0.05))
        else:
            raise ValueError(f"unknown method {name!r}")
    return out
