"""Every script in examples/ runs as a user runs it: alone, and chained on one workspace."""

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
pytestmark = pytest.mark.slow


def run_example(name: str, *args: str | Path, cwd: Path) -> str:
    """Run examples/`name` with `args` in `cwd`; its stdout, after checking it exited 0."""
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def test_examples_are_numbered():
    names = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert names[:4] == ["01_ingest_and_map.py", "02_query_esdf.py", "03_plan_with_a_model.py", "04_evaluate.py"]
    assert all(name[:2].isdigit() and name[2] == "_" for name in names)


@pytest.mark.parametrize("name, expected", [
    ("01_ingest_and_map.py", "esdf: "),
    ("02_query_esdf.py", "the ball's exact -0.500"),
    ("03_plan_with_a_model.py", "wrote plan_"),
    ("04_evaluate.py", "learned: "),
    ("05_export_training_tuples.py", "tuple 0's goals"),
    ("06_fly_your_own_vehicle.py", "reached after"),
])
def test_example_alone_writes_only_temporary_files(name, expected, tmp_path):
    out = run_example(name, cwd=tmp_path)
    assert expected in out
    assert not any(tmp_path.iterdir()), f"{name} wrote into the folder it ran in"


def test_the_own_vehicle_loop_is_short():
    """The loop a user copies stays readable: at most 60 lines of code in the example."""
    lines = (EXAMPLES / "06_fly_your_own_vehicle.py").read_text().splitlines()
    body = lines[next(i for i, line in enumerate(lines) if line.startswith("import")):]
    assert len(body) <= 60


def test_examples_chained_on_one_workspace(tmp_path):
    ws = tmp_path / "ws"
    assert "esdf: " in run_example("01_ingest_and_map.py", ws, cwd=tmp_path)
    assert "distance " in run_example("02_query_esdf.py", ws / "map.zarr", cwd=tmp_path)
    assert "wrote plan_" in run_example("03_plan_with_a_model.py", ws, cwd=tmp_path)
    assert "tuple 0's goals" in run_example("05_export_training_tuples.py", ws, cwd=tmp_path)
    assert {p.name for p in ws.iterdir()} >= {"frames.zarr", "cloud.ply", "map.zarr", "tuples.zarr", "plans"}
