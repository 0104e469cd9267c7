"""Fly the shipped planner from your own vehicle loop: rotorpy's quadrotor under its SE(3) controller.

    python examples/06_fly_your_own_vehicle.py

The pilot gets one call per camera frame (30 Hz) with the depth image, the camera's pose at that frame
(the body's true attitude and the mount: the camera tilts with the airframe), the vehicle's state and
the goal, all world frame ENU, SI units; it replans every 0.5 s and returns a reference to sample at the
controller's rate (100 Hz) for position through snap, yaw and yaw rate. Depth here comes from mapkit's
ray caster in a wall with a doorway; use your own camera instead. About 20 s on 2 cores.
"""

import numpy as np
from rotorpy.controllers.quadrotor_control import SE3Control
from rotorpy.vehicles.hummingbird_params import quad_params
from rotorpy.vehicles.multirotor import Multirotor

from mapkit.flight import Pilot, VehicleState
from mapkit.geometry import transform_from_pose
from mapkit.sim import Box, CameraModel, World, render_depth

START, GOAL = np.array([0.0, 0.0, 1.5]), np.array([10.0, 1.0, 1.5])
WALLS = [Box((5.0, -4.0, 1.5), (0.1, 3.5, 1.5)), Box((5.0, 4.0, 1.5), (0.1, 3.0, 1.5)),  # a doorway at y = -0.5..1
         Box((6.0, 0.0, -0.05), (10.0, 10.0, 0.05))]  # the ground: a frame must have some valid depth
CONTROL_HZ, CAMERA_HZ = 100, 30


def fly() -> None:
    world = World(WALLS, np.array([[-2.0, -8.0, 0.0], [14.0, 8.0, 3.0]]), kind="custom")
    pilot = Pilot.load("pretrained")  # the full flight stack; stack="none" flies the network alone
    cam = pilot.camera  # the camera the model was trained with (its size, K and mount)
    camera = CameraModel(width=cam.width, height=cam.height, fx=cam.K[0, 0], fy=cam.K[1, 1])
    hover = np.full(4, np.sqrt(quad_params["mass"] * 9.81 / (4 * quad_params["k_eta"])))
    state = {"x": START.copy(), "v": np.zeros(3), "q": np.array([0.0, 0.0, 0.0, 1.0]), "w": np.zeros(3),
             "wind": np.zeros(3), "rotor_speeds": hover}
    vehicle, controller = Multirotor(quad_params, initial_state=state), SE3Control(quad_params)
    step, reference = None, None
    for k in range(30 * CONTROL_HZ):
        t = k / CONTROL_HZ
        T_world_body = transform_from_pose(state["x"], state["q"])  # true attitude, xyzw
        R = T_world_body[:3, :3]
        if k % (CONTROL_HZ // CAMERA_HZ) == 0:  # a camera frame: one pilot call
            depth = render_depth(world, T_world_body @ cam.T_body_camera, camera)  # metres, NaN invalid
            now = VehicleState(position=state["x"], velocity=state["v"], yaw=float(np.arctan2(R[1, 0], R[0, 0])))
            step = pilot.step(t, now, GOAL, depth, K=cam.K, T_world_body=T_world_body)
            reference = step.reference
            if step.status == "reached":  # hold at the goal: the reference ends there at rest
                break
            if step.status in ("braking", "blocked"):  # no way ahead, or lost inputs: it brakes, then holds
                print(f"t={t:5.2f} s  {step.status}: {step.reason}")
        sp = reference.sample(t)  # what a position / velocity / acceleration controller tracks
        flat = {"x": sp.position, "x_dot": sp.velocity, "x_ddot": sp.acceleration, "x_dddot": sp.jerk,
                "x_ddddot": sp.snap, "yaw": sp.yaw, "yaw_dot": sp.yaw_rate}
        state = vehicle.step(state, controller.update(t, state, flat), 1.0 / CONTROL_HZ)
        if world.signed_distance(state["x"][None])[0] < 0.3:
            raise SystemExit(f"collision at t={t:.2f} s, {np.round(state['x'], 2).tolist()}")
    print(f"{step.status} after {t:.1f} s at {np.round(state['x'], 2).tolist()} (goal {GOAL.tolist()})")


if __name__ == "__main__":
    fly()
