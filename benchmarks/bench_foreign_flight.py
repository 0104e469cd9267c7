"""An independent closed-loop referee of `mapkit.flight.Pilot`: worlds mapkit did not make, flown by a
vehicle and a controller mapkit did not write, through the pilot's public API only.

What it measures, per flight stack (``Pilot.load("pretrained", stack=...)``): success (the vehicle
within 0.5 m of the goal), collisions (exact distance from the vehicle's position to a mesh < 0.3 m),
timeouts (max(20 s, 4 × distance / 1.2 m/s)), the reference's peak acceleration (max |a| per axis over
a flight; median and max over flights), the tracking error |vehicle − reference position| (per flight
mean and max; medians over flights), the climb (max z − start z; median over flights) and the pilot's
latency (``PilotStep.latency_ms`` of the calls that replanned; median and p95), plus the statuses seen.

How:
- Worlds: one per (seed, pair), built with Open3D from meshes: a floor, no ceiling, 10–16 obstacles in
  a 20 × 14 m area (wall-like long thin boxes, boxes, cylinders; all 2.3–4 m tall, so they cover the
  1–2 m flight band), each rotated about z at random.
- Pairs: start and goal at one height in 1.0–2.0 m, 8–14 m apart, each ≥ 0.6 m from every mesh, whose
  straight line passes within 0.3 m of a mesh (blocked), and connected on a 0.2 m 2-D grid at that
  height through cells ≥ 0.4 m from every mesh (reachable); rejected candidates are counted by reason.
- Depth: Open3D's ray caster from ``T_world_body @ pilot.camera.T_body_camera`` with the model's
  recorded camera (K, size), the ray distance turned into depth along the optical axis, NaN past 10 m
  or where no mesh is hit. 30 camera frames per second, one ``pilot.step`` each.
- Vehicle: rotorpy's ``Multirotor`` (hummingbird parameters) under rotorpy's plain ``SE3Control`` (no
  drag feed-forward) at 100 Hz, fed ``reference.sample(t)`` (position … snap, yaw, yaw rate) each
  control step; the pilot gets the true attitude (rotorpy's q is xyzw, body → world).

Only public names are used: ``mapkit.flight`` (Pilot, VehicleState, FlightError, SpeedProfile) and
``mapkit.geometry.transform_from_pose``; nothing from ``mapkit.evaluation`` or any ``_`` module.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_foreign_flight.py --seeds 0,1 --pairs 10

Progress (one line per flight) goes to stderr; the table and the targets to stdout.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from collections import Counter
from dataclasses import dataclass, field

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy and torch size their thread pools

import numpy as np

AREA = np.array([[0.0, -7.0], [20.0, 7.0]])  # x, y bounds of the obstacle field, metres
ROBOT_RADIUS, START_CLEARANCE, GRID_CLEARANCE, GRID_STEP = 0.3, 0.6, 0.4, 0.2
GOAL_RADIUS, DEPTH_RANGE, CRUISE = 0.5, 10.0, 1.2
CONTROL_HZ, CAMERA_HZ = 100, 30
TARGETS = {"full": 95.0, "none": 75.0}  # success %, the targets
CLIMB_TARGET = 0.5


# --- worlds --------------------------------------------------------------------------------------------

def obstacle(rng: np.random.Generator, o3d):
    """One mesh standing on the floor inside AREA: a wall, a box or a cylinder, turned about z."""
    x, y = rng.uniform(AREA[0, 0], AREA[1, 0]), rng.uniform(AREA[0, 1], AREA[1, 1])
    h = rng.uniform(2.3, 4.0)  # covers the 1–2 m flight band: flying over means a climb of 0.3 m or more
    kind = rng.choice(["wall", "box", "cylinder"], p=[0.3, 0.35, 0.35])
    if kind == "cylinder":
        r = rng.uniform(0.15, 0.6)
        return o3d.geometry.TriangleMesh.create_cylinder(r, h, resolution=24).translate((x, y, h / 2))
    w, d = (rng.uniform(3.0, 6.0), rng.uniform(0.15, 0.4)) if kind == "wall" else rng.uniform(0.5, 2.0, 2)
    m = o3d.geometry.TriangleMesh.create_box(w, d, h).translate((x - w / 2, y - d / 2, 0.0))
    R = o3d.geometry.get_rotation_matrix_from_xyz((0.0, 0.0, rng.uniform(0.0, np.pi)))
    return m.rotate(R, center=(x, y, h / 2))


def build_world(rng: np.random.Generator):
    """An Open3D raycasting scene: a 60 × 60 m floor (top at z = 0) and 10–16 obstacles, no ceiling."""
    import open3d as o3d

    meshes = [o3d.geometry.TriangleMesh.create_box(60.0, 60.0, 0.1).translate((-20.0, -30.0, -0.1))]
    meshes += [obstacle(rng, o3d) for _ in range(int(rng.integers(10, 17)))]
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    return scene


def distance(scene, points: np.ndarray) -> np.ndarray:
    """Exact unsigned distance (metres) from each point (N, 3) to the nearest mesh."""
    import open3d as o3d

    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))).numpy()


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit ray directions (H·W, 3) in the optical camera frame, row-major like the image."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def render_depth(scene, T_world_camera: np.ndarray, rays: np.ndarray, width: int, height: int) -> np.ndarray:
    """float32 (H, W) depth along the optical axis, metres; NaN where nothing is hit within DEPTH_RANGE."""
    import open3d as o3d

    d_world = rays @ T_world_camera[:3, :3].T
    origin = np.broadcast_to(T_world_camera[:3, 3], d_world.shape)
    t_hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, d_world], 1).astype(np.float32)))["t_hit"]
    depth = (t_hit.numpy() * rays[:, 2]).reshape(height, width).astype(np.float32)  # ray length → optical z
    depth[~np.isfinite(depth) | (depth > DEPTH_RANGE)] = np.nan
    return depth


# --- start / goal pairs --------------------------------------------------------------------------------

def reachable(scene, start: np.ndarray, goal: np.ndarray) -> bool:
    """Start and goal connected through grid cells at their height keeping GRID_CLEARANCE from every mesh
    (4-connected; the grid reaches 4 m past AREA so detours around the whole field count)."""
    from scipy import ndimage

    lo, hi = AREA[0] - 4.0, AREA[1] + 4.0
    xs, ys = np.arange(lo[0], hi[0] + 1e-9, GRID_STEP), np.arange(lo[1], hi[1] + 1e-9, GRID_STEP)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, start[2])], 1)
    labels, _ = ndimage.label(distance(scene, pts).reshape(X.shape) >= GRID_CLEARANCE)

    def cell(p):
        return labels[int(round((p[0] - lo[0]) / GRID_STEP)), int(round((p[1] - lo[1]) / GRID_STEP))]

    return bool(cell(start) != 0 and cell(start) == cell(goal))


def sample_pair(rng: np.random.Generator, scene, rejected: Counter) -> tuple[np.ndarray, np.ndarray] | None:
    """A level start/goal pair 8–14 m apart whose straight line is blocked and whose goal is reachable."""
    for _ in range(400):
        z = rng.uniform(1.0, 2.0)
        start = np.array([*rng.uniform(AREA[0], AREA[1]), z])
        heading, length = rng.uniform(-np.pi, np.pi), rng.uniform(8.0, 14.0)
        goal = start + length * np.array([np.cos(heading), np.sin(heading), 0.0])
        if np.any(goal[:2] < AREA[0]) or np.any(goal[:2] > AREA[1]):
            rejected["goal outside the area"] += 1
            continue
        if distance(scene, np.stack([start, goal])).min() < START_CLEARANCE:
            rejected["start/goal clearance < 0.6 m"] += 1
            continue
        line = start + np.linspace(0.0, 1.0, int(length / 0.05) + 1)[:, None] * (goal - start)
        if distance(scene, line).min() >= ROBOT_RADIUS:
            rejected["straight line free"] += 1
            continue
        if not reachable(scene, start, goal):
            rejected["blocked and unreachable"] += 1
            continue
        return start, goal
    return None


@dataclass
class Case:
    seed: int
    pair: int
    scene: object
    start: np.ndarray
    goal: np.ndarray


def make_cases(seeds: list[int], pairs: int) -> tuple[list[Case], Counter]:
    """One world per (seed, pair), reproducible from both; a world with no valid pair is redrawn."""
    cases, rejected = [], Counter()
    for seed in seeds:
        for i in range(pairs):
            rng = np.random.default_rng([seed, i])
            found = None
            while found is None:
                scene = build_world(rng)
                found = sample_pair(rng, scene, rejected)
            cases.append(Case(seed, i, scene, *found))
    return cases, rejected


# --- one flight ----------------------------------------------------------------------------------------

@dataclass
class Flight:
    """What the referee saw in one flight."""

    case: Case
    stack: str
    outcome: str = "timeout"
    t_end: float = 0.0
    wall_s: float = 0.0
    acc_peak: np.ndarray = field(default_factory=lambda: np.zeros(3))  # max |reference acceleration| per axis
    err_sum: float = 0.0
    err_max: float = 0.0
    samples: int = 0
    z_max: float = -np.inf
    yaw_err_max: float = 0.0  # |vehicle yaw − reference yaw|, radians
    peak_at: str = ""  # when the reference's largest |a| came, and the status then
    over_s: float = 0.0  # seconds the reference's |a| exceeded the per-axis limit
    status: str = "blocked"  # the pilot's last status
    latencies: list[float] = field(default_factory=list)  # ms, calls that replanned
    statuses: Counter = field(default_factory=Counter)  # pilot calls per status
    reasons: Counter = field(default_factory=Counter)  # braking / blocked reasons, digits masked
    detail: str = ""

    def note(self, step) -> None:
        """One pilot call."""
        self.statuses[step.status] += 1
        self.status = step.status
        if step.replanned:
            self.latencies.append(step.latency_ms)
        if step.status in ("braking", "blocked"):
            self.reasons[f"{step.status}: {re.sub(r'[0-9.]+', '#', step.reason)[:90]}"] += 1

    def track(self, t: float, x: np.ndarray, yaw: float, sp, a_max: float) -> None:
        """One control step: the vehicle against the setpoint it is sent."""
        err = float(np.linalg.norm(x - sp.position))
        self.err_sum, self.err_max, self.samples = self.err_sum + err, max(self.err_max, err), self.samples + 1
        a = np.abs(sp.acceleration)
        if a.max() > self.acc_peak.max():
            self.peak_at = f"t {t:.2f} s, {self.status}, speed {np.linalg.norm(sp.velocity):.2f} m/s"
        self.over_s += float(a.max() > a_max + 1e-6) / CONTROL_HZ
        self.acc_peak = np.maximum(self.acc_peak, np.abs(sp.acceleration))
        self.z_max = max(self.z_max, float(x[2]))
        self.yaw_err_max = max(self.yaw_err_max, abs(float(np.angle(np.exp(1j * (yaw - sp.yaw))))))


def make_vehicle(start: np.ndarray, goal: np.ndarray):
    """rotorpy's hummingbird hovering at ``start``, facing the goal, and its plain SE(3) controller."""
    from rotorpy.controllers.quadrotor_control import SE3Control
    from rotorpy.vehicles.hummingbird_params import quad_params
    from rotorpy.vehicles.multirotor import Multirotor

    yaw = float(np.arctan2(goal[1] - start[1], goal[0] - start[0]))
    hover = np.full(4, np.sqrt(quad_params["mass"] * 9.81 / (4 * quad_params["k_eta"])))
    state = {"x": start.copy(), "v": np.zeros(3), "q": np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]),
             "w": np.zeros(3), "wind": np.zeros(3), "rotor_speeds": hover}
    return Multirotor(quad_params, initial_state=state), SE3Control(quad_params), state


