"""`mapkit fly` over DDS on loopback: setpoint timing, latency, and software-in-the-loop success
(goals: ≥ 99 % of setpoint periods within 2 ms of nominal while the planner runs; median latency from a
depth message to the first setpoint of its plan ≤ 40 ms; success within 5 points of `mapkit eval
--vehicle rotorpy` on the same pairs).

    .venv/bin/python benchmarks/bench_fly.py [--world office] [--pairs 3] [--seed 10012]

The node (`FlyNode`, the shipped model, full stack, simulator time) runs in this process as `mapkit fly`
runs it; the simulated vehicle (`SimulatedVehicle`: the world, its depth camera, rotorpy's quadrotor)
runs in a second process and flies `mapkit eval`'s pairs for the world and seed in real time. Named
peers, measured in the same run: the setpoint stream while no plan is made (before the first goal),
and `mapkit eval --vehicle rotorpy --stack full` on the same pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

NOMINAL_RATE = 50.0
DOMAIN = 201


def harness(world_kind: str, pairs: int, seed: int) -> None:
    """The vehicle's process: fly the pairs and print one JSON line per flight."""
    from mapkit.evaluation import LoopConfig, sample_pairs
    from mapkit.flight._recorded import load_network
    from mapkit.fly import DdsConfig, FlyConfig, Link, SimulatedVehicle
    from mapkit.sim import FreeSpaceGraph, make_world

    world = make_world(world_kind, seed=seed)
    net, camera = load_network("pretrained")
    loop = LoopConfig()  # mapkit eval's judge: its goal and robot radii, its time limit at the model's pace
    vehicle = SimulatedVehicle(Link(DdsConfig(domain_id=DOMAIN)), world, camera, FlyConfig())
    if not vehicle.wait_for_node(60):
        raise SystemExit("no node on the loopback domain")
    chosen = sample_pairs(FreeSpaceGraph(world, clearance=0.6), pairs, seed=seed, min_distance=8.0)
    vehicle.hover(chosen[0].start, 3.0)  # the peer: the stream while no plan is made
    print(json.dumps({"idle_until": True}), flush=True)
    for pair in chosen:
        limit = max(loop.timeout_min, loop.timeout_factor * pair.distance / net.config.cruise_speed)
        flight = vehicle.fly(pair.start, pair.goal, time_limit=limit, goal_radius=loop.goal_radius,
                             robot_radius=loop.robot_radius)
        print(json.dumps({"pair": pair.index, "outcome": flight.outcome, "time_s": flight.time_s}), flush=True)


def fly_pairs(args: argparse.Namespace) -> tuple[list[dict], object]:
    """Run the node here and the vehicle in a subprocess; (flights, node)."""
    import torch

    from mapkit.flight import Pilot
    from mapkit.fly import DdsConfig, FlyConfig, FlyNode, Link

    torch.set_num_threads(1)
    sys.setswitchinterval(0.0005)  # as `mapkit fly` sets it
    config = FlyConfig(link=DdsConfig(domain_id=DOMAIN), sim_time=True, fence_radius=100.0, fence_height=20.0)
    node = FlyNode(Pilot.load("pretrained"), config, Link(config.link))
    node.start()
    cmd = [sys.executable, __file__, "--harness", "--world", args.world, "--pairs", str(args.pairs), "--seed", str(args.seed)]
    flights, idle_until = [], None
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            row = json.loads(line)
            if "idle_until" in row:
                idle_until = time.perf_counter()
            else:
                flights.append(row)
                print(f"  pair {row['pair']}: {row['outcome']} in {row['time_s']:.1f} s", flush=True)
    node.close()
    node.idle_until = idle_until
    return flights, node


def timing(node: object) -> None:
    times = np.array(node.setpoint_times)
    idle = times[times <= node.idle_until] if node.idle_until else times[:0]
    busy = times[times > node.idle_until] if node.idle_until else times
    nominal = 1.0 / NOMINAL_RATE
    print(f"setpoint stream at {NOMINAL_RATE:g} Hz: periods within 2 ms of {1e3 * nominal:g} ms")
    for name, t in (("while planning", busy), ("idle (peer)", idle)):
        if len(t) < 3:
            continue
        err = np.abs(np.diff(t) - nominal)
        print(f"  {name:15s} {100 * np.mean(err <= 0.002):6.2f} % of {len(err)}, worst {1e3 * err.max():.1f} ms, "
              f"p99 {1e3 * np.quantile(err, 0.99):.2f} ms")
    times_sorted = np.sort(times)
    lat = []
    for received, returned, step in node.steps:
        if step.taken:
            i = np.searchsorted(times_sorted, returned)
            if i < len(times_sorted):
                lat.append(1e3 * (times_sorted[i] - received))
    if lat:
        plan = [s.latency_ms for _, _, s in node.steps if s.taken]
        print(f"depth message → first setpoint of its plan: median {np.median(lat):.1f} ms, p95 "
              f"{np.quantile(lat, 0.95):.1f} ms over {len(lat)} plans (the pilot's step inside: median "
              f"{np.median(plan):.1f} ms; ratio {np.median(lat) / np.median(plan):.2f}x)")


def eval_peer(args: argparse.Namespace) -> dict[int, str]:
    """`mapkit eval --vehicle rotorpy --methods learned --stack full` on the same world, seed and pairs."""
    import tempfile
    from pathlib import Path

    from mapkit.evaluation import EvalConfig, evaluate

    config = EvalConfig(worlds=(args.world,), pairs=args.pairs, seed=args.seed, methods=("learned",), stacks=("full",),
                        vehicle="rotorpy")
    with tempfile.TemporaryDirectory() as tmp:
        evaluate("pretrained", Path(tmp) / "eval", config, progress=False)
        rows = json.loads((Path(tmp) / "eval" / "results.json").read_text())["episodes"]
    return {int(r["pair"]): r["outcome"] for r in rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=10012)
    parser.add_argument("--no-eval", action="store_true", help="skip the `mapkit eval` peer")
    parser.add_argument("--harness", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.harness:
        return harness(args.world, args.pairs, args.seed)
    print(f"mapkit fly, software in the loop: {args.pairs} pairs of {args.world} seed {args.seed}, loopback DDS")
    flights, node = fly_pairs(args)
    success = 100.0 * float(np.mean([f["outcome"] == "success" for f in flights])) if flights else 0.0
    timing(node)
    print(f"success over DDS: {success:.1f} % of {len(flights)}")
    if not args.no_eval:
        outcomes = eval_peer(args)
        peer = 100.0 * float(np.mean([o == "success" for o in outcomes.values()]))
        same = sum(outcomes.get(f["pair"]) == f["outcome"] for f in flights)
        print(f"mapkit eval --vehicle rotorpy, same pairs (peer): {peer:.1f} %; difference {success - peer:+.1f} points; "
              f"the same outcome on {same} of {len(flights)} pairs")


if __name__ == "__main__":
    main()
