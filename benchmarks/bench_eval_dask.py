"""`mapkit eval` on Dask against its process pool (issue 15): wall time of the same evaluation with
``--workers 1`` (in process), ``--workers 2`` (the peer: a spawn ProcessPoolExecutor) and
``--scheduler local --workers 2`` (a 2-worker Dask LocalCluster, started and stopped inside the
measured time, as the command does). Every run's results.json must be byte-identical; the figure is
the Dask path's wall time over the pool's. CPU seconds (this process and its reaped child processes:
the pool's processes, the LocalCluster's workers) are printed beside, since wall time on a shared
machine moves with the load.

    python benchmarks/bench_eval_dask.py [--pairs 4] [--world office,garage] [--methods learned,straight]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

from mapkit.evaluation import EvalConfig


def cpu_seconds() -> float:
    """User + system CPU of this process and of its child processes that have ended."""
    me, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + children.ru_utime + children.ru_stime


def timed(out: Path, config: EvalConfig) -> tuple[float, float]:
    """Wall and CPU seconds of one evaluation of the shipped model into ``out``."""
    from mapkit.evaluation import evaluate

    t, c = time.perf_counter(), cpu_seconds()
    evaluate("pretrained", out, config, progress=False)
    return time.perf_counter() - t, cpu_seconds() - c


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=4, help="pairs per world")
    parser.add_argument("--world", default="office,garage", help="comma list of worlds")
    parser.add_argument("--methods", default=",".join(EvalConfig().methods), help="comma list of methods (default: every one)")
    args = parser.parse_args()
    common = dict(worlds=tuple(args.world.split(",")), pairs=args.pairs, seed=5, methods=tuple(args.methods.split(",")))
    runs = {"--workers 1 (in process)": EvalConfig(**common, workers=1),
            "--workers 2 (process pool, the peer)": EvalConfig(**common, workers=2),
            "--scheduler local --workers 2 (Dask)": EvalConfig(**common, workers=2, scheduler="local")}
    worlds = common["worlds"]
    with tempfile.TemporaryDirectory() as tmp:
        seconds = {name: timed(Path(tmp) / str(i), config) for i, (name, config) in enumerate(runs.items())}
        docs = {(Path(tmp) / str(i) / "results.json").read_bytes() for i in range(len(runs))}
    n = len(worlds) * args.pairs
    named = "every method" if args.methods == parser.get_default("methods") else f"methods {args.methods}"
    print(f"eval of the shipped model, {named}, {n} pairs ({', '.join(worlds)}, seed 5):")
    for name, (wall, cpu) in seconds.items():
        print(f"  {name:<40} {wall:7.1f} s wall  {n / wall:5.2f} pairs/s  {cpu:7.1f} s CPU")
    pool, dask = seconds["--workers 2 (process pool, the peer)"], seconds["--scheduler local --workers 2 (Dask)"]
    print(f"  Dask / process pool: wall {dask[0] / pool[0]:.2f}x, CPU {dask[1] / pool[1]:.2f}x; "
          f"results.json {'identical' if len(docs) == 1 else 'DIFFERENT'} in all three")


if __name__ == "__main__":
    main()
