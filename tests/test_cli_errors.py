"""Every numeric option of every command, given a value no command can use, stops before any work
with one line naming the option (click usage error, exit 2) — and the exit-code convention."""

from __future__ import annotations

from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from mapkit.cli.main import Number, main


def _commands() -> dict[str, click.Command]:
    """Every command by its path below `mapkit` (`eval`, `lab tune-timing`)."""
    found: dict[str, click.Command] = {}
    for name, command in sorted(main.commands.items()):
        if isinstance(command, click.Group):
            found.update({f"{name} {sub}": c for sub, c in sorted(command.commands.items())})
        else:
            found[name] = command
    return found


def _numeric_options() -> list[tuple[str, click.Option]]:
    found = []
    for name, command in _commands().items():
        for param in command.params:
            if isinstance(param, click.Option) and isinstance(param.type, Number):
                found.append((name, param))
    return found


NUMERIC = _numeric_options()


def test_every_numeric_option_is_checked():
    """No numeric option is a bare float/int any more (those accept nan and inf)."""
    bare = [f"{name} {param.opts[0]}" for name, command in _commands().items() for param in command.params
            if isinstance(param, click.Option) and param.type in (click.FLOAT, click.INT)]
    assert not bare, bare
    assert len(NUMERIC) >= 20


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf", "abc"])
@pytest.mark.parametrize("command, option", NUMERIC, ids=[f"{c}{o.opts[0]}" for c, o in NUMERIC])
def test_a_bad_number_is_one_line_naming_the_option(command: str, option: click.Option, bad: str):
    values = [bad] + ["0"] * (option.nargs - 1)
    r = CliRunner().invoke(main, [*command.split(), option.opts[0], *values], prog_name="mapkit")
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2, r.output
    assert len(lines) == 1 and lines[0].startswith(f"error: mapkit {command}: ") and option.opts[0] in lines[0]
    assert "Traceback" not in r.output


@pytest.mark.parametrize("command, option", [(c, o) for c, o in NUMERIC if o.type.low is not None],
                         ids=[f"{c}{o.opts[0]}" for c, o in NUMERIC if o.type.low is not None])
def test_a_number_below_range_is_refused(command: str, option: click.Option):
    low = option.type.low
    bad = str(low) if option.type.low_open else str(low - 1)
    values = [bad] + ["1"] * (option.nargs - 1)
    r = CliRunner().invoke(main, [*command.split(), option.opts[0], *values], prog_name="mapkit")
    assert r.exit_code == 2 and r.output.count("\n") == 1 and f"must be {'>' if option.type.low_open else '>='}" in r.output


def test_usage_errors_are_one_line_with_exit_2_and_help_still_works():
    for args in (["nosuch"], ["esdf", "--no-such-option"], ["view", "-w", "x", "--port", "99999"], ["plan", "-w", "x"]):
        r = CliRunner().invoke(main, args, prog_name="mapkit")
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and r.output.startswith("error: mapkit")
    r = CliRunner().invoke(main, ["esdf", "--help"], prog_name="mapkit")
    assert r.exit_code == 0 and "Usage: mapkit esdf" in r.output


# Values that click's types let through but a command's config refuses (a range that depends on the
# option, or on another one, or text the library parses): (arguments, what the one line names).
LIBRARY_CHECKED = [
    (["esdf", "-w", "ws", "--voxel", "-1"], "--voxel -1.0 must be positive"),
    (["fuse", "-w", "ws", "--voxel", "0"], "--voxel 0.0 must be positive"),
    (["fuse", "-w", "ws", "--set", "trunc=0.5"], "trunc 0.5 must be at least 1 voxel"),
    (["fuse-world", "ws", "-o", "world", "--set", "tile=100"], "tile 100 must be a positive multiple of 64"),
    (["ingest", "x.mcap", "-w", "ws", "--set", "ingest.extrinsic=1,2"], "extrinsic '1,2' is not x,y,z"),
    (["ingest", "x.mcap", "-w", "ws", "--intrinsics", "-1,1,1,1"], "focal lengths must be positive"),
    (["batch", "x.mcap", "-o", "root", "--set", "esdf.voxel=0"], "--voxel 0.0 must be positive"),
    (["batch", "x.mcap", "-o", "root", "--steps", "ingest,mesh"], "unknown step 'mesh'"),
    (["export", "-w", "ws", "--set", "goal_range=[5, 1]"], "goal_range 5.0 1.0: need 0 < min < max"),
    (["simulate", "-o", "flight", "--set", "width=0"], "bad resolution width=0"),
    (["dataset", "-o", "d", "--set", "speed=0.5,2"], "speed 0.5 2.0: need 1.0 <= min <= max <= 3.0"),
    (["dataset", "-o", "d", "--set", "cameras=640by360"], "is not WIDTHxHEIGHT"),
    (["train", "-w", "ws", "--set", "lr=-1"], "lr -1.0 must be positive"),
    (["train", "-w", "ws", "--set", "planner.no_such_field=1"], "no setting 'planner.no_such_field'"),
    (["eval", "-o", "ev", "--methods", "straight", "--set", "loop.pilot.replan_interval=0.13"],
     "loop.pilot.replan_interval 0.13 s"),
    (["eval", "-o", "ev", "--methods", "straight", "--stack", "full,full"], "flight stack given twice"),
    (["lab", "tune-timing", "--plans", "p", "--val", "v", "-o", "t", "--set", "tan_hidden=0,256"],
     "tan_hidden must be widths >= 1"),
]


