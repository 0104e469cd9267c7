"""Planning latency of the shipped planner, piece by piece, on one CPU thread.

    .venv/bin/python benchmarks/bench_planner.py            # 300 repeats per piece
    .venv/bin/python benchmarks/bench_planner.py --quick    # 60

Depth frames are rendered in a simulated office (the evaluation's camera, 160 × 120) from poses
along a straight flight; the goal lies 6 m ahead, the vehicle flies at 1.5 m/s. Each piece is timed
against its named peer in the same run, the peer being what mapkit used before 2026-11-30:

- the encoder and the nearest-depth pyramid run by ONNX Runtime in one graph
  (``PlannerNet.prepare_inference``, since 2026-11-30) against the eager encoder and the numpy
  pyramid; the network pass with the frozen encoder against the eager encoder;
- the nearest-depth pyramid in numpy against torch's pooling (the same minima);
- the corridor minimum snap (1 m) around the plan's key-points, beside the closed form through them
  (a reference point, not a peer it replaced); and the same corridor with speed and acceleration
  limits tight enough to need re-solving, where the peer sets the problem up again each round
  instead of changing only the limits' bounds; and the corridor without gradients (DAQP's own
  answer) against the same solve with the torch KKT re-solve autograd needs.

Each pair is timed in alternating blocks (median of 10): a shared machine's speed drifts by tens of
per cent within minutes, and alternating blocks see the same drift.

Wall-clock and the thread's CPU time are both printed: on a shared machine the CPU time is the
figure other processes do not move. The closed-loop latency (``mapkit eval``'s latency.json) adds
the memory checks, the corridor's depth checks and the rest of a plan to these pieces.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def _frames(count: int) -> tuple[list[np.ndarray], object]:
    """Depth frames along a flight through a simulated office, and the camera calibration."""
    from mapkit.planner import CameraInput
    from mapkit.sim import CameraModel, camera_extrinsics, make_world, render_depth

    world = make_world("office", seed=11)
    camera = CameraModel(width=160, height=120)
    T_body_link, T_link_optical = camera_extrinsics()
    T_body_camera = T_body_link @ T_link_optical
    frames = []
    for i in range(count):
        T = np.eye(4)
        T[:3, 3] = (1.0 + 0.15 * i % 16.0, 3.5 + 0.05 * (i % 20), 1.5)
        frames.append(render_depth(world, T @ T_body_camera, camera))
    return frames, CameraInput.from_calibration(camera.K, 160, 120, T_body_camera)


def _compare(ours, peer, args_list: list, repeats: int, rounds: int = 10) -> tuple[tuple[float, float], tuple[float, float]]:
    """Median over ``rounds`` alternating blocks of each one's mean wall-clock and thread CPU
    milliseconds per call (a shared machine's speed drifts; alternating blocks share the drift)."""
    per = max(1, repeats // rounds)
    samples: dict[str, list[tuple[float, float]]] = {"ours": [], "peer": []}
    for fn in (ours, peer):
        for a in args_list[:5]:
            fn(*a)
    for r in range(rounds):
        for name, fn in (("ours", ours), ("peer", peer)):
            wall, cpu = time.perf_counter(), time.thread_time()
            for i in range(per):
                fn(*args_list[(r * per + i) % len(args_list)])
            samples[name].append((1e3 * (time.perf_counter() - wall) / per, 1e3 * (time.thread_time() - cpu) / per))
    med = {k: tuple(float(np.median([v[j] for v in vs])) for j in (0, 1)) for k, vs in samples.items()}
    return med["ours"], med["peer"]  # type: ignore[return-value]


def _row(name: str, times: tuple[tuple[float, float], tuple[float, float]], peer_name: str,
         reference: bool = False) -> None:
    """One line: ours, the peer, and the CPU-time ratio (``reference``: the peer is a cheaper
    reference point, not what ours replaced)."""
    ours, peer = times
    ratio = f"×{ours[1] / peer[1]:.1f} its cost" if reference else f"×{peer[1] / ours[1]:.2f} faster"
    print(f"{name:34s} {ours[0]:7.2f} ms ({ours[1]:6.2f} CPU)   {peer_name:28s} {peer[0]:7.2f} ms ({peer[1]:6.2f} CPU)"
          f"   {ratio} (CPU)")


def _inputs(net, frames) -> list[tuple[torch.Tensor]]:
    return [(net.preprocess(torch.from_numpy(d[None].astype(np.float32))),) for d in frames]


def _network(net, frames, camera, repeats: int) -> None:
    from mapkit.planner._depthcheck import nearest_depth_pyramid
    goal = torch.tensor([[6.0, 0.0, 0.0]])
    velocity = torch.tensor([[1.5, 0.0, 0.0]])
    inputs = _inputs(net, frames)
    net.prepare_inference()
    frozen = net._frozen_encoder
    assert frozen is not None  # ONNX Runtime is a dependency

    def forward(x):
        return net(x, goal, camera=camera, velocity=velocity)

    def encoder_and_pyramid(x):  # the eager encoder, then the numpy pyramid
        return net.encoder(x), nearest_depth_pyramid(x)

    def forward_eager(x):
        net._frozen_encoder = None
        try:
            return forward(x)
        finally:
            net._frozen_encoder = frozen

    with torch.inference_mode():
        _row("encoder + pyramid (onnxruntime)", _compare(frozen.module, encoder_and_pyramid, inputs, repeats),
             "eager encoder + numpy pyramid")
        _row("network pass (encoder included)", _compare(forward, forward_eager, inputs, repeats),
             "with the eager encoder")


def _pyramid(net, frames, repeats: int) -> None:
    from mapkit.planner._depthcheck import _pyramid_torch, nearest_depth_pyramid

    def pooling(x):
        return _pyramid_torch(torch.where(x[:, 1:2] > 0.5, x[:, :1], torch.ones_like(x[:, :1])))

    with torch.inference_mode():
        _row("nearest-depth pyramid", _compare(nearest_depth_pyramid, pooling, _inputs(net, frames), repeats),
             "torch pooling")


def _min_snap(net, frames, camera, repeats: int) -> None:
    from mapkit.planner import plan_timing
    from mapkit.trajopt import min_snap

    goal = torch.tensor([[6.0, 0.0, 0.0]])
    problems = []
    with torch.inference_mode():
        for (x,) in _inputs(net, frames):
            out = net(x, goal, camera=camera)
            wp = torch.cat([torch.zeros(1, 1, 3), out.keypoints], dim=1).double()
            start = torch.zeros(1, 3, 3, dtype=torch.float64)
            start[0, 0, 0] = 1.5
            timing = plan_timing(wp, start, torch.tensor([2.0], dtype=torch.float64), net.config, tan=net.tan)
            problems.append((wp, timing.durations, start, timing.end))
    def limited(wp, T, start, end):
        return min_snap(wp, T, start=start, end=end, corridor=1.0, on_infeasible="ignore", limits_everywhere=True,
                        v_max=2.0, a_max=1.5)

    def corridor(wp, T, start, end):
        return min_snap(wp, T, start=start, end=end, corridor=1.0, on_infeasible="ignore")

    def pinned(wp, T, start, end):
        return min_snap(wp, T, start=start, end=end)

    def corridor_polished(*args):
        with torch.enable_grad():
            return corridor(*args)

    with torch.no_grad():
        _row("corridor min snap (1 m)", _compare(corridor, pinned, problems, repeats), "through the key-points",
             reference=True)
        _row("  without gradients: DAQP's answer", _compare(corridor, corridor_polished, problems, repeats),
             "with the torch KKT re-solve")
        _row("  + v/a limits, re-solved", _compare(limited, corridor, problems, repeats // 3),
             "the corridor without limits", reference=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="60 repeats per piece instead of 300")
    parser.add_argument("--repeats", type=int, help="calls per piece (default 300, 60 with --quick); 10 rounds of a tenth")
    parser.add_argument("--frames", type=int, default=20, help="depth frames the calls cycle through")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from mapkit.flight import Planner, resolve_model

    repeats = args.repeats or (60 if args.quick else 300)
    net = Planner.load(resolve_model("pretrained")).net.eval()
    frames, camera = _frames(args.frames)
    print(f"shipped planner, input {net.config.input_size}, one thread, {repeats} repeats (torch {torch.__version__})")
    _network(net, frames, camera, repeats)
    _pyramid(net, frames, repeats)
    _min_snap(net, frames, camera, repeats)


if __name__ == "__main__":
    main()
