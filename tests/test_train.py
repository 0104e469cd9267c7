"""Training: smoke run, resume after a stop, incompatible resume, bad inputs, 2-process DDP (gloo)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, build_esdf
from mapkit.export import ExportConfig, export_tuples
from mapkit.fusion import FuseConfig, fuse
from mapkit.sim import SimConfig, simulate
from mapkit.train import TrainConfigError, preset, train

TINY = {"input_size": [32, 48], "encoder_width": 0.125}


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("train")
    result = simulate(SimConfig(world="forest", seed=4, duration=4.0, width=64, height=48), tmp / "flight", progress=False)
    ws = tmp / "ws"
    fuse([result.bag_path], ws, FuseConfig(voxel=0.1), progress=False)
    build_esdf(ws, EsdfConfig(voxel=0.2, sigma=0.2), progress=False)
    export_tuples(ws, ExportConfig(goals_per_frame=2, stride=4, segment_seconds=1.0), progress=False)
    return ws


def tiny(name: str, **kw: object):
    return preset("cpu", name=name, epochs=kw.pop("epochs", 1), batch_size=4, max_steps=kw.pop("max_steps", 2),
                  val_batches=2, planner=kw.pop("planner", TINY), **kw)


@pytest.mark.slow
def test_smoke_run_writes_the_run_directory(workspace: Path, tmp_path: Path) -> None:
    s = train([workspace], tiny("smoke"), runs_dir=tmp_path, progress=False)
    run = tmp_path / "smoke"
    assert s.steps == 2
    for name in ("config.json", "metrics.jsonl", "checkpoint.pt", "model.pt", "training_curves.png"):
        assert (run / name).exists(), name
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert lines[0]["epoch"] == 0 and "straight" in lines[0] and lines[1]["epoch"] == 1
    model = torch.load(run / "model.pt", map_location="cpu", weights_only=True)
    assert "state_dict" in model and list(model["planner_config"]["input_size"]) == [32, 48]
    # Seeded: the same run gives the same weights on CPU.
    train([workspace], tiny("smoke"), runs_dir=tmp_path, overwrite=True, progress=False)
    again = torch.load(run / "model.pt", map_location="cpu", weights_only=True)
    for key, value in model["state_dict"].items():
        assert torch.equal(value, again["state_dict"][key]), key


@pytest.mark.slow
def test_resume_continues_after_the_last_epoch(workspace: Path, tmp_path: Path) -> None:
    train([workspace], tiny("r", epochs=1, max_steps=None), runs_dir=tmp_path, progress=False)
    with open(tmp_path / "r" / "metrics.jsonl", "a") as f:  # killed after epoch 2's row, before its checkpoint
        f.write(json.dumps({"epoch": 2, "step": 99}) + "\n")
    saved_path = tmp_path / "r" / "config.json"
    saved = json.loads(saved_path.read_text())
    for old in (2.5, None):  # a run made before eta_horizon was removed: refused unless at the old default
        saved_path.write_text(json.dumps({**saved, "loss": {**saved["loss"], "eta_horizon": old}}))
        if old is not None:
            with pytest.raises(TrainConfigError, match=r"eta_horizon=2\.5: the field was removed"):
                train([workspace], tiny("r", epochs=2, max_steps=None), runs_dir=tmp_path, resume=True, progress=False)
    s = train([workspace], tiny("r", epochs=2, max_steps=None), runs_dir=tmp_path, resume=True, progress=False)
    rows = [json.loads(x) for x in (tmp_path / "r" / "metrics.jsonl").read_text().splitlines()]
    assert [row["epoch"] for row in rows] == [0, 1, 2] and rows[-1]["step"] != 99 and s.epochs_done == 2
    with pytest.raises(TrainConfigError, match="incompatible config: planner"):
        train([workspace], preset("cpu", name="r", epochs=3, batch_size=4, planner={"input_size": [48, 64]}),
              runs_dir=tmp_path, resume=True, progress=False)
    with pytest.raises(TrainConfigError, match="exists; pass --resume"):
        train([workspace], tiny("r"), runs_dir=tmp_path, progress=False)


def test_a_fine_tuned_run_records_the_worlds_its_init_model_trained_on(tmp_path: Path, caplog) -> None:
    """`mapkit eval` refuses the seeds of every world a model has seen, its --init model's too."""
    from mapkit.train._loop import _init_worlds

    run = tmp_path / "base"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"training_worlds": [["forest", 1000], ["office", 1001]]}))
    assert _init_worlds(str(run)) == {("forest", 1000), ("office", 1001)}
    assert _init_worlds(str(run / "model.pt")) == {("forest", 1000), ("office", 1001)}
    assert _init_worlds(None) == set()
    assert ("forest", 1000) in _init_worlds("pretrained")  # the shipped model records the worlds of both its trainings
    (run / "config.json").write_text("not json")
    assert _init_worlds(str(run)) == set() and "cannot refuse them" in caplog.text


