"""Plan from a recorded frame with the planner shipped with mapkit (`--model pretrained`).

    python examples/03_plan_with_a_model.py [WORKSPACE]

WORKSPACE holds a frames.zarr (`mapkit ingest`, or examples/01_ingest_and_map.py). Without it the
example ingests ten frames of sample_data/forest.mcap into a temporary folder. Plans toward a goal
5 m ahead and 1 m to the left of the body, from the frame's depth image, pose and velocity, as
`mapkit plan` does, and writes the trajectory as JSON, TUM and MCAP into WORKSPACE/plans.
A few seconds on 2 cores.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from mapkit.export import body_velocities
from mapkit.flight import Planner, write_plan_outputs
from mapkit.geometry import invert_transform
from mapkit.ingest import IngestConfig, ingest, open_frames_store

RECORDING = Path(__file__).resolve().parents[1] / "sample_data" / "forest.mcap"
GOAL_BODY = np.array([5.0, 1.0, 0.0])  # metres, body frame: x forward, y left, z up


def plan(workspace: Path) -> None:
    """Plan from the middle frame of `workspace`'s frames.zarr and write the outputs beside it."""
    store = open_frames_store(workspace)
    i = len(store) // 2
    T_world_body = store.T_world_body[i]
    T_body_camera = invert_transform(T_world_body) @ store.T_world_camera[i]
    velocity = body_velocities(store.stamp_ns, store.T_world_body, store.source_index)[i]

    planner = Planner.load("pretrained")
    # K and T_body_camera let the model check its candidate paths against the depth image.
    result = planner.plan(np.asarray(store.depth[i]), GOAL_BODY, velocity_body=velocity, K=store.K,
                          T_body_camera=T_body_camera)

    verdict = "execute" if result.execute else "do not execute (eta >= 0.5)"
    print(f"frame {i}: eta {result.eta:.3f} → {verdict}")
    print(f"  key-points (body, m):\n{np.round(result.keypoints, 2)}")
    print(f"  segment times {np.round(result.durations, 2)} s, control effort {result.control_effort:.1f} m²/s⁷, "
          f"latency {result.latency_ms:.1f} ms (the first plan includes warm-up)")
    end_world = T_world_body[:3, :3] @ result.samples_body[-1] + T_world_body[:3, 3]
    print(f"  the trajectory ends at {end_world.round(2)} m in the world frame")
    paths = write_plan_outputs(result, T_world_body, int(store.stamp_ns[i]), workspace / "plans", stem=f"plan_{i:06d}")
    print("wrote " + ", ".join(p.name for p in paths))


def main(argv: list[str]) -> None:
    if argv:
        plan(Path(argv[0]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        ingest([RECORDING], tmp, IngestConfig(stride=30), progress=False)
        plan(Path(tmp))


if __name__ == "__main__":
    main(sys.argv[1:])
