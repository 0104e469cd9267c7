"""Planner training throughput (samples/s, both presets) and planning latency (depth → trajectory).

Issue 5 goals: report training samples/s on CPU for the `cpu` and `paper` presets' input sizes;
planning latency at batch 1 on CPU for the `cpu` preset ≤ 13 ms (the paper: 13.16 ms on an RTX 4060).
A synthetic scene (floor + boxes) stands in for a map so the figures measure the network, the
min-snap layer and the loss, not disk reads.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def synthetic_map():
    from mapkit.esdf import EsdfMap, signed_distance

    occ = np.zeros((120, 120, 40), dtype=bool)
    occ[:, :, :3] = True
    rng = np.random.default_rng(0)
    for _ in range(25):
        x, y = rng.integers(5, 115, size=2)
        occ[x - 2 : x + 2, y - 2 : y + 2, :30] = True
    esdf = signed_distance(occ, voxel_size=0.1)
    return EsdfMap(esdf=esdf, voxel_size=0.1, origin=np.array([-6.0, -6.0, -0.3]))


def throughput(preset_name: str, esdf_map, *, batch: int, steps: int) -> float:
    from mapkit.planner import LossConfig, PlannerConfig, PlannerNet, planner_loss
    from mapkit.train import preset

    cfg = preset(preset_name)
    net = PlannerNet(PlannerConfig.from_dict(cfg.planner))
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    h, w = cfg.planner["input_size"]
    depth = torch.rand(batch, 480, 640) * 8 + 0.5
    goal = torch.tensor([[6.0, 0.5, 0.0]]).repeat(batch, 1)
    T = torch.eye(4).repeat(batch, 1, 1)
    T[:, 2, 3] = 1.5
    vel = torch.zeros(batch, 3)
    loss_cfg = LossConfig()
    times = []
    for i in range(steps + 1):
        t = time.perf_counter()
        plan = net.plan(depth, goal, start_velocity=vel)
        loss, _ = planner_loss(plan, goal=goal, T_world_body=T, esdf_map=esdf_map, config=loss_cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i:  # the first step pays one-off costs
            times.append(time.perf_counter() - t)
    del h, w
    return batch / float(np.median(times))


def latency(esdf_map) -> tuple[float, float]:
    from mapkit.planner import PlannerConfig, PlannerNet
    from mapkit.train import preset

    net = PlannerNet(PlannerConfig.from_dict(preset("cpu").planner)).eval()
    depth = torch.rand(1, 480, 640) * 8 + 0.5
    goal = torch.tensor([[6.0, 0.5, 0.0]])
    vel = torch.zeros(1, 3)
    times = []
    with torch.inference_mode():
        for i in range(60):
            t = time.perf_counter()
            p = net.plan(depth, goal, start_velocity=vel)
            p.trajectory.position(torch.tensor([0.5]))
            if i >= 10:
                times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times)), 1e3 * float(np.percentile(times, 90))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=5)
    args = parser.parse_args()
    torch.manual_seed(0)
    esdf_map = synthetic_map()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU")
    print(f"{'preset':<8}{'input':>10}{'batch':>7}{'train samples/s':>17}")
    for name, size, batch in (("cpu", "96x160", 16), ("paper", "360x640", 16)):
        rate = throughput(name, esdf_map, batch=batch, steps=args.steps if name == "cpu" else 2)
        print(f"{name:<8}{size:>10}{batch:>7}{rate:>17.1f}")
    med, p90 = latency(esdf_map)
    print(f"planning latency (cpu preset, batch 1, depth 640x480 → trajectory): median {med:.2f} ms, p90 {p90:.2f} ms; goal <= 13 ms")


if __name__ == "__main__":
    main()
