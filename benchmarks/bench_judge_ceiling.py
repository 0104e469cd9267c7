"""How much the judge leaves without the flight stack: a model's own trained candidates flown under
``mapkit eval --stack none``, chosen at every replan by a stand-in judge instead of the network's.

The stand-in looks at each candidate's trajectory as it would be flown (the loop's timing and
corridor), flies the best-scored clear one (the network's own scores) and vetoes the plan when none is
clear, as the loop treats η >= 0.5 (keep the last plan, or hover and turn). Judges:

- ``network``: the network's own choice and η (what ``mapkit eval`` flies);
- ``exact``: clear = 0.3 m from the exact world;
- ``image``: clear = 0.3 m from every point of the depth image the plan was made from (every second
  pixel; what lies out of view counts as free), and of the flight's frames of the last ``--history``
  seconds (default 0: none);

each over the trajectory's first ``--horizon-m`` metres (default 2.5; 0: all of it), or its first
``--horizon-s`` seconds. The path judged (``--path``): ``flown`` the trajectory the loop flies (in
its corridor); ``through`` the minimum-snap trajectory through the key-points with the same timing
(what the network's own ``PlannerNet.trajectory`` gives); ``keypoints`` the key-point polyline from
the plan's start (every 0.1 m; ``--horizon-m`` only).

An exact judge bounds what judging these candidates can give; the image judge what one depth image
can tell about them. docs/results.md ("The judge against an exact one, without the stack" and "The
judge must see the trajectory as flown") has the figures of dev seeds 300 and 301. Prints success, collisions and timeouts per world.

    python benchmarks/bench_judge_ceiling.py --seed 301 --pairs 40 --judge network,exact,image
    python benchmarks/bench_judge_ceiling.py --seed 301 --pairs 40 --judge exact --horizon-m 0 --horizon-s 2
    python benchmarks/bench_judge_ceiling.py --seed 300 --pairs 80 --judge image --horizon-m 1.5 --path keypoints
    python benchmarks/bench_judge_ceiling.py --seed 301 --pairs 40 --judge image --horizon-m 1.5 --history 1.5
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from typing import Literal

import numpy as np
import torch

from mapkit.evaluation import EvalConfig
from mapkit.evaluation import _run as run
from mapkit.evaluation._loop import run_episode
from mapkit.evaluation._stack import Run
from mapkit.flight import _learned as methods
from mapkit.sim import render_depth

ROBOT_RADIUS = 0.3
PATH_NAMES = {"flown": "trajectory as flown", "through": "trajectory through the key-points",
              "keypoints": "key-point polyline"}


@dataclasses.dataclass
class Judge:
    kind: Literal["network", "exact", "image"]
    horizon_s: float | None = None
    horizon_m: float | None = None
    path: Literal["flown", "through", "keypoints"] = "flown"
    history: float = 0.0


def _cut(pts: np.ndarray, start: np.ndarray, horizon_m: float | None) -> np.ndarray:
    """The points of ``pts`` (P, 3) within ``horizon_m`` metres along them from ``start``."""
    if horizon_m is None:
        return pts
    along = np.cumsum(np.linalg.norm(np.diff(np.vstack([start[:1], pts]), axis=0), axis=1))
    return pts[along <= horizon_m]


def _polyline(start: np.ndarray, keypoints: np.ndarray, step: float = 0.1) -> np.ndarray:
    """(P, 3) points every ``step`` metres along start → k1 → … → kK (the start excluded)."""
    corners = np.vstack([start[:1], keypoints])
    pts = []
    for a, b in itertools.pairwise(corners):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        pts.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(pts)


def _stretch(traj, start: np.ndarray, judge: Judge) -> np.ndarray:
    """(P, 3) body-frame samples of the part of ``traj`` the judge looks at."""
    return _cut(methods._samples(traj, count=96, within=judge.horizon_s)[0, 0].numpy(), start, judge.horizon_m)


def _image_points(depth: np.ndarray, K: np.ndarray, T_body_camera: np.ndarray) -> np.ndarray:
    """(P, 3) the depth image's points (every second pixel) in the body frame."""
    v, u = np.mgrid[0:depth.shape[0]:2, 0:depth.shape[1]:2]
    z = depth[::2, ::2]
    ok = np.isfinite(z) & (z > 0)
    cam = np.stack([(u[ok] - K[0, 2]) / K[0, 0] * z[ok], (v[ok] - K[1, 2]) / K[1, 1] * z[ok], z[ok]], axis=1)
    return cam @ T_body_camera[:3, :3].T + T_body_camera[:3, 3]


class _Recent:
    """The world points of one flight's frames of the last ``seconds``."""

    def __init__(self, seconds: float) -> None:
        self.seconds, self.frames = seconds, []

    def tree(self, obs, body: np.ndarray):
        """A KD-tree of ``body`` and the recent frames' points in the body frame of ``obs``, or None;
        ``body`` joins the recent frames (a time that goes back starts a new flight)."""
        from scipy.spatial import cKDTree

        T = obs.T_world_body
        if self.frames and obs.t < self.frames[-1][0]:
            self.frames = []
        self.frames = [(t, p) for t, p in self.frames if 0 < obs.t - t <= self.seconds + 1e-6]
        points = np.vstack([body, *[(p - T[:3, 3]) @ T[:3, :3] for _, p in self.frames]])
        self.frames.append((obs.t, body @ T[:3, :3].T + T[:3, 3]))
        return cKDTree(points) if len(points) else None


