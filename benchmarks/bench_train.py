"""Planner training throughput (samples/s, both presets) and planning latency (depth → trajectory).

Issue 5 goals: report training samples/s on CPU for the `cpu` and `paper` presets' input sizes;
planning latency at batch 1 on CPU for the `cpu` preset ≤ 13 ms (the paper: 13.16 ms on an RTX 4060);
issue 11: the shipped model's closed-loop success on a few unseen pairs.
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


def d435_camera(width: int, height: int):
    """The simulator's D435-like camera calibration at ``width`` × ``height``, level."""
    from mapkit.planner import CameraInput
    from mapkit.sim import CameraModel, camera_extrinsics

    cam = CameraModel(width=width, height=height)
    T_bl, T_lo = camera_extrinsics()
    return CameraInput.from_calibration(torch.from_numpy(cam.K), width, height, torch.from_numpy(T_bl @ T_lo))


def throughput(preset_name: str, esdf_map, *, batch: int, steps: int, goals_per_image: int = 1) -> float:
    """Training samples/s of the preset's full step (network, every candidate's min-snap, loss,
    backward); ``goals_per_image`` > 1 shares each depth image among that many goals, as the cpu
    preset's batches do (``goals_together``)."""
    from mapkit.planner import PlannerNet, candidate_loss
    from mapkit.train import preset

    cfg = preset(preset_name)
    net = PlannerNet(cfg.planner)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    images = max(1, batch // goals_per_image)
    depth = torch.rand(images, 480, 640) * 8 + 0.5
    index = torch.arange(batch) % images
    goal = torch.tensor([[6.0, 0.5, 0.0]]).repeat(batch, 1) + torch.randn(batch, 3) * 0.5
    T = torch.eye(4).repeat(batch, 1, 1)
    T[:, 2, 3] = 1.5
    vel = torch.zeros(batch, 3)
    camera = d435_camera(640, 480).expand(batch)
    times = []
    for i in range(steps + 1):
        t = time.perf_counter()
        out = net(net.preprocess(depth), goal, index, camera, vel)
        loss, _ = candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=esdf_map, start_velocity=vel,
                                 config=cfg.loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i:  # the first step pays one-off costs
            times.append(time.perf_counter() - t)
    return batch / float(np.median(times))


def latency(esdf_map) -> tuple[float, float]:
    from mapkit.planner import PlannerNet
    from mapkit.train import preset

    net = PlannerNet(preset("cpu").planner).eval()
    depth = torch.rand(1, 480, 640) * 8 + 0.5
    goal = torch.tensor([[6.0, 0.5, 0.0]])
    vel = torch.zeros(1, 3)
    camera = d435_camera(640, 480)
    times = []
    with torch.inference_mode():
        for i in range(60):
            t = time.perf_counter()
            p = net.plan(depth, goal, start_velocity=vel, camera=camera)
            p.trajectory.position(torch.tensor([0.5]))
            if i >= 10:
                times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times)), 1e3 * float(np.percentile(times, 90))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=5, help="Timed training steps per cpu-preset row.")
    parser.add_argument("--paper-steps", type=int, default=2, help="Timed training steps of the paper-preset row.")
    parser.add_argument("--batch", type=int, default=16, help="Training batch of every row (goals per step).")
    parser.add_argument("--pairs", type=int, default=5, help="Unseen pairs per world for the shipped model's success.")
    parser.add_argument("--world", default="office,garage,forest", help="Comma list of worlds for the shipped model's success.")
    args = parser.parse_args()
    torch.manual_seed(0)
    esdf_map = synthetic_map()
    print(f"torch {torch.__version__}, CPU")
    from mapkit.train import set_threads

    set_threads()
    print(f"{'preset':<8}{'input':>10}{'batch':>7}{'goals/image':>13}{'train samples/s':>17}")
    for name, size, per_image in (("cpu", "96x160", 1), ("cpu", "96x160", 5), ("paper", "360x640", 1)):
        steps = args.steps if name == "cpu" else args.paper_steps
        rate = throughput(name, esdf_map, batch=args.batch, steps=steps, goals_per_image=per_image)
        print(f"{name:<8}{size:>10}{args.batch:>7}{per_image:>13}{rate:>17.1f}")
    torch.set_num_threads(1)
    med, p90 = latency(esdf_map)
    print(f"planning latency (cpu preset, 1 thread, batch 1, depth 640x480 → trajectory): median {med:.2f} ms, "
          f"p90 {p90:.2f} ms; goal <= 13 ms")
    shipped_success(args.pairs, tuple(args.world.split(",")))


def shipped_success(pairs: int, worlds: tuple[str, ...]) -> None:
    """Closed-loop success of the shipped model (`--model pretrained`) on a few unseen pairs, with
    the straight line and the oracle on the same pairs (the full protocol: README, 60 pairs per world)."""
    import tempfile

    from mapkit.evaluation import EvalConfig, evaluate

    with tempfile.TemporaryDirectory() as tmp:
        config = EvalConfig(worlds=worlds, pairs=pairs, seed=101, methods=("learned", "straight", "oracle"))
        result = evaluate("pretrained", f"{tmp}/eval", config, overwrite=True)
    s = result.summary["success"]
    cells = ", ".join(f"{m} {100 * (s[m]['overall']['success_rate'] or 0):.0f} %" for m in config.methods)
    print(f"shipped model, {pairs} unseen pairs per world ({', '.join(worlds)}; seed 101): success {cells}")


if __name__ == "__main__":
    main()