def camera_call(pilot, case: Case, state: dict, t: float, rays: np.ndarray):
    """One camera frame: render at the body's true attitude and ask the pilot."""
    from mapkit.flight import VehicleState
    from mapkit.geometry import transform_from_pose

    cam = pilot.camera
    T_world_body = transform_from_pose(state["x"], state["q"])  # rotorpy's q: xyzw, body → world
    depth = render_depth(case.scene, T_world_body @ cam.T_body_camera, rays, cam.width, cam.height)
    now = VehicleState(position=state["x"], velocity=state["v"], yaw=yaw_of(state["q"]))
    return pilot.step(t, now, case.goal, depth, K=cam.K, T_world_body=T_world_body)


def yaw_of(q_xyzw: np.ndarray) -> float:
    """Heading of the body's x axis in the world (radians) from a body → world quaternion, xyzw."""
    x, y, z, w = q_xyzw
    return float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def verdict(case: Case, x: np.ndarray) -> str | None:
    """The referee's call on the vehicle's position: None while the flight goes on."""
    if not np.all(np.isfinite(x)):
        return "diverged"
    if distance(case.scene, x)[0] < ROBOT_RADIUS:
        return "collision"
    if np.linalg.norm(x - case.goal) < GOAL_RADIUS:
        return "success"
    return None


