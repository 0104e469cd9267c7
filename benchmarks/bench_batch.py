"""Batch throughput: `mapkit batch` on 1 and 2 Dask workers against the single commands in sequence.

Simulates the same flights once (forest worlds, 160x120 depth at 30 Hz), then measures in one run:
  sequence   ingest → fuse → esdf → export per flight, the library calls of the single commands, one
             after another in one fresh process with its default threads (what a shell loop does,
             minus the interpreter start and imports per command): the named peer
  batch 1    run_batch with a local cluster of 1 worker (cluster start and stop included)
  batch 2    the same with 2 workers
  rerun      batch 1 again: every step is up to date, so this is the fixed cost (cluster, workers)
The three runs are repeated in --repeat interleaved rounds (default 3) and their medians reported:
on a shared machine one round moves by ±10 %. With --growth, batch 2 also runs on the first 2 and 4
flights (how wall time grows with flights).
Goals (issue 15): batch 2 ≥ 1.7× batch 1 on 2 cores; batch 1 within 10 % of the sequence.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Literal

from mapkit.esdf import EsdfConfig
from mapkit.export import ExportConfig
from mapkit.fusion import FuseConfig

FUSE = FuseConfig(voxel=0.1)
ESDF = EsdfConfig(voxel=0.2)
EXPORT = ExportConfig()


def cpu_seconds() -> float:
    """CPU time of this process and its reaped children (the peer's process; a local cluster's worker
    processes, once stopped)."""
    me, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + children.ru_utime + children.ru_stime


def make_flights(folder: Path, n: int, duration: float) -> list[Path]:
    from mapkit.sim import SimConfig, simulate

    folder.mkdir(parents=True, exist_ok=True)
    return [simulate(SimConfig(world="forest", seed=100 + i, duration=duration, width=160, height=120),
                     folder / f"flight{i}", progress=False).bag_path for i in range(n)]


def sequence(flights: list[Path], root: Path) -> None:
    """The peer's work: the single commands' library calls, flight after flight."""
    from mapkit.esdf import build_esdf
    from mapkit.export import export_tuples
    from mapkit.fusion import fuse
    from mapkit.ingest import ingest

    for flight in flights:
        ws = root / flight.stem
        ingest([flight], ws, progress=False)
        fuse([], ws, FUSE, progress=False)
        build_esdf(ws, ESDF, progress=False)
        export_tuples(ws, EXPORT, progress=False)


def run_sequence(flights: list[Path], root: Path) -> float:
    """The peer in a fresh interpreter, as the batch's workers are: both pay their imports."""
    t = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--sequence", str(root), *map(str, flights)], check=True)
    return time.perf_counter() - t


def run_batch_timed(flights: list[Path], root: Path, workers: int, *, expect: Literal["done", "skipped"] = "done") -> float:
    from mapkit.batch import BatchConfig, resolve_recordings, run_batch

    config = BatchConfig(recordings=resolve_recordings(flights), root=root, workers=workers, fuse=FUSE, esdf=ESDF,
                         export=EXPORT)
    t = time.perf_counter()
    summary = run_batch(config, progress=False)
    seconds = time.perf_counter() - t
    if len(summary.having(expect)) != len(flights):
        raise SystemExit("bench_batch: " + "; ".join(summary.lines()))
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--flights", type=int, default=6)
    parser.add_argument("--duration", type=float, default=8.0, help="Seconds per simulated flight.")
    parser.add_argument("--repeat", type=int, default=3, help="Rounds of the three runs; medians are reported.")
    parser.add_argument("--growth", action=argparse.BooleanOptionalAction, default=True,
                        help="Also time batch 2 on 2 and 4 flights.")
    parser.add_argument("--sequence", nargs="+", type=Path, metavar=("ROOT", "FLIGHT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sequence:  # the peer's own process (see run_sequence)
        sequence(args.sequence[1:], args.sequence[0])
        return
    with tempfile.TemporaryDirectory() as tmp:
        flights = make_flights(Path(tmp) / "flights", args.flights, args.duration)
        walls: dict[str, list[float]] = {}
        cpus: dict[str, list[float]] = {}
        load0 = os.getloadavg()[0]
        for _ in range(args.repeat):  # rounds interleave the runs, so a busy spell hits all of them alike
            for label, run in (("sequence", lambda r: run_sequence(flights, r)),
                               ("batch 1", lambda r: run_batch_timed(flights, r, 1)),
                               ("batch 2", lambda r: run_batch_timed(flights, r, 2))):
                root = Path(tmp) / label.replace(" ", "")
                c0 = cpu_seconds()
                walls.setdefault(label, []).append(run(root))
                cpus.setdefault(label, []).append(cpu_seconds() - c0)
                if label == "batch 1":  # a rerun skips every step: the fixed cost of a batch (cluster, workers)
                    walls.setdefault("rerun", []).append(run_batch_timed(flights, root, 1, expect="skipped"))
                shutil.rmtree(root)
        times = {label: statistics.median(v) for label, v in walls.items()}
        cpu = {label: statistics.median(v) for label, v in cpus.items()}
        growth = {}
        if args.growth:
            for n in (2, 4):
                if n < args.flights:
                    growth[n] = run_batch_timed(flights[:n], Path(tmp) / f"growth{n}", 2)
        growth[args.flights] = times["batch 2"]
    load = os.getloadavg()[0]
    print(f"input: {args.flights} simulated flights, {args.duration:.0f} s each at 30 Hz, 160x120 depth; fuse voxel "
          f"{FUSE.voxel} m, esdf voxel {ESDF.voxel} m; {os.cpu_count()} cores, load average {load0:.1f} at the start, "
          f"{load:.1f} at the end (other processes share the cores above a load of 2); median of {args.repeat} "
          "interleaved round(s)")
    seq = times["sequence"]
    print(f"{'run':<42}{'wall s':>8}{'flights/min':>13}{'vs sequence':>13}{'CPU s':>8}  goal")
    print(f"{'sequence (single commands, one process)':<42}{seq:>8.1f}{60 * args.flights / seq:>13.2f}{1.0:>13.2f}"
          f"{cpu['sequence']:>8.1f}")
    for label, goal in (("batch 1", "wall <= 1.10 x sequence"), ("batch 2", "")):
        t = times[label]
        print(f"{label + ' worker(s)':<42}{t:>8.1f}{60 * args.flights / t:>13.2f}{t / seq:>13.2f}{cpu[label]:>8.1f}  {goal}")
    print(f"{'batch 1 worker, rerun (every step skipped)':<42}{times['rerun']:>8.1f}")
    if args.repeat > 1:
        print("rounds, wall s: " + "; ".join(f"{label} " + " / ".join(f"{t:.1f}" for t in walls[label])
                                            for label in ("sequence", "batch 1", "batch 2")))
    print(f"speed-up batch 2 vs batch 1: {times['batch 1'] / times['batch 2']:.2f}x (goal >= 1.7x on 2 cores); "
          f"overhead batch 1 vs sequence: {100 * (times['batch 1'] / seq - 1):+.1f} % (goal <= +10 %)")
    if len(growth) > 1:
        print("growth, batch 2 workers: " + ", ".join(f"{n} flights {t:.1f} s" for n, t in sorted(growth.items())))


if __name__ == "__main__":
    main()