@pytest.mark.slow
def test_init_starts_from_another_models_weights(workspace: Path, tmp_path: Path) -> None:
    train([workspace], tiny("a"), runs_dir=tmp_path, progress=False)
    train([workspace], tiny("b", max_steps=1, lr=1e-12, seed=1, init=str(tmp_path / "a")), runs_dir=tmp_path,
          progress=False)
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=True)["state_dict"]
    weights = [k for k in a if k.endswith("weight") and "bn" not in k and a[k].ndim > 1]
    assert weights and all(torch.allclose(a[k], b[k], atol=1e-6) for k in weights)
    assert json.loads((tmp_path / "b" / "config.json").read_text())["init"] == str(tmp_path / "a")
    with pytest.raises(TrainConfigError, match="input_size"):
        train([workspace], preset("cpu", name="c", epochs=1, batch_size=4, max_steps=1, init=str(tmp_path / "a"),
                                  planner={**TINY, "input_size": [48, 64]}), runs_dir=tmp_path, progress=False)
    r = CliRunner().invoke(main, ["train", "-w", str(workspace), "--init", str(tmp_path / "nope"), "--set", "max_steps=1",
                                  "--runs-dir", str(tmp_path / "runs")])
    assert r.exit_code == 1 and "no model.pt" in r.output, r.output


