"""`mapkit fly` over DDS on loopback: setpoint timing, latency, and software-in-the-loop success
(goals: ≥ 99 % of setpoint periods within 2 ms of nominal while the planner runs; median latency from a
depth message to the first setpoint flown from its plan ≤ 40 ms; success within 5 points of `mapkit eval
--vehicle rotorpy` on the same pairs).

    .venv/bin/python benchmarks/bench_fly.py [--world office|garage|forest|all] [--pairs 3] [--seed 10012]
                                             [--domain 201] [--json rows.json]

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
WORLDS = ("office", "garage", "forest")


def harness(world_kind: str, pairs: int, seed: int, domain: int, only: list[int]) -> None:
    """The vehicle's process: fly the pairs and print one JSON line per flight."""
    from mapkit.evaluation import judging_loop, sample_pairs
    from mapkit.flight import Pilot
    from mapkit.fly import DdsConfig, FlyConfig, Link, SimulatedVehicle
    from mapkit.sim import FreeSpaceGraph, make_world

    sys.setswitchinterval(0.0005)  # setpoints (Cyclone's thread) reach the vehicle without waiting for a step
    world = make_world(world_kind, seed=seed)
    camera = Pilot.load("pretrained").camera
    loop = judging_loop("pretrained")  # mapkit eval's judge: its goal and robot radii, its time limit
    vehicle = SimulatedVehicle(Link(DdsConfig(domain_id=domain)), world, camera, FlyConfig())
    if not vehicle.wait_for_node(60):
        raise SystemExit("no node on the loopback domain")
    chosen = sample_pairs(FreeSpaceGraph(world, clearance=0.6), pairs, seed=seed, min_distance=8.0)
    vehicle.hover(chosen[0].start, 3.0)  # the peer: the stream while no plan is made
    print(json.dumps({"idle_until": True}), flush=True)
    for pair in chosen:
        if only and pair.index not in only:
            continue
        flight = vehicle.fly(pair.start, pair.goal, time_limit=loop.time_limit(pair.distance), goal_radius=loop.goal_radius,
                             robot_radius=loop.robot_radius)
        print(json.dumps({"pair": pair.index, "outcome": flight.outcome, "time_s": flight.time_s}), flush=True)


def fly_pairs(args: argparse.Namespace, world: str) -> tuple[list[dict], object]:
    """Run the node here and the vehicle in a subprocess; (flights, node)."""
    import torch

    from mapkit.flight import Pilot
    from mapkit.fly import DdsConfig, FlyConfig, FlyNode, Link

    torch.set_num_threads(1)
    sys.setswitchinterval(0.0005)  # as `mapkit fly` sets it
    config = FlyConfig(link=DdsConfig(domain_id=args.domain), sim_time=True, fence_radius=100.0, fence_height=20.0)
    node = FlyNode(Pilot.load("pretrained", config=config.pilot), config, Link(config.link))
    node.start()
    cmd = [sys.executable, __file__, "--harness", "--world", world, "--pairs", str(args.pairs), "--seed", str(args.seed),
           "--domain", str(args.domain), "--only", ",".join(map(str, args.only))]
    flights, idle_until = [], None
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            row = json.loads(line)
            if "idle_until" in row:
                idle_until = time.perf_counter()
            else:
                flights.append({"world": world, **row})
                print(f"  {world} pair {row['pair']}: {row['outcome']} in {row['time_s']:.1f} s", flush=True)
    node.close()
    node.link.close()
    node.idle_until = idle_until
    return flights, node


def timing(node: object) -> None:
    times = np.array(node.setpoint_times)
    idle = times[times <= node.idle_until] if node.idle_until else times[:0]
    busy = times[times > node.idle_until] if node.idle_until else times
    nominal = 1.0 / NOMINAL_RATE
    print(f"setpoint stream at {NOMINAL_RATE:g} Hz ({node.stream_priority} priority): periods within 2 ms of "
          f"{1e3 * nominal:g} ms")
    for name, t in (("while planning", busy), ("idle (peer)", idle)):
        if len(t) < 3:
            continue
        err = np.abs(np.diff(t) - nominal)
        print(f"  {name:15s} {100 * np.mean(err <= 0.002):6.2f} % of {len(err)}, worst {1e3 * err.max():.1f} ms, "
              f"p99 {1e3 * np.quantile(err, 0.99):.2f} ms")
    times_sorted = np.sort(times)
    taken = [t for t in node.steps if t.step.taken and np.searchsorted(times_sorted, t.takeover) < len(times_sorted)]
    if not taken:
        return
    first = np.array([times_sorted[np.searchsorted(times_sorted, t.takeover)] for t in taken])
    stages = {"waiting for the planner": [t.called - t.received for t in taken],
              "the pilot's step and the hand-over": [t.handed - t.called for t in taken],
              "until the time it was made for": [t.takeover - t.handed for t in taken],
              "until the next setpoint": first - [t.takeover for t in taken]}
    lat = 1e3 * (first - [t.received for t in taken])
    print(f"depth message → the first setpoint flown from its plan: median {np.median(lat):.1f} ms, p95 "
          f"{np.quantile(lat, 0.95):.1f} ms over {len(lat)} plans; medians: " +
          ", ".join(f"{name} {1e3 * np.median(v):.1f} ms" for name, v in stages.items()))
    print(f"  plans made for {1e3 * node.plan_lead:.0f} ms ahead at the end (plan_lead, measured); {node.late_plans} "
          f"arrived after their time, by {_spread(node.late_by)}")


