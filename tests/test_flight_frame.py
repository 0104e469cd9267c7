"""mapkit.flight.goal_in_body / plan_from_frame: the goal → body conversion `mapkit plan` and the viewer share."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.flight import GOAL_FRAMES, goal_in_body, plan_from_frame


def test_goal_in_body_inverts_the_body_pose() -> None:
    T_wb = np.eye(4)
    T_wb[:3, :3] = Rotation.from_euler("zyx", [0.7, 0.1, -0.2]).as_matrix()
    T_wb[:3, 3] = [3.0, -2.0, 1.5]
    goal_w = np.array([5.0, 1.0, 2.0])
    g = goal_in_body(goal_w, T_wb, "world")
    np.testing.assert_allclose(T_wb[:3, :3] @ g + T_wb[:3, 3], goal_w, atol=1e-12)
    np.testing.assert_array_equal(goal_in_body(goal_w, T_wb, "body"), goal_w)
    assert GOAL_FRAMES == ("body", "world")


def test_plan_from_frame_passes_the_body_goal_and_the_camera_calibration() -> None:
    class Recorder:
        def plan(self, depth, goal_body, **kw):  # the Planner.plan call it makes
            self.args = (depth, goal_body, kw)
            return "result"

    T_wb = np.eye(4)
    T_wb[:3, 3] = [1.0, 2.0, 0.5]
    T_wc = T_wb.copy()
    T_wc[:3, 3] += [0.1, 0.0, 0.0]
    K = np.diag([40.0, 40.0, 1.0])
    rec = Recorder()
    planned = plan_from_frame(rec, np.ones((4, 5), np.float32), T_wb, T_wc, K, (4.0, 2.0, 0.5), goal_frame="world",
                              velocity_body=np.zeros(3), corridor=0.3)
    np.testing.assert_allclose(planned.goal_body, [3.0, 0.0, 0.0])
    assert planned.result == "result"
    _, goal_body, kw = rec.args
    np.testing.assert_array_equal(goal_body, planned.goal_body)
    np.testing.assert_allclose(kw["T_body_camera"][:3, 3], [0.1, 0.0, 0.0])
    assert kw["corridor"] == 0.3 and kw["K"] is K
    from mapkit.flight import WIDEN

    assert kw["widen"] == WIDEN  # the default
    plan_from_frame(rec, np.ones((4, 5), np.float32), T_wb, T_wc, K, (4.0, 2.0, 0.5), widen=())
    assert rec.args[2]["widen"] == ()