def fly(pilot, case: Case, stack: str, rays: np.ndarray) -> Flight:
    """One closed-loop flight from the case's start to its goal."""
    from mapkit.flight import FlightError, SpeedProfile

    a_max = SpeedProfile().a_max or float("inf")  # the configured per-axis limit the reference should keep
    wall0, rec = time.perf_counter(), Flight(case, stack)
    pilot.reset()
    vehicle, controller, state = make_vehicle(case.start, case.goal)
    limit = max(20.0, 4.0 * float(np.linalg.norm(case.goal - case.start)) / CRUISE)
    reference, frame = None, -1
    for k in range(int(limit * CONTROL_HZ) + 1):
        t = k / CONTROL_HZ
        rec.t_end = t
        outcome = verdict(case, state["x"])
        if outcome is not None:
            rec.outcome = outcome
            break
        if k * CAMERA_HZ // CONTROL_HZ > frame:  # the next 30 Hz camera frame falls in this control step
            frame = k * CAMERA_HZ // CONTROL_HZ
            try:
                step = camera_call(pilot, case, state, t, rays)
            except FlightError as e:  # a referee records the pilot's refusal and ends the flight
                rec.outcome, rec.detail = "error", str(e)
                break
            rec.note(step)
            reference = step.reference
        sp = reference.sample(t)
        rec.track(t, state["x"], yaw_of(state["q"]), sp, a_max)
        flat = {"x": sp.position, "x_dot": sp.velocity, "x_ddot": sp.acceleration, "x_dddot": sp.jerk,
                "x_ddddot": sp.snap, "yaw": sp.yaw, "yaw_dot": sp.yaw_rate}
        state = vehicle.step(state, controller.update(t, state, flat), 1.0 / CONTROL_HZ)
    rec.wall_s = time.perf_counter() - wall0
    return rec