@pytest.mark.parametrize("args, needle", LIBRARY_CHECKED, ids=[" ".join(a[:1] + a[-2:]) for a, _ in LIBRARY_CHECKED])
def test_a_value_the_library_refuses_is_a_usage_error_before_any_work(args: list[str], needle: str, tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch):
    """Exit 2 and one line naming the option, its value and the fix, as for the values click refuses;
    nothing is written (the inputs do not even exist)."""
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(main, args, prog_name="mapkit")
    lines = r.output.strip().splitlines()
    command = " ".join(args[:2] if args[0] == "lab" else args[:1])
    assert r.exit_code == 2, r.output
    assert len(lines) == 1 and lines[0].startswith(f"error: mapkit {command}: ") and needle in lines[0], r.output
    assert lines[0].endswith(f"(see mapkit {command} --help)") and not list(tmp_path.iterdir())


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_what_killed_commands_left_is_cleaned_up_and_a_half_replaced_store_restored(tmp_path, caplog):
    from mapkit.workspace import atomic_output, clean_stale

    dead = _dead_pid()
    (tmp_path / f".map.zarr.partial-{dead}").mkdir()
    (tmp_path / f".map.zarr.partial-{dead}" / "zarr.json").write_text("{}")
    (tmp_path / f".cloud.ply.partial-{dead}.ply").write_bytes(b"ply")
    (tmp_path / f".frames.zarr.old-{dead}").mkdir()  # killed between moving the old store aside and the new in
    (tmp_path / f".tuples.zarr.old-{dead}").mkdir()
    (tmp_path / "tuples.zarr").mkdir()  # ... or after the new one was in place
    mine = tmp_path / f".x.partial-{__import__('os').getpid()}"  # a live process's: left alone
    mine.write_text("busy")
    with caplog.at_level("WARNING"):
        handled = clean_stale(tmp_path)
    assert len(handled) == 4 and mine.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["frames.zarr", "tuples.zarr", mine.name])
    assert "restored" in caplog.text and "removed" in caplog.text
    (tmp_path / f".eval.partial-{dead}").mkdir()
    with atomic_output(tmp_path / "eval", overwrite=False) as tmp:  # every writer cleans up first
        tmp.mkdir()
    assert not (tmp_path / f".eval.partial-{dead}").exists() and (tmp_path / "eval").is_dir()


@pytest.fixture
def small_disk(tmp_path):
    """A directory on a tmpfs of a chosen size (needs root and mount; CI runs as root)."""
    import subprocess

    mounted = []

    def make(size_bytes: int):
        where = tmp_path / f"disk{len(mounted)}"
        where.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes}", "tmpfs", str(where)], capture_output=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip() or 'not root'}); CI runs this as root")
        mounted.append(where)
        return where

    yield make
    for where in mounted:
        subprocess.run(["umount", "--lazy", str(where)], capture_output=True)  # lazy: a store handle may still be open