@pytest.mark.slow
def test_only_tan_trains_the_time_allocation_and_nothing_else(workspace: Path, tmp_path: Path) -> None:
    # The init model's TAN has no boundary inputs; the new one does (its weights start fresh).
    train([workspace], tiny("base", planner={**TINY, "tan_boundary": False}), runs_dir=tmp_path, progress=False)
    train([workspace], tiny("tan", max_steps=3, lr=1e-2, init=str(tmp_path / "base"), only="tan",
                            planner={**TINY, "tan_boundary": True}), runs_dir=tmp_path, progress=False)
    a = torch.load(tmp_path / "base" / "model.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "tan" / "model.pt", weights_only=True)["state_dict"]
    rest = [k for k in a if not k.startswith("tan.")]
    assert rest and all(torch.equal(a[k], b[k]) for k in rest)  # batch-norm statistics included
    assert b["tan.mlp.0.weight"].shape[1] == a["tan.mlp.0.weight"].shape[1] + 7
    with pytest.raises(TrainConfigError, match="--init"):
        train([workspace], tiny("x", only="tan"), runs_dir=tmp_path, progress=False)
    with pytest.raises(TrainConfigError, match="input_size"):  # only the TAN's options may differ
        train([workspace], tiny("y", only="tan", init=str(tmp_path / "base"), planner={**TINY, "input_size": [48, 64]}),
              runs_dir=tmp_path, progress=False)


@pytest.mark.slow
def test_only_judge_trains_the_judge_and_nothing_else(workspace: Path, tmp_path: Path) -> None:
    planner = {**TINY, "num_candidates": 4}
    train([workspace], tiny("base", planner=planner), runs_dir=tmp_path, progress=False)
    train([workspace], tiny("judge", max_steps=3, lr=1e-2, init=str(tmp_path / "base"), only="judge", planner=planner),
          runs_dir=tmp_path, progress=False)
    a = torch.load(tmp_path / "base" / "model.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "judge" / "model.pt", weights_only=True)["state_dict"]
    judge = [k for k in a if k.startswith("judge_mlp.")]
    rest = [k for k in a if not k.startswith("judge_mlp.")]
    assert rest and all(torch.equal(a[k], b[k]) for k in rest)  # batch-norm statistics included
    assert judge and not all(torch.equal(a[k], b[k]) for k in judge)
    with pytest.raises(TrainConfigError, match="--init"):
        train([workspace], tiny("x", only="judge"), runs_dir=tmp_path, progress=False)


def test_cli_bad_inputs(workspace: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(main, ["train", "-w", str(tmp_path), "--runs-dir", str(tmp_path / "runs")])
    assert result.exit_code == 1 and "mapkit export" in result.output and "Traceback" not in result.output
    result = runner.invoke(main, ["train", "-w", str(workspace), "--device", "cuda:7", "--runs-dir", str(tmp_path / "runs")])
    assert result.exit_code == 1 and "cuda" in result.output.lower() and "Traceback" not in result.output
    result = runner.invoke(main, ["train", "-w", str(workspace), "--set", "lr=-1", "--runs-dir", str(tmp_path / "runs")])
    assert result.exit_code == 2 and "lr -1.0 must be positive" in result.output  # a usage error, before any work


@pytest.mark.slow
def test_gradients_reach_every_parameter_group(workspace: Path) -> None:
    from mapkit.esdf import EsdfMap
    from mapkit.planner import LossConfig, PlannerConfig, PlannerNet, candidate_loss
    from mapkit.train import TupleSamples, TupleStore

    torch.manual_seed(0)
    samples = TupleSamples([TupleStore.open(workspace)], "train", goals_together=True)
    k, part = next(samples.batches(4, shuffle=False))
    batch = samples.load(k, part, torch.device("cpu"))
    assert batch["depth"].shape[0] < len(part)  # goals of one image share its encoder pass
    net = PlannerNet(PlannerConfig.from_dict({**TINY, "num_candidates": 4}))
    out = net(net.preprocess(batch["depth"]), batch["goal"], batch["image_index"])
    loss, _ = candidate_loss(net, out, goal=batch["goal"], T_world_body=batch["T_world_body"],
                             esdf_map=EsdfMap.open(workspace / "map.zarr"), start_velocity=batch["velocity"],
                             config=LossConfig())
    loss.backward()
    groups = {"encoder": net.encoder, "goal": net.goal_embed, "keypoints": net.keypoint_mlp, "judge": net.judge_mlp,
              "tan": net.tan}
    for name, module in groups.items():
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        assert grads and any(float(g.abs().sum()) > 0 for g in grads), name


@pytest.mark.slow
def test_two_process_ddp_with_gloo(workspace: Path, tmp_path: Path) -> None:
    """The documented multi-process command, with 2 CPU processes (gloo)."""
    env = {**os.environ, "MAPKIT_DDP_BACKEND": "gloo", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port", "29531",
           "-m", "mapkit.cli", "train", "-w", str(workspace), "--name", "ddp", "--runs-dir", str(tmp_path),
           "--epochs", "1", "--set", "batch_size=4", "--set", "max_steps=2", "--set", "val_batches=1",
           "--set", "planner.input_size=[32,48]", "--set", "planner.encoder_width=0.125"]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "ddp" / "model.pt").exists()
    lines = [json.loads(x) for x in (tmp_path / "ddp" / "metrics.jsonl").read_text().splitlines()]
    assert lines[-1]["epoch"] == 1 and lines[-1]["step"] == 2


@pytest.mark.slow
def test_corridor_training_step(workspace: Path, tmp_path: Path) -> None:
    s = train([workspace], tiny("corr", corridor=0.2), runs_dir=tmp_path, progress=False)
    assert s.steps == 2 and (tmp_path / "corr" / "model.pt").exists()
    with pytest.raises(TrainConfigError, match=r"corridor -1\.0"):
        train([workspace], tiny("bad", corridor=-1.0), runs_dir=tmp_path, progress=False)


@pytest.mark.slow
def test_plan_from_a_recorded_frame(workspace: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    train([workspace], tiny("p"), runs_dir=tmp_path, progress=False)
    runner = CliRunner()
    out = tmp_path / "plans"
    result = runner.invoke(main, ["plan", "--model", str(tmp_path / "p"), "-w", str(workspace), "--frame", "3",
                                  "--goal", "4", "0.5", "0", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "eta" in result.output and "latency" in result.output
    data = json.loads((out / "plan_000003.json").read_text())
    assert len(data["positions_world"]) == len(data["t"]) > 10
    tum = (out / "plan_000003.tum").read_text().splitlines()
    assert len(tum) == len(data["t"]) and len(tum[0].split()) == 8
    with open(out / "plan_000003.mcap", "rb") as f:
        schemas = {s.name for s in make_reader(f).get_summary().schemas.values()}
    assert "nav_msgs/msg/Path" in schemas
    result = runner.invoke(main, ["plan", "--model", str(tmp_path / "p"), "-w", str(workspace), "--frame", "3",
                                  "--goal", "4", "0.5", "0", "-o", str(tmp_path / "plain"), "--no-widen", "--no-shift"])
    assert result.exit_code == 0, result.output
    # Stamps exact to the nanosecond: frame stamp + round(t · 1e9), in TUM, JSON and every MCAP pose.
    from mcap_ros2.decoder import DecoderFactory

    from mapkit.ingest import open_frames_store

    stamp = int(open_frames_store(workspace).stamp_ns[3])
    expected = [stamp + round(t * 1e9) for t in data["t"]]
    assert data["stamps_ns"] == expected and len(set(expected)) == len(expected)
    assert [int(line.split()[0].replace(".", "")) for line in tum] == expected
    with open(out / "plan_000003.mcap", "rb") as f:
        _, _, _, path = next(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in path.poses] == expected
    # A goal beyond the planner's range: planned to the local goal on its way, and said so.
    result = runner.invoke(main, ["plan", "--model", str(tmp_path / "p"), "-w", str(workspace), "--frame", "3",
                                  "--goal", "1e9", "0", "0", "-o", str(tmp_path / "far")])
    assert result.exit_code == 0 and "beyond the planner's 6 m range" in result.output, result.output
    far = json.loads((tmp_path / "far" / "plan_000003.json").read_text())
    assert far["goal_clipped"] and far["goal_body"] == [6.0, 0.0, 0.0]
    assert np.abs(np.asarray(far["keypoints_body"])).max() < 100 and far["control_effort_m2_s7"] < 1e9
    result = runner.invoke(main, ["plan", "--model", str(tmp_path / "nope"), "-w", str(workspace), "--frame", "3",
                                  "--goal", "4", "0", "0"])
    assert result.exit_code == 1 and "no model.pt" in result.output
    result = runner.invoke(main, ["plan", "--model", str(tmp_path / "p"), "-w", str(workspace), "--frame", "99999",
                                  "--goal", "4", "0", "0"])
    assert result.exit_code == 1 and "--frame 99999" in result.output
    a_file = tmp_path / "plan.json"
    a_file.write_text("keep me")
    for target in (a_file, a_file / "sub"):
        result = runner.invoke(main, ["plan", "--model", str(tmp_path / "p"), "-w", str(workspace), "--frame", "3",
                                      "--goal", "4", "0", "0", "-o", str(target)])
        assert result.exit_code == 1 and "-o takes a folder" in result.output and "Traceback" not in result.output
    assert a_file.read_text() == "keep me"


def test_a_file_system_error_is_one_line_naming_the_path(tmp_path: Path) -> None:
    import click

    from mapkit.cli.main import library_call

    @click.command()
    @library_call
    def denied() -> None:
        raise PermissionError(13, "Permission denied", str(tmp_path / "locked"))

    result = CliRunner().invoke(denied, [])
    assert result.exit_code == 1
    assert result.output.strip() == f"error: Permission denied: {tmp_path / 'locked'}"


@pytest.mark.slow
def test_held_out_worlds_validate_and_select_the_model(workspace: Path, tmp_path: Path) -> None:
    import shutil

    from mapkit.train import TrainDataError

    held_out = tmp_path / "held_out_world"
    shutil.copytree(workspace, held_out, ignore=shutil.ignore_patterns("runs"))
    s = train([workspace], tiny("held", epochs=2, max_steps=None), runs_dir=tmp_path, progress=False,
              val_workspaces=[held_out])
    lines = [json.loads(x) for x in (tmp_path / "held" / "metrics.jsonl").read_text().splitlines()]
    for key in ("blocked_collision", "blocked_reach", "blocked_count", "active_units", "eta_catches",
                "eta_false_rejects"):
        assert key in lines[-1]["val"], key
        assert 0.0 <= lines[-1]["val"][key] <= 1.0 or key == "blocked_count"
    assert "blocked_reach" in lines[0]["straight"]
    assert s.best_epoch in (1, 2) and lines[-1]["best_epoch"] == s.best_epoch
    model = torch.load(tmp_path / "held" / "model.pt", map_location="cpu", weights_only=True)
    assert model["epoch"] == s.best_epoch
    cfg = json.loads((tmp_path / "held" / "config.json").read_text())
    assert cfg["val_workspaces"] == [str(held_out.resolve())]
    assert cfg["camera"]["width"] == 64 and ["forest", 4] in cfg["training_worlds"]
    assert s.threads == torch.get_num_threads() >= 1
    with pytest.raises(TrainDataError, match="both a training and a validation workspace"):
        train([workspace], tiny("both"), runs_dir=tmp_path, progress=False, val_workspaces=[workspace])


def test_set_threads_follows_the_cpu_affinity() -> None:
    from mapkit.dataset import available_cpus
    from mapkit.train import set_threads

    before = torch.get_num_threads()
    try:
        assert set_threads() == available_cpus() == torch.get_num_threads()
        assert set_threads(world_size=64) == 1 == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("planner, loss, message", [
    ({"input_size": 0}, {}, "planner input_size=0: expected a list of 2 (an integer, an integer)"),
    ({"head_activation": "tanh"}, {}, 'expected one of "relu", "leaky_relu"'),
    ({"num_candidates": 2.5}, {}, "planner num_candidates=2.5: expected an integer"),
    ({}, {"robot_radius": "abc"}, 'loss robot_radius="abc": expected a number'),
    ({}, {"no_such_field": 1}, "LossConfig has no field 'no_such_field'"),
])
def test_nested_options_are_type_checked(planner: dict, loss: dict, message: str) -> None:
    with pytest.raises(TrainConfigError) as info:  # when the typed config is built from the dicts
        preset("cpu", planner=planner, loss=loss).validate()
    assert message in str(info.value)
    preset("cpu", planner={"input_size": [48, 64], "num_candidates": 2, "tan_hidden": [32, 32], "accel": 2},
           loss={"robot_radius": 0.35}).validate()  # lists stand for tuples, integers for floats


def test_a_model_of_random_bytes_is_one_line_without_unsafe_advice(workspace: Path, tmp_path: Path) -> None:
    run = tmp_path / "junk"
    run.mkdir()
    (run / "model.pt").write_bytes(np.random.default_rng(0).bytes(4000))
    partial = tmp_path / "partial"
    partial.mkdir()
    torch.save({"planner_config": {}}, partial / "model.pt")  # a torch file, but not a whole model
    for model in (run, partial):
        result = CliRunner().invoke(main, ["plan", "--model", str(model), "-w", str(workspace), "--frame", "0",
                                           "--goal", "3", "0", "0", "-o", str(tmp_path / "out")])
        lines = result.output.strip().splitlines()
        assert result.exit_code == 1 and len(lines) == 1 and "is not a mapkit planner" in lines[0], result.output
        assert "weights_only" not in result.output
    result = CliRunner().invoke(main, ["train", "-w", str(workspace), "--init", str(run), "--runs-dir", str(tmp_path / "r"),
                                       "--set", "max_steps=1"])
    assert result.exit_code == 1 and "is not a mapkit planner" in result.output and "Traceback" not in result.output


def test_train_alone_trains_in_the_current_directory(workspace: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Without -w (or --dataset) the workspace is the current directory, as for every other command:
    here one without map.zarr, so the run stops at once, naming that folder's missing map."""
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws, ignore=shutil.ignore_patterns("map.zarr", "runs"))
    monkeypatch.chdir(ws)
    result = CliRunner().invoke(main, ["train", "--set", "max_steps=1"])
    assert f"workspace: {ws} (the current directory" in result.output, result.output
    assert result.exit_code == 1 and "map.zarr is missing" in result.output and "mapkit esdf -w ." in result.output


def test_a_missing_map_names_the_command_that_makes_it(workspace: Path, tmp_path: Path) -> None:
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws, ignore=shutil.ignore_patterns("map.zarr", "runs"))
    result = CliRunner().invoke(main, ["train", "-w", str(ws), "--runs-dir", str(tmp_path / "r"), "--set", "max_steps=1"])
    assert result.exit_code == 1 and "map.zarr is missing" in result.output and "mapkit esdf -w" in result.output
