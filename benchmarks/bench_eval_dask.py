"""`mapkit eval` on Dask against its process pool (issue 15): wall time of the same evaluation with
``--workers 1`` (in process), ``--workers 2`` (the peer: a spawn ProcessPoolExecutor) and
``--scheduler local --workers 2`` (a 2-worker Dask LocalCluster, started and stopped inside the
measured time, as the command does). Every run's results.json must be byte-identical; the figure is
the Dask path's wall time over the pool's.

    python benchmarks/bench_eval_dask.py [--pairs 4] [--world office,garage]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from mapkit.evaluation import EvalConfig


def timed(out: Path, config: EvalConfig) -> float:
    """Seconds of one evaluation of the shipped model into ``out``."""
    from mapkit.evaluation import evaluate

    t = time.perf_counter()
    evaluate("pretrained", out, config, progress=False)
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=4, help="pairs per world")
    parser.add_argument("--world", default="office,garage", help="comma list of worlds")
    args = parser.parse_args()
    worlds = tuple(args.world.split(","))
    runs = {"--workers 1 (in process)": EvalConfig(worlds=worlds, pairs=args.pairs, seed=5, workers=1),
            "--workers 2 (process pool, the peer)": EvalConfig(worlds=worlds, pairs=args.pairs, seed=5, workers=2),
            "--scheduler local --workers 2 (Dask)": EvalConfig(worlds=worlds, pairs=args.pairs, seed=5, workers=2,
                                                               scheduler="local")}
    with tempfile.TemporaryDirectory() as tmp:
        seconds = {name: timed(Path(tmp) / str(i), config) for i, (name, config) in enumerate(runs.items())}
        docs = {(Path(tmp) / str(i) / "results.json").read_bytes() for i in range(len(runs))}
    n = len(worlds) * args.pairs
    print(f"eval of the shipped model, every method, {n} pairs ({', '.join(worlds)}, seed 5):")
    for name, s in seconds.items():
        print(f"  {name:<40} {s:7.1f} s  {n / s:5.2f} pairs/s")
    pool, dask = seconds["--workers 2 (process pool, the peer)"], seconds["--scheduler local --workers 2 (Dask)"]
    print(f"  Dask / process pool wall time: {dask / pool:.2f}x; "
          f"results.json {'identical' if len(docs) == 1 else 'DIFFERENT'} in all three")


if __name__ == "__main__":
    main()
