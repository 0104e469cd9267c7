"""Per-frame latency of the pilot (goal: full stack median ≤ 15 ms, p95 ≤ 30 ms on one thread).

    .venv/bin/python benchmarks/bench_pilot.py [--pairs 4] [--seed 11]

The shipped model's pilot (`Pilot.load("pretrained")`, full stack and stack none) flies ``--pairs``
start–goal pairs in each of `mapkit eval`'s worlds (seed 11, the linear tracker), one thread. Rows: the
wall-clock time of every `Pilot.step` that planned (checks, the frame's camera, the plan, the
reference's yaw profile), and, as the named peer measured in the same calls, the planner inside it
(`LearnedMethod.plan`, what `mapkit eval` timed before the pilot): median, p95, and the pilot's
overhead as a ratio.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np


class _TimedPilot:
    """Records the latency of every planning call of a pilot (and of the planner inside it)."""

    def __init__(self, pilot) -> None:
        self.pilot, self.step_ms, self.plan_ms = pilot, [], []
        original = pilot.step

        def step(*args, **kwargs):
            out = original(*args, **kwargs)
            if out.replanned:
                self.step_ms.append(out.latency_ms)
                self.plan_ms.append(out.plan.latency_ms)
            return out

        pilot.step = step


def fly(stack: str, pairs: int, seed: int) -> _TimedPilot:
    from mapkit.evaluation import LoopConfig, run_episode, sample_pairs
    from mapkit.flight import Pilot
    from mapkit.sim import WORLD_KINDS, CameraModel, FreeSpaceGraph, make_world, render_depth

    timed = _TimedPilot(Pilot.load("pretrained", stack=stack))
    cam = timed.pilot.camera
    camera = CameraModel(width=cam.width, height=cam.height, fx=float(cam.K[0, 0]), fy=float(cam.K[1, 1]))
    for kind in WORLD_KINDS:
        world = make_world(kind, seed=seed)
        for pair in sample_pairs(FreeSpaceGraph(world, clearance=0.6), pairs, seed=seed, min_distance=8.0):
            def render(T_world_body: np.ndarray, world=world) -> np.ndarray:
                return render_depth(world, T_world_body @ cam.T_body_camera, camera)

            run_episode(world, pair.start, pair.goal, timed.pilot, LoopConfig(), render=render)
    return timed


def main() -> None:
    import torch

    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    print(f"{'stack':6s} {'plans':>6s} {'pilot median':>13s} {'p95':>7s} {'planner median':>15s} {'p95':>7s} "
          f"{'pilot / planner (median)':>25s}")
    for stack in ("full", "none"):
        t = fly(stack, args.pairs, args.seed)
        step, plan = np.array(t.step_ms), np.array(t.plan_ms)
        print(f"{stack:6s} {len(step):6d} {np.median(step):10.1f} ms {np.percentile(step, 95):5.1f} ms "
              f"{np.median(plan):12.1f} ms {np.percentile(plan, 95):5.1f} ms {np.median(step) / np.median(plan):24.2f}x")
    print("goal: full stack median ≤ 15 ms, p95 ≤ 30 ms (one thread)")


if __name__ == "__main__":
    main()
