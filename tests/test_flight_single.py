"""`Planner.plan` without K / T_body_camera: a model that checks its paths against the depth image uses
the camera its run recorded (config.json's ``camera``), says so once, and refuses when there is none."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from mapkit.flight import FlightError, Planner, pretrained_dir, recorded_camera

GOAL = np.array([5.0, 0.5, 0.0])


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner.load("pretrained")


def _depth(width: int = 160, height: int = 120) -> np.ndarray:
    """A wall 6 m ahead with a box 2.5 m ahead left of centre, and a few invalid pixels."""
    depth = np.full((height, width), 6.0, np.float32)
    depth[height // 3 : 2 * height // 3, width // 4 : width // 2] = 2.5
    depth[:4, :] = np.nan
    return depth


def test_the_shipped_model_plans_from_only_a_depth_image_and_a_goal(planner: Planner):
    saved = json.loads((pretrained_dir() / "config.json").read_text())["camera"]
    cam = planner.camera
    assert planner.needs_camera and cam is not None
    assert (cam.width, cam.height) == (saved["width"], saved["height"])
    np.testing.assert_array_equal(cam.K, saved["K"])
    np.testing.assert_array_equal(cam.T_body_camera, saved["T_body_camera"])

    with pytest.warns(UserWarning, match=r"camera the model's run recorded \(160x120"):
        implicit = planner.plan(_depth(), GOAL)
    explicit = planner.plan(_depth(), GOAL, K=np.array(saved["K"]), T_body_camera=np.array(saved["T_body_camera"]))
    assert implicit.camera_from_run and not explicit.camera_from_run
    for name in ("keypoints", "durations", "samples_t", "samples_body", "goal_body"):
        np.testing.assert_array_equal(getattr(implicit, name), getattr(explicit, name), err_msg=name)
    assert (implicit.eta, implicit.control_effort, implicit.widened) == (explicit.eta, explicit.control_effort,
                                                                        explicit.widened)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once per planner
        assert planner.plan(_depth(), GOAL).camera_from_run


def test_the_recorded_camera_is_refused_for_depth_of_another_size_and_half_a_calibration(planner: Planner):
    with pytest.raises(FlightError, match=r"depth is 200x100 pixels .* is 160x120: pass the camera's K"):
        planner.plan(_depth(200, 100), GOAL)
    assert planner.camera is not None
    with pytest.raises(FlightError, match="both, or neither"):
        planner.plan(_depth(), GOAL, K=planner.camera.K)


def test_messages_name_the_recorded_camera_without_the_training_machine_s_paths():
    """The shipped model's config.json records where its run read the camera on the machine that
    trained it; the warning and the refusal name only the workspace and store (a fresh planner, so
    the once-only warning is said)."""
    source = Path(json.loads((pretrained_dir() / "config.json").read_text())["camera"]["source"])
    assert source.is_absolute() and len(source.parts) > 3  # the foreign path the messages must not show
    shown = f"{source.parent.name}/{source.name}"
    planner = Planner.load("pretrained")
    with pytest.warns(UserWarning) as said:
        planner.plan(_depth(), GOAL)
    with pytest.raises(FlightError) as refused:
        planner.plan(_depth(200, 100), GOAL)
    for message in (str(said[0].message), str(refused.value)):
        assert f"({shown}" in message or f"from {shown})" in message, message
        assert str(source.parent) not in message, message


def test_a_run_that_records_no_camera_keeps_the_refusal_naming_the_fix(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(pretrained_dir() / "model.pt", run / "model.pt")
    saved = json.loads((pretrained_dir() / "config.json").read_text())
    del saved["camera"]
    (run / "config.json").write_text(json.dumps(saved))
    planner = Planner.load(run)
    assert planner.camera is None and recorded_camera(run) is None
    with pytest.raises(FlightError, match=r"pass the camera's K and T_body_camera \(its run records no camera"):
        planner.plan(_depth(), GOAL)
    (run / "config.json").write_text("{ not json")  # unreadable: no camera either, still loads
    assert recorded_camera(run) is None and Planner.load(run).camera is None