# --- report --------------------------------------------------------------------------------------------

HEADER = (f"{'stack':6} {'flights':>7} {'success':>8} {'coll':>4} {'tout':>4} {'err':>3} | "
          f"{'peak |a| ref med/max':>20} | {'track mean/max (med)':>20} | {'climb med/max':>13} | "
          f"{'latency med/p95':>15} | {'t goal med':>10}")


def row(stack: str, flights: list[Flight]) -> str:
    """One table row: the stack's figures over its flights."""
    n = len(flights)
    count = Counter(f.outcome for f in flights)
    peak = np.array([f.acc_peak.max() for f in flights])
    mean_err = np.array([f.err_sum / max(f.samples, 1) for f in flights])
    max_err = np.array([f.err_max for f in flights])
    climb = np.array([f.z_max - f.case.start[2] for f in flights])
    lat = np.concatenate([f.latencies for f in flights]) if any(f.latencies for f in flights) else np.zeros(1)
    t_goal = [f.t_end for f in flights if f.outcome == "success"]
    return (f"{stack:6} {n:7d} {100 * count['success'] / n:7.1f}% {count['collision']:4d} {count['timeout']:4d} "
            f"{count['error'] + count['diverged']:3d} | {np.median(peak):8.2f} / {peak.max():5.2f} m/s² | "
            f"{100 * np.median(mean_err):7.1f} / {100 * np.median(max_err):5.1f} cm | "
            f"{np.median(climb):5.2f} / {climb.max():4.2f} m | {np.median(lat):6.1f} / {np.percentile(lat, 95):5.1f} ms"
            f" | {np.median(t_goal) if t_goal else float('nan'):8.1f} s")


