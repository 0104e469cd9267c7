"""A tiny closed-loop evaluation: the shipped planner and the straight line fly two pairs in a forest.

    python examples/04_evaluate.py [OUT_DIR]

Each method flies the same start–goal pairs in a simulated world made from the seed (one the model
never saw in training): depth is rendered from the vehicle's pose, the method plans, the vehicle
flies the plan, and so on until the goal, a collision or the time limit. The same as
`mapkit eval --model pretrained --world forest --pairs 2 --seed 0 --methods learned,straight`;
the README's figures use 60 pairs per world. OUT_DIR (refused if it exists) gets results.json,
report.md, trajectories.npz and PNGs; without it a temporary folder. About 30 s on 2 cores.
"""

import json
import sys
import tempfile
from pathlib import Path

from mapkit.evaluation import EpisodeRecord, EvalConfig, evaluate, load_paths

CONFIG = EvalConfig(worlds=("forest",), pairs=2, seed=0, methods=("learned", "straight"))


def run(out_dir: Path) -> None:
    """Evaluate the shipped planner into `out_dir` and print each flight and the success rates."""
    result = evaluate("pretrained", out_dir, CONFIG, progress=False)
    episodes = json.loads((out_dir / "results.json").read_text())["episodes"]
    paths = load_paths(out_dir)  # "world/pair/method" → (N, 4) rows [t, x, y, z]
    for row in episodes:
        episode = EpisodeRecord.from_dict(row)
        flown = paths[f"{episode.world}/{episode.pair:03d}/{episode.method}"]
        print(f"{episode.world} pair {episode.pair} {episode.method:>8}: {episode.outcome:<9} "
              f"after {episode.time_s:5.1f} s, {episode.distance:.1f} m apart, {len(flown)} path samples")
    for method in CONFIG.methods:
        rate = result.summary["success"][method]["overall"]["success_rate"]
        print(f"{method}: {rate:.0%} success")
    print(f"report: {out_dir / 'report.md'}")


def main(argv: list[str]) -> None:
    if argv:
        run(Path(argv[0]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        run(Path(tmp) / "eval")


if __name__ == "__main__":
    main(sys.argv[1:])
