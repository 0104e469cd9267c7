"""Every benchmarks/bench_*.py runs to its end at tiny sizes and prints its figures, so that `make bench`
cannot break unnoticed (it once stopped at bench_train.py on a changed config type).

The scripts are found by glob: a new benchmark without an entry in SMOKE fails here until it gets one.
The figures themselves mean nothing at these sizes; only that each script starts, finishes and prints
its table is checked."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
SAMPLE = ROOT / "sample_data" / "forest.mcap"
PEERS = ROOT / ".venv-peers" / "bin" / "python"


@dataclass(frozen=True)
class Smoke:
    args: tuple[str, ...]
    """The tiny-size options; ``{ws}`` stands for a workspace ingested from the sample forest flight."""
    expect: tuple[str, ...]
    """Regular expressions the output must match: the table header and a figure."""
    slow: bool = True
    """Over 5 s on one core (most are: each pays its imports, worlds and model loads)."""


SMOKE: dict[str, Smoke] = {
    "bench_batch.py": Smoke(("--flights", "1", "--duration", "1", "--repeat", "1", "--no-growth"),
                            (r"wall s\s+flights/min", r"speed-up batch 2 vs batch 1: [\d.]+x")),
    "bench_esdf.py": Smoke(("--grid", "32", "--large-grid", "32", "--chunked-grid", "64,64,32", "--no-growth"),
                           (r"signed EDT\s+Gaussian", r"ratio peer / ours: [\d.]+x", r"2 worker processes \(1 thread/chunk\)\s+[\d.]+s")),
    "bench_eval_dask.py": Smoke(("--pairs", "1", "--world", "office", "--methods", "straight"),
                                (r"\(Dask\)\s+[\d.]+ s wall", r"Dask / process pool: wall [\d.]+x")),
    "bench_exchange.py": Smoke(("--workspace", "{ws}", "--grid", "16"),
                               (r"workspace → foxglove\s+[\d.]+ s", r"workspace → rerun\s+[\d.]+ s",
                                r"16³ VoxelGrid channel\s+[\d.]+ s"), slow=False),
    "bench_fly.py": Smoke(("--pairs", "1", "--world", "office"),
                          (r"while planning\s+[\d.]+ %", r"depth message → the first setpoint flown from its plan: median [\d.]+ ms",
                           r"difference [+-][\d.]+ points")),
    # The other engineer's benchmarks, run with their own options.
    "bench_foreign_flight.py": Smoke(("--seeds", "0", "--pairs", "1", "--stacks", "full"),
                                     (r"stack\s+flights\s+success", r"full\s+1\s+[\d.]+%")),
    "bench_foreign_scene.py": Smoke(("--plans", "2"), (r"\d+/2 plans to hidden goals collision-free",), slow=False),
    "bench_ingest.py": Smoke(("--frames", "5", "--repeat", "1"),
                             (r"stage\s+frames/s\s+vs raw", r"mapkit ingest -> frames.zarr\s+\d+"), slow=False),
    "bench_judge_ceiling.py": Smoke(("--pairs", "1", "--world", "office", "--judge", "network,exact"),
                                    (r"network\s+office\s+[\d.]+ %", r"exact\s+office\s+[\d.]+ %.*overall")),
    "bench_mapping.py": Smoke(("--speed-frames", "5", "--accuracy-frames", "5", "--width", "64", "--worlds", "office"),
                              (r"end to end .*\s[\d.]+ frames/s", r"world\s+voxels\s+mean\|e\|", r"office\s+\d+\s+[\d.]+")),
    "bench_pilot.py": Smoke(("--pairs", "1"), (r"pilot median", r"full\s+\d+\s+[\d.]+ ms")),
    "bench_planner.py": Smoke(("--repeats", "10", "--frames", "2"),
                              (r"network pass \(encoder included\)\s+[\d.]+ ms", r"\+ v/a limits, re-solved\s+[\d.]+ ms"),
                              slow=False),
    "bench_stores.py": Smoke(("--frames", "5", "--repeats", "1"), (r"memory://\s+[\d.]+ s",), slow=False),
    "bench_train.py": Smoke(("--steps", "1", "--paper-steps", "1", "--batch", "2", "--pairs", "1", "--world", "office"),
                            (r"train samples/s", r"paper\s+360x640\s+2\s+1\s+[\d.]+", r"planning latency .* median [\d.]+ ms",
                             r"shipped model, 1 unseen pairs per world .* success learned \d+ %")),
    "bench_trajopt.py": Smoke(("--batch", "4", "--quick"),
                              (r"case\s+mapkit\s+target", r"equality path \(closed form\)\s+[\d.]+ µs",
                               r"daqp\s+\d+\s+\d+\s+0/4"), slow=False),
    "bench_viewer.py": Smoke(("--grid", "32", "--points", "2000", "--no-browser"),
                             (r"viewer update, cold slab .*\s[\d.]+$", r"`mapkit view -w WS` until the URL is printed .*\s[\d.]+")),
}


@contextmanager
def _one_core() -> Iterator[None]:
    """This process, and so the benchmark it starts, on one core (the n-th of its own, by xdist worker),
    restored after: the benchmarks size their threads by the cores they may use, and two of them side by
    side, each with a thread per core, slow each other down many times over."""
    if not hasattr(os, "sched_setaffinity"):  # not Linux: no pinning
        yield
        return
    cores = sorted(os.sched_getaffinity(0))
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    os.sched_setaffinity(0, {cores[index % len(cores)]})
    try:
        yield
    finally:
        os.sched_setaffinity(0, cores)


def _scripts() -> list:
    """Every benchmark, marked slow as its entry says (one without an entry runs, and fails, unmarked)."""
    names = sorted(p.name for p in BENCHMARKS.glob("bench_*.py"))
    return [pytest.param(n, marks=[pytest.mark.slow] if n in SMOKE and SMOKE[n].slow else []) for n in names]


def test_every_smoke_entry_names_a_benchmark() -> None:
    stale = sorted(set(SMOKE) - {p.name for p in BENCHMARKS.glob("bench_*.py")})
    assert not stale, f"SMOKE entries without a script in benchmarks/: {stale}"


@pytest.mark.parametrize("name", _scripts())
def test_benchmark_runs_at_tiny_sizes(name: str, tmp_path: Path) -> None:
    assert name in SMOKE, (f"benchmarks/{name} has no smoke run: add its tiny-size options to SMOKE in "
                           "tests/test_benchmarks.py (give it such options when it has none)")
    smoke = SMOKE[name]
    if any("{ws}" in a for a in smoke.args):
        from mapkit.ingest import ingest

        ingest([SAMPLE], tmp_path / "ws", progress=False)
    args = [a.replace("{ws}", str(tmp_path / "ws")) for a in smoke.args]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    with _one_core():  # the repository root as the working directory, as scripts/bench.sh runs them
        proc = subprocess.run([sys.executable, str(BENCHMARKS / name), *args], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=300)
    assert proc.returncode == 0, f"{name} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    for pattern in smoke.expect:
        assert re.search(pattern, proc.stdout, re.MULTILINE), f"{name}: no match for {pattern!r} in:\n{proc.stdout}"
    if name == "bench_trajopt.py" and not PEERS.exists():
        # without .venv-peers the peers' cells are empty and a note says how to get them
        assert "peer environment .venv-peers not found" in proc.stdout