def stand_in(method, world, camera, judge: Judge):
    """Wrap ``method`` (a LearnedMethod) so that ``judge`` chooses among its trained candidates."""
    own_keypoints = method._keypoints
    recent = _Recent(judge.history)

    def keypoints(obs, start, goal, end_speed=0.0):
        x, out = own_keypoints(obs, start, goal, end_speed)
        tree = recent.tree(obs, _image_points(np.asarray(obs.depth), np.asarray(camera.K), np.asarray(camera.T_body_camera))) \
            if judge.kind == "image" else None
        T = obs.T_world_body
        clear = []
        for c in out.candidates[0].double().numpy():
            if judge.path == "keypoints":
                pts = _cut(_polyline(start, c), start, judge.horizon_m)
            else:
                wp, st, es = methods._tensors(np.vstack([start[:1], c]), start, end_speed)
                with torch.inference_mode():
                    timing = method._timed(wp, st, es)
                    traj = (methods.min_snap(wp, timing.durations, start=st, end=timing.end) if judge.path == "through"
                            else methods._execute(wp, timing.durations, st, timing.end, method.execution, None))
                pts = _stretch(traj, start, judge)
            if not len(pts):
                clear.append(True)
            elif judge.kind == "exact":
                clear.append(world.signed_distance(pts @ T[:3, :3].T + T[:3, 3]).min() >= ROBOT_RADIUS)
            else:
                clear.append(tree is None or tree.query(pts)[0].min() >= ROBOT_RADIUS)
        scores = out.scores[0].numpy()
        clear = np.array(clear)
        m = int(np.argmax(np.where(clear, scores, -np.inf))) if clear.any() else int(np.argmax(scores))
        logit = torch.full((1,), -10.0 if clear.any() else 10.0)
        return x, dataclasses.replace(out, keypoints=out.candidates[:, m], eta=torch.sigmoid(logit), eta_logit=logit,
                                      chosen=torch.full_like(out.chosen, m))

    if judge.kind != "network":
        method._keypoints = keypoints


def fly(model: str, kind: str, seed: int, pairs: int, judge: Judge) -> list[str]:
    config = EvalConfig(worlds=(kind,), pairs=pairs, seed=seed, methods=("learned",), stacks=("none",))
    context = run._model_context(model, config)
    _, world_pairs = run._worlds_and_pairs(config)
    setup = run._WorkerSetup(model=run._model_for_workers(model, config), model_sha256=None, camera=context.camera,
                             runs=(Run("learned", "none"),), config=config)
    run._init_worker(setup)
    bundle = run._world_bundle(kind)
    pilot = bundle.pilots[0]  # the loop flies a pilot; the judge is swapped inside its planner
    stand_in(pilot.planner, bundle.world, setup.camera, judge)
    T_body_camera = np.asarray(setup.camera.T_body_camera)
    outcomes = []
    for pair in world_pairs[kind]:
        p = pair.to_dict()
        episode = run_episode(bundle.world, np.asarray(p["start"]), np.asarray(p["goal"]), pilot, config.loop,
                              render=lambda T: render_depth(bundle.world, T @ T_body_camera, bundle.camera,
                                                            rays=bundle.rays))
        outcomes.append(episode.outcome)
    return outcomes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="pretrained")
    ap.add_argument("--seed", type=int, default=301)
    ap.add_argument("--pairs", type=int, default=20, help="per world")
    ap.add_argument("--world", default="office,garage,forest")
    ap.add_argument("--judge", default="network,exact", help="comma-separated: network, exact, image")
    ap.add_argument("--horizon-s", type=float, default=None, help="also only the first seconds (pass --horizon-m 0 for these alone)")
    ap.add_argument("--horizon-m", type=float, default=2.5, help="the first metres only (0: the whole trajectory)")
    ap.add_argument("--path", choices=("flown", "through", "keypoints"), default="flown",
                    help="judge the trajectory as flown, the one through the key-points, or their polyline")
    ap.add_argument("--history", type=float, default=0.0,
                    help="seconds of the flight's earlier frames the image judge also reads (0: the image alone)")
    args = ap.parse_args()
    if args.path == "keypoints" and args.horizon_s is not None:
        ap.error("--path keypoints has no timing: judge it with --horizon-m alone")
    torch.set_num_threads(1)
    for name in args.judge.split(","):
        if name not in ("network", "exact", "image"):
            ap.error(f"--judge {name!r}: expected network, exact or image")
        judge = Judge(name, args.horizon_s, args.horizon_m or None, args.path, args.history)  # type: ignore[arg-type]
        line, total = f"{name:8s}", []
        for kind in args.world.split(","):
            outcomes = fly(args.model, kind, args.seed, args.pairs, judge)
            total += outcomes
            line += (f"  {kind} {100 * outcomes.count('success') / len(outcomes):5.1f} %"
                     f" ({outcomes.count('collision')} coll., {outcomes.count('timeout')} t/o)")
        print(f"{line}  overall {100 * total.count('success') / len(total):5.1f} % of {len(total)}", flush=True)
    print(f"seed {args.seed}, stack none; exact and image judge the first "
          f"{f'{args.horizon_s} s' if args.horizon_s else f'{args.horizon_m} m' if args.horizon_m else 'whole trajectory'}"
          f" of the {PATH_NAMES[args.path]}" + (f"; the image judge also reads {args.history:g} s of earlier frames"
                                                if args.history else ""))


if __name__ == "__main__":
    main()