def _spread(seconds: object) -> str:
    values = 1e3 * np.asarray(list(seconds), dtype=float)
    return f"median {np.median(values):.1f} ms, max {values.max():.1f} ms" if len(values) else "nothing"


def eval_peer(args: argparse.Namespace, worlds: tuple[str, ...]) -> dict[tuple[str, int], str]:
    """`mapkit eval --vehicle rotorpy --methods learned --stack full` on the same worlds, seed and pairs."""
    import tempfile
    from pathlib import Path

    from mapkit.evaluation import EvalConfig, evaluate

    config = EvalConfig(worlds=worlds, pairs=args.pairs, seed=args.seed, methods=("learned",), stacks=("full",),
                        vehicle="rotorpy")
    with tempfile.TemporaryDirectory() as tmp:
        evaluate("pretrained", Path(tmp) / "eval", config, progress=False)
        rows = json.loads((Path(tmp) / "eval" / "results.json").read_text())["episodes"]
    return {(r["world"], int(r["pair"])): r["outcome"] for r in rows}


def compare(flights: list[dict], outcomes: dict[tuple[str, int], str], worlds: tuple[str, ...]) -> None:
    """Success over DDS against the peer's, per world and over all, and how many pairs end the same way."""
    def rate(values: list[str]) -> float:
        return 100.0 * float(np.mean([v == "success" for v in values])) if values else 0.0

    for world in (*worlds, "all") if len(worlds) > 1 else worlds:
        mine = [f["outcome"] for f in flights if world in ("all", f["world"])]
        peer = [outcomes[(f["world"], f["pair"])] for f in flights if world in ("all", f["world"])]
        same = sum(p == m for p, m in zip(peer, mine, strict=True))
        print(f"  {world:7s} over DDS {rate(mine):5.1f} %, mapkit eval --vehicle rotorpy (peer) {rate(peer):5.1f} %: "
              f"difference {rate(mine) - rate(peer):+.1f} points; the same outcome on {same} of {len(mine)} pairs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", choices=(*WORLDS, "all"))
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=10012)
    parser.add_argument("--domain", type=int, default=201, help="DDS domain id (runs side by side need their own)")
    parser.add_argument("--only", type=lambda v: [int(i) for i in v.split(",") if i], default=[],
                        help="fly only these pairs (comma-separated indices of the --pairs sampled)")
    parser.add_argument("--json", default=None, help="write every flight (and the peer's outcome) to this file")
    parser.add_argument("--no-eval", action="store_true", help="skip the `mapkit eval` peer")
    parser.add_argument("--harness", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.harness:
        return harness(args.world, args.pairs, args.seed, args.domain, args.only)
    worlds = WORLDS if args.world == "all" else (args.world,)
    flights: list[dict] = []
    for world in worlds:
        print(f"mapkit fly, software in the loop: {args.pairs} pairs of {world} seed {args.seed}, loopback DDS")
        rows, node = fly_pairs(args, world)
        flights += rows
        timing(node)
    success = 100.0 * float(np.mean([f["outcome"] == "success" for f in flights])) if flights else 0.0
    print(f"success over DDS: {success:.1f} % of {len(flights)}")
    if not args.no_eval:
        outcomes = eval_peer(args, worlds)
        compare(flights, outcomes, worlds)
        flights = [{**f, "eval": outcomes[(f["world"], f["pair"])]} for f in flights]
    if args.json:
        with open(args.json, "w") as out:
            json.dump({"seed": args.seed, "pairs": args.pairs, "flights": flights}, out, indent=1)


if __name__ == "__main__":
    main()