def _dir_bytes(path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def test_a_full_disk_is_one_line_naming_the_place_and_keeps_what_was_there(small_disk, tmp_path):
    import shutil

    from scenes import box_world, orbit_poses, record_scene

    flight = record_scene(box_world(), tmp_path / "box.mcap", orbit_poses(24))
    runner = CliRunner()
    tiny = small_disk(64 * 1024)
    r = runner.invoke(main, ["ingest", str(flight), "-w", str(tiny / "ws")])
    assert r.exit_code == 1 and f"No space left on device: {tiny / 'ws'}" in r.output and "Traceback" not in r.output
    assert not [p for p in tiny.rglob("*") if p.name.endswith("zarr") or ".partial-" in p.name]

    ws = tmp_path / "ws"
    assert runner.invoke(main, ["fuse", str(flight), "-w", str(ws), "--voxel", "0.1", "--mesh"]).exit_code == 0
    disk = small_disk(_dir_bytes(ws) + 256 * 1024)
    shutil.copytree(ws, disk / "ws")
    before = {p.name: p.read_bytes() for p in (disk / "ws").iterdir() if p.is_file()}
    r = runner.invoke(main, ["fuse", "-w", str(disk / "ws"), "--voxel", "0.06", "--mesh", "--overwrite"])
    errors = [line for line in r.output.splitlines() if line.startswith("error:")]
    assert r.exit_code == 1 and len(errors) == 1 and "Traceback" not in r.output, r.output
    assert {p.name: p.read_bytes() for p in (disk / "ws").iterdir() if p.is_file()} == before
    assert not [p for p in (disk / "ws").iterdir() if ".partial-" in p.name]
    r = runner.invoke(main, ["esdf", "-w", str(disk / "ws"), "--voxel", "0.1"])
    assert r.exit_code == 1 and "No space left on device" in r.output and not (disk / "ws" / "map.zarr").exists(), r.output


@pytest.mark.slow
def test_kill_9_at_any_point_leaves_every_store_readable(tmp_path):
    """kill -9 of ingest / fuse / esdf / export --overwrite at several moments: every output still
    opens with its reader and fuse's files match fuse.json; the next run clears what was left."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from scenes import box_world, orbit_poses, record_scene

    from mapkit.esdf import EsdfMap
    from mapkit.fusion import check_fused
    from mapkit.ingest import open_frames_store
    from mapkit.train._data import TupleStore

    flight = record_scene(box_world(), tmp_path / "box.mcap", orbit_poses(36))
    ws = tmp_path / "ws"
    commands = {
        "ingest": ["ingest", str(flight)],
        "fuse": ["fuse", "--voxel", "0.05", "--mesh"],
        "esdf": ["esdf", "--voxel", "0.05"],
        "export": ["export"],
    }
    for args in commands.values():
        assert CliRunner().invoke(main, [*args, "-w", str(ws)]).exit_code == 0

    def readable() -> None:
        open_frames_store(ws)
        check_fused(ws)
        EsdfMap.open(ws / "map.zarr").load()
        TupleStore.open(ws)

    killed = 0
    env = {**os.environ, "PYTHONPATH": str(__import__("pathlib").Path(__file__).parent)}
    for args in commands.values():
        for delay in (0.8, 2.0):
            proc = subprocess.Popen([sys.executable, "-m", "mapkit.cli", *args, "-w", str(ws), "--overwrite"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
            time.sleep(delay)
            if proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                killed += 1
            proc.wait()
            readable()
    assert killed >= 3  # the kills did land mid-command
    assert CliRunner().invoke(main, ["esdf", "-w", str(ws), "--voxel", "0.05", "--overwrite"]).exit_code == 0
    assert not [p.name for p in ws.iterdir() if ".partial-" in p.name or ".old-" in p.name]
    readable()


def test_unreadable_and_unwritable_places_are_one_line_for_an_unprivileged_user(tmp_path):
    """Run as `nobody` (needs root and setpriv; CI runs as root): an input in a folder it cannot read
    and a workspace in a folder it cannot write."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run a command as an unprivileged user; CI runs this as root")
    from recordings import write_recording

    base = Path(tempfile.mkdtemp(prefix="mapkit-perm-"))
    try:
        base.chmod(0o755)
        rec = write_recording(base / "open", "mcap", n=3)
        rec.path.chmod(0o644)
        locked = base / "locked"
        locked.mkdir(mode=0o700)
        shutil.copy(rec.path, locked / "rec.mcap")
        readonly = base / "readonly"
        readonly.mkdir(mode=0o755)
        cases = [(["ingest", str(locked / "rec.mcap"), "-w", str(base / "ws1")], "Permission denied"),
                 (["ingest", str(rec.path), "-w", str(readonly / "ws")], "Permission denied")]
        for args, needle in cases:
            r = subprocess.run(["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups",
                                sys.executable, "-m", "mapkit.cli", *args], capture_output=True, text=True, cwd=base)
            lines = [line for line in r.stderr.splitlines() if line.strip() and not line.startswith("ingest:")]
            assert r.returncode == 1 and len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, r.stderr
    finally:
        shutil.rmtree(base, ignore_errors=True)