def details(stack: str, flights: list[Flight]) -> list[str]:
    """What the pilot did: statuses, braking and blocked episodes, yaw, and each failure."""
    calls = sum((f.statuses for f in flights), Counter())
    total = max(sum(calls.values()), 1)
    share = ", ".join(f"{s} {100 * c / total:.1f}%" for s, c in calls.most_common())
    braked = sum(f.statuses["braking"] > 0 for f in flights)
    blocked = sum(f.statuses["blocked"] > 0 for f in flights)
    per_axis = np.max([f.acc_peak for f in flights], axis=0)
    yaw = np.degrees(np.median([f.yaw_err_max for f in flights]))
    lines = [f"  {stack}: pilot calls by status: {share}; flights with braking {braked}, with blocked {blocked};",
             f"  {stack}: peak |a| of the reference per axis over all flights (x, y, z) "
             f"{np.round(per_axis, 2).tolist()} m/s²; max |yaw − reference yaw| per flight, median {yaw:.1f}°"]
    over = [f for f in flights if f.over_s > 0]
    lines.append(f"  {stack}: flights whose reference exceeds the per-axis |a| limit: {len(over)}/{len(flights)}"
                 + "".join(f"\n  {stack}:   seed {f.case.seed} pair {f.case.pair}: peak {f.acc_peak.max():.2f} m/s² "
                           f"at {f.peak_at}; {f.over_s:.2f} s over the limit" for f in over))
    reasons = sum((f.reasons for f in flights), Counter())
    lines += [f"  {stack}:   {c:5d} calls  {r}" for r, c in reasons.most_common(5)]
    lines += [f"  {stack}: seed {f.case.seed} pair {f.case.pair}: {f.outcome} at {f.t_end:.1f} s, "
              f"{np.linalg.norm(f.case.goal - f.case.start):.1f} m pair, ended "
              f"{f.detail or 'calls by status ' + str(dict(f.statuses))}" for f in flights if f.outcome != "success"]
    return lines


def targets(results: dict[str, list[Flight]]) -> str:
    """The issue's targets against what was measured."""
    from mapkit.flight import SpeedProfile

    a_max = SpeedProfile().a_max or float("inf")
    parts = []
    for stack, flights in results.items():
        ok = 100 * sum(f.outcome == "success" for f in flights) / len(flights)
        climb = float(np.median([f.z_max - f.case.start[2] for f in flights]))
        peak = float(max(f.acc_peak.max() for f in flights))
        goal = TARGETS.get(stack)
        parts.append(f"{stack}: success {ok:.0f}%" + ("" if goal is None else f" (≥ {goal:.0f}%: {'PASS' if ok >= goal else 'FAIL'})")
                     + f", median climb {climb:.2f} m (≤ {CLIMB_TARGET}: {'PASS' if climb <= CLIMB_TARGET else 'FAIL'})"
                     + f", peak reference |a| {peak:.2f} m/s² (≤ {a_max:g} per axis: {'PASS' if peak <= a_max + 1e-6 else 'FAIL'})")
    return "targets (full ≥ 95 %, none ≥ 75 %, median climb ≤ 0.5 m, reference |a| ≤ configured per-axis limit): " \
        + "; ".join(parts)


# --- main ----------------------------------------------------------------------------------------------

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0,1", help="comma-separated world seeds")
    parser.add_argument("--pairs", type=int, default=10, help="start/goal pairs (one world each) per seed")
    parser.add_argument("--stacks", default="full,none", help="comma-separated flight stacks")
    parser.add_argument("--model", default="pretrained", help="'pretrained' or a run directory")
    args = parser.parse_args()
    import torch

    from mapkit.flight import Pilot

    torch.set_num_threads(1)  # two shared cores: one process, one thread
    wall0 = time.perf_counter()
    cases, rejected = make_cases([int(s) for s in args.seeds.split(",")], args.pairs)
    print(f"{len(cases)} pairs in {len(cases)} worlds ({time.perf_counter() - wall0:.1f} s); candidates rejected: "
          + ", ".join(f"{r} {c}" for r, c in rejected.most_common()), flush=True)
    results: dict[str, list[Flight]] = {}
    for stack in args.stacks.split(","):
        pilot, t0 = Pilot.load(args.model, stack=stack), time.perf_counter()
        rays = pixel_rays(pilot.camera.K, pilot.camera.width, pilot.camera.height)
        results[stack] = []
        for case in cases:
            f = fly(pilot, case, stack, rays)
            results[stack].append(f)
            print(f"seed {case.seed} pair {case.pair} {stack}: {f.outcome} at {f.t_end:.1f} s "
                  f"(wall {f.wall_s:.1f} s)", file=sys.stderr, flush=True)
        print(f"{stack}: {time.perf_counter() - t0:.0f} s wall", file=sys.stderr, flush=True)
    print(HEADER)
    for stack, flights in results.items():
        print(row(stack, flights))
    for stack, flights in results.items():
        print("\n".join(details(stack, flights)))
    print(f"wall time {time.perf_counter() - wall0:.0f} s")
    print(targets(results))


if __name__ == "__main__":
    main()
