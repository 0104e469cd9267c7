"""mapkit.planner: ResNet-18 encoder and torchvision mapping, preprocessing, PlannerNet, loss terms."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from mapkit.esdf import EsdfMap, signed_distance
from mapkit.planner import (
    CameraInput,
    LossConfig,
    PlannerConfig,
    PlannerError,
    PlannerNet,
    ResNet18,
    body_to_world,
    candidate_loss,
    collision_labels,
    escape_cost,
    goal_cost,
    image_points,
    load_torchvision_state_dict,
    obstacle_cost,
    obstacle_penalty,
    planner_preset,
    preprocess_depth,
    sample_trajectory,
    smoothness_cost,
    time_cost,
    time_targets,
)
from mapkit.planner._model import choose_candidate
from mapkit.trajopt import allocate_times, min_snap

VOXEL = 0.2
ORIGIN = (-2.0, -4.0, -2.0)


@pytest.fixture(scope="module")
def box_map() -> EsdfMap:
    """Box world: a 1 m (x) × 2 m (y) pillar through the whole height, x in [4, 5], y in [-1, 1]."""
    occ = np.zeros((70, 40, 20), bool)  # x in [-2, 11.8], y in [-4, 3.8], z in [-2, 1.8]
    x = ORIGIN[0] + VOXEL * np.arange(70)
    y = ORIGIN[1] + VOXEL * np.arange(40)
    ix = (x >= 4.0 - 1e-9) & (x <= 5.0 + 1e-9)
    iy = (y >= -1.0 - 1e-9) & (y <= 1.0 + 1e-9)
    occ[np.ix_(ix, iy, np.ones(20, bool))] = True
    esdf = signed_distance(occ, voxel_size=VOXEL)
    return EsdfMap(esdf=esdf, esdf_raw=esdf, voxel_size=VOXEL, origin=ORIGIN)


def _inputs(B: int, cfg: PlannerConfig, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(B, 120, 200, generator=g) * 8 + 0.5
    depth[:, :15, :40] = float("nan")
    goal = torch.randn(B, 3, generator=g) * torch.tensor([1.0, 1.5, 0.2]) + torch.tensor([8.0, 0.0, 0.0])
    return depth, goal


# ----------------------------------------------------------------------------- network shapes
@pytest.mark.slow
@pytest.mark.parametrize("preset", ["cpu", "paper"])
def test_preset_shapes(preset):
    torch.manual_seed(0)
    cfg = planner_preset(preset)
    net = PlannerNet(cfg).eval()
    h, w = cfg.input_size
    B = 2 if preset == "cpu" else 1
    x = preprocess_depth(torch.rand(B, 240, 400) * 5 + 0.5, input_size=cfg.input_size, max_depth=cfg.max_depth)
    assert x.shape == (B, 2, h, w)
    with torch.no_grad():
        feat = net.encoder(x)
        out = net(x, torch.tensor([[6.0, 1.0, 0.0]]).expand(B, 3))
    assert feat.shape == (B, net.encoder.out_channels, math.ceil(h / 32), math.ceil(w / 32))
    assert net.encoder.out_channels == (512 if preset == "paper" else 128)
    assert out.keypoints.shape == (B, cfg.num_keypoints, 3)
    assert out.eta.shape == (B,) and bool(((out.eta > 0) & (out.eta < 1)).all())
    n = sum(p.numel() for p in net.parameters() if p.requires_grad)
    assert (15e6 < n < 30e6) if preset == "paper" else (0.5e6 < n < 2e6)


def test_config_checks_and_roundtrip():
    cfg = planner_preset("cpu", num_keypoints=4)
    assert PlannerConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(PlannerError, match="unknown planner preset"):
        planner_preset("huge")
    with pytest.raises(PlannerError, match="max_depth"):
        PlannerConfig(max_depth=0)
    with pytest.raises(PlannerError, match="unknown PlannerConfig fields"):
        PlannerConfig.from_dict({"bogus": 1})
    net = PlannerNet(cfg)
    with pytest.raises(PlannerError, match="preprocess"):
        net(torch.zeros(1, 1, 96, 160), torch.zeros(1, 3))


# ------------------------------------------------------------------------------ preprocessing
def test_preprocess_nan_and_mask():
    depth = torch.full((1, 64, 64), 4.0)
    depth[0, :32, :32] = float("nan")  # one whole quadrant invalid
    depth[0, 40, 40] = float("inf")
    depth[0, 41, 41] = 0.0
    depth[0, 50:, 50:] = 25.0  # beyond max_depth: clipped, still valid
    x = preprocess_depth(depth, input_size=(32, 32), max_depth=10.0)
    assert x.shape == (1, 2, 32, 32) and x.dtype == torch.float32
    assert bool(torch.isfinite(x).all())
    d, m = x[0, 0], x[0, 1]
    assert torch.all(m[:16, :16] == 0) and torch.all(d[:16, :16] == 0)  # invalid: mask 0, depth 0
    assert torch.all(m[16:, :16] == 1) and torch.allclose(d[16:, :16], torch.tensor(0.4))
    assert m[20, 20] == 0.5 and torch.isclose(d[20, 20], torch.tensor(0.4))  # half valid: depth not diluted
    assert torch.allclose(d[26:, 26:], torch.tensor(1.0))
    # bilinear upsampling path, and an unbatched image
    up = preprocess_depth(depth[0], input_size=(96, 96), max_depth=10.0)
    assert up.shape == (1, 2, 96, 96) and bool(torch.isfinite(up).all())
    assert torch.all(up[0, 1, :40, :40] == 0) and torch.all(up[0, 0, :40, :40] == 0)
    with pytest.raises(PlannerError, match="shape"):
        preprocess_depth(torch.zeros(1, 1, 2, 8, 8), input_size=(32, 32), max_depth=10.0)


def test_no_nan_reaches_the_network():
    torch.manual_seed(0)
    net = PlannerNet(planner_preset("cpu")).eval()
    seen = []
    net.encoder.conv1.register_forward_hook(lambda mod, inp, out: seen.append(bool(torch.isfinite(inp[0]).all())))
    depth = torch.full((1, 120, 200), float("nan"))
    depth[0, 60:, :] = 3.0
    with torch.no_grad():
        p = net.plan(depth, torch.tensor([[5.0, 0.0, 0.0]]))
    assert seen == [True]
    assert bool(torch.isfinite(p.keypoints).all()) and bool(torch.isfinite(p.eta).all())


# ------------------------------------------------------------------------- planning behaviour
def test_untrained_keypoints_near_straight_line_and_plan():
    torch.manual_seed(0)
    cfg = planner_preset("cpu")
    net = PlannerNet(cfg).eval()
    depth, goal = _inputs(4, cfg)
    v0 = torch.tensor([[0.5, 0.2, 0.0]]).expand(4, 3)
    with torch.no_grad():
        p = net.plan(depth, goal, start_velocity=v0)
    K = cfg.num_keypoints
    line = torch.arange(1, K + 1).reshape(1, K, 1) / K * goal.unsqueeze(1)
    assert float((p.keypoints - line).norm(dim=-1).max()) < 0.05  # by construction, centimetres
    assert float((p.keypoints[:, -1] - goal).norm(dim=-1).max()) < 0.05
    assert p.waypoints.shape == (4, K + 1, 3) and torch.all(p.waypoints[:, 0] == 0)
    assert torch.allclose(p.shares.sum(-1), torch.ones(4), atol=1e-5)
    assert torch.allclose(p.durations.sum(-1), p.total_time, atol=1e-4)
    L = (p.waypoints[:, 1:] - p.waypoints[:, :-1]).norm(dim=-1).sum(-1)
    # The speed profile: from the speed along the first segment up to cruise at `accel`, then to rest.
    first = p.waypoints[:, 1] / p.waypoints[:, 1].norm(dim=-1, keepdim=True)
    v_along = (v0 * first).sum(-1).double()
    L = L.double()
    peak = torch.sqrt(cfg.accel * L + v_along ** 2 / 2)
    up, down = (cfg.cruise_speed ** 2 - v_along ** 2) / (2 * cfg.accel), cfg.cruise_speed ** 2 / (2 * cfg.accel)
    expected = torch.where(up + down <= L, (cfg.cruise_speed - v_along) / cfg.accel + cfg.cruise_speed / cfg.accel
                           + (L - up - down) / cfg.cruise_speed, (2 * peak - v_along) / cfg.accel)
    floor = max(cfg.min_total_time, K * cfg.min_segment_time)
    assert torch.allclose(p.total_time.double(), expected.clamp(floor, cfg.max_total_time), rtol=1e-5)
    assert (p.durations >= cfg.min_segment_time - 1e-5).all()
    tr = p.trajectory
    assert torch.allclose(tr.position(0.0)[:, 0], torch.zeros(4, 3), atol=1e-4)
    assert torch.allclose(tr.derivative(0.0, 1)[:, 0], v0, atol=1e-4)
    assert torch.allclose(tr.position(tr.total_time.unsqueeze(-1))[:, 0], p.keypoints[:, -1], atol=1e-3)


@pytest.mark.slow
def test_seeded_determinism(box_map):
    def run():
        torch.manual_seed(123)
        cfg = planner_preset("cpu")
        net = PlannerNet(cfg)
        depth, goal = _inputs(2, cfg, seed=5)
        out = net(net.preprocess(depth), goal)
        loss, _ = candidate_loss(net, out, goal=goal, T_world_body=torch.eye(4, dtype=torch.float64).repeat(2, 1, 1),
                                 esdf_map=box_map)
        loss.backward()
        return out.keypoints.detach(), out.eta.detach(), loss.detach(), net.encoder.conv1.weight.grad.clone()

    a, b = run(), run()
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


# ------------------------------------------------------------------------------- gradients
@pytest.mark.slow
def test_gradients_reach_every_parameter_group(box_map):
    torch.manual_seed(0)
    cfg = planner_preset("cpu")
    net = PlannerNet(cfg).train()
    B = 3
    depth, _ = _inputs(B, cfg)
    goal = torch.tensor([[9.0, 0.3, 0.0], [8.0, -0.5, 0.2], [7.0, 2.5, 0.0]])
    T = torch.eye(4, dtype=torch.float64).repeat(B, 1, 1)
    T[:, :3, 3] = torch.tensor([-0.5, 0.2, 0.3], dtype=torch.float64)  # body 0.5 m behind the world origin
    out = net(net.preprocess(depth), goal)
    loss, terms = candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=box_map,
                                 start_velocity=torch.tensor([[1.0, 0.0, 0.0]]).expand(B, 3))
    assert loss.ndim == 0 and bool(torch.isfinite(loss))
    assert set(terms) >= {"obstacle", "goal", "smoothness", "escape", "time", "collision_rate", "total"}
    assert float(terms["collision_rate"]) > 0  # the first two fly straight through the pillar
    loss.backward()
    groups = {
        "encoder.conv1": net.encoder.conv1.weight,
        "encoder.layer4": net.encoder.layer4[1].conv2.weight,
        "goal_embed": net.goal_embed.weight,
        "head_conv": net.head_conv[0].weight,
        "keypoint_mlp": net.keypoint_mlp[0].weight,
        "keypoint_mlp.last": net.keypoint_mlp[-1].weight,
        "eta_mlp": net.eta_mlp[0].weight,
        "tan": net.tan.mlp[0].weight,
        "tan.last": net.tan.mlp[-1].weight,
    }
    for name, prm in groups.items():
        assert prm.grad is not None, name
        assert bool(torch.isfinite(prm.grad).all()), name
        assert float(prm.grad.abs().max()) > 0, name


def test_obstacle_penalty_monotone_with_gradient_far_away():
    d = torch.linspace(-2.0, 10.0, 1201, dtype=torch.float64, requires_grad=True)
    c = obstacle_penalty(d, robot_radius=0.3, softness=1.0)
    assert bool((c[1:] < c[:-1]).all())  # strictly decreasing
    (g,) = torch.autograd.grad(c.sum(), d)
    assert bool((g < 0).all())
    at3 = g[torch.argmin((d - 3.0).abs())]
    assert float(-at3) > 1e-2  # no plateau 3 m from obstacles
    c = c.detach()
    assert float(c[0]) > 20 * float(c[torch.argmin((d - 3.0).abs())])  # large inside


def test_obstacle_cost_on_map(box_map):
    # points on a line leaving the pillar's +y face (y = 1) at x = 4.5: 0.5 .. 3.5 m away
    ys = torch.tensor([1.5, 2.0, 2.5, 3.0, 3.5])
    pts = torch.stack([torch.full_like(ys, 4.5), ys, torch.zeros_like(ys)], -1).unsqueeze(1)  # (5, 1, 3)
    pts.requires_grad_(True)
    c = obstacle_cost(pts, box_map, robot_radius=0.3, softness=1.0)
    assert c.shape == (5,) and bool((c[1:] < c[:-1]).all())
    (g,) = torch.autograd.grad(c.sum(), pts)
    assert float(g[3, 0, 1]) < -1e-3  # 3 m away: the cost still falls moving away from the pillar
    inside = obstacle_cost(torch.tensor([[[4.5, 0.0, 0.0]]]), box_map)
    assert float(inside) > 5 * float(c[3].detach())
    far = obstacle_cost(torch.tensor([[[50.0, 0.0, 0.0]]]), box_map)  # outside the grid: clamped, finite
    assert bool(torch.isfinite(far).all())


def test_obstacle_cost_gradcheck_float64(box_map):
    g = torch.Generator().manual_seed(3)
    pts = (torch.rand(2, 6, 3, generator=g, dtype=torch.float64) * torch.tensor([8.0, 6.0, 2.0], dtype=torch.float64)
           + torch.tensor([0.5, -3.0, -1.0], dtype=torch.float64))
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: obstacle_cost(p, box_map, robot_radius=0.3, softness=0.7), (pts,), eps=1e-6, atol=1e-6, rtol=1e-4
    )


# ------------------------------------------------------------------------------ other terms
def _straight(y: float) -> torch.Tensor:
    wp = torch.tensor([[[0.0, y, 0.0], [3.0, y, 0.0], [6.0, y, 0.0], [9.0, y, 0.0]]])
    tr = min_snap(wp, torch.tensor([[1.5, 1.5, 1.5]]))
    return sample_trajectory(tr, samples_per_second=20.0)


def test_escape_labels_through_and_beside_box(box_map):
    through, beside, grazing = _straight(0.0), _straight(2.5), _straight(1.2)
    pts = torch.cat([through, beside, grazing])
    lab = collision_labels(pts, box_map, threshold=0.3)
    assert lab.tolist() == [True, False, True]  # 0.2 m from the face is inside the robot radius
    eta = torch.tensor([0.2, 0.2, 0.9], requires_grad=True)
    e = escape_cost(eta, lab)
    assert torch.allclose(e, torch.tensor([-math.log(0.2), -math.log(0.8), -math.log(0.9)]), atol=1e-5)
    e.sum().backward()
    assert eta.grad is not None and float(eta.grad[0]) < 0 < float(eta.grad[1])
    # from the logit: same values, and a saturated eta (float32 sigmoid == 1) still gets a gradient
    logit = torch.tensor([math.log(0.2 / 0.8), 30.0], requires_grad=True)
    lab2 = torch.tensor([True, False])
    e2 = escape_cost(torch.sigmoid(logit), lab2, logit=logit)
    assert torch.isclose(e2[0], torch.tensor(-math.log(0.2)), atol=1e-5) and torch.isclose(e2[1], torch.tensor(30.0))
    e2.sum().backward()
    assert float(logit.grad[1]) > 0.99


def _through_and_beside_the_box():
    """A two-candidate net's output toward (9, 0, 0), and candidates (1, 2, 5, 3): one straight through
    the box, one 1.5 m beside it all along; the body at the world origin."""
    cfg = PlannerConfig(num_candidates=2, depth_check=False)
    torch.manual_seed(0)
    net = PlannerNet(cfg)
    depth, _ = _inputs(1, cfg)
    goal = torch.tensor([[9.0, 0.0, 0.0]])
    out = net(net.preprocess(depth), goal)
    through = torch.tensor([[[1.8, 0.0, 0.0], [3.6, 0.0, 0.0], [5.4, 0.0, 0.0], [7.2, 0.0, 0.0], [9.0, 0.0, 0.0]]])
    cand = torch.stack([through, through + torch.tensor([0.0, 2.5, 0.0])], dim=1)
    return net, out, goal, cand, torch.eye(4, dtype=torch.float64)[None]


def test_eta_learns_each_candidates_collision_label(box_map):
    """candidate_loss: U_E is small exactly when each candidate's η matches its own collision label
    (the path into the box 1, the one beside it 0)."""
    net, out, goal, cand, T = _through_and_beside_the_box()
    label = [True, False]
    for guess, low in ((label, True), ([not label[0], label[1]], False), ([label[0], not label[1]], False)):
        logits = torch.tensor([[20.0 if g else -20.0 for g in guess]])
        o = dataclasses.replace(out, candidates=cand, keypoints=cand[:, 0], candidate_eta_logits=logits,
                                chosen=torch.zeros(1, dtype=torch.long))
        _, terms = candidate_loss(net, o, goal=goal, T_world_body=T, esdf_map=box_map)
        assert float(terms["collision_rate"]) == 1.0  # the chosen path runs into the box
        assert (float(terms["escape"]) < 1e-6) == low, guess


def test_image_points_of_a_wall() -> None:
    """A wall 4 m ahead: every point of the image lies on the body-frame plane x = 4, where the pinhole
    puts it (y = −4 · (u − cx) / fx); pixels without a return lie far away."""
    H, W = 96, 160
    K = np.array([[80.0, 0.0, W / 2 - 0.5], [0.0, 80.0, H / 2 - 0.5], [0.0, 0.0, 1.0]])
    T_body_camera = np.array([[0, 0, 1, 0.1], [-1, 0, 0, 0], [0, -1, 0, 0.05], [0, 0, 0, 1]], float)
    camera = CameraInput.from_calibration(K, W, H, T_body_camera)
    depth = torch.full((1, H, W), 0.4)  # depth / max_depth
    depth[0, :, :8] = 1.0  # the left columns: no return
    pts = image_points(depth, camera, max_depth=10.0, stride=2)
    assert pts.shape == (1, (H // 2) * (W // 2), 3)
    grid = pts.reshape(H // 2, W // 2, 3)
    assert float(grid[:, :4].abs().min()) > 1e5
    seen = grid[:, 4:]
    torch.testing.assert_close(seen[..., 0], torch.full_like(seen[..., 0], 4.1))
    u = torch.arange(8, W, 2, dtype=torch.float32)
    torch.testing.assert_close(seen[0, :, 1], -4.0 * (u - K[0, 2]) / K[0, 0])
    v = torch.arange(0, H, 2, dtype=torch.float32)
    torch.testing.assert_close(seen[:, 0, 2], 0.05 - 4.0 * (v - K[1, 2]) / K[1, 1])


def test_smoothness_goal_and_time_terms():
    goal = torch.tensor([[6.0, 2.0, 1.0]])
    start = torch.zeros(1, 3)
    line = torch.linspace(0, 1, 11).reshape(1, 11, 1) * goal.unsqueeze(1)
    assert float(smoothness_cost(line, start, goal)) < 1e-5
    bent = line.clone()
    bent[0, 5, 2] += 1.0
    assert float(smoothness_cost(bent, start, goal)) > 0.5
    assert torch.allclose(goal_cost(torch.tensor([[3.0, 4.0, 0.0]]), torch.zeros(1, 3)), torch.tensor([5.0]))
    # U_T target: the gradient allocation's shares
    wp = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [4.0, 1.0, 0], [5.0, 1.5, 0], [8.0, 0, 0]]])
    tot = torch.tensor([5.0])
    tgt = time_targets(wp, total_time=tot, max_iters=100, rel_tol=1e-9)
    ref = allocate_times(wp.double(), "gradient", total_time=tot.double(), max_iters=100, rel_tol=1e-9)
    assert torch.allclose(tgt, (ref / ref.sum(-1, keepdim=True)).float(), atol=1e-6)
    assert float(time_cost(tgt, tgt)) == 0.0
    shares = torch.full((1, 4), 0.25, requires_grad=True)
    time_cost(shares, tgt).sum().backward()
    assert float(shares.grad.abs().max()) > 0


def test_body_to_world():
    T = torch.eye(4, dtype=torch.float64).unsqueeze(0)
    T[0, :3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)  # yaw +90°
    T[0, :3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    out = body_to_world(torch.tensor([[[1.0, 0.0, 0.0]]]), T)
    assert torch.allclose(out, torch.tensor([[[1.0, 3.0, 3.0]]]))
    with pytest.raises(PlannerError, match="T_world_body"):
        body_to_world(torch.zeros(2, 4, 3), T)


def test_loss_config_checks():
    with pytest.raises(PlannerError, match="robot_radius"):
        LossConfig(robot_radius=-0.1)
    with pytest.raises(PlannerError, match="obstacle_softness"):
        LossConfig(obstacle_softness=0.0)


# ----------------------------------------------------------------------- torchvision weights
def _torchvision_keys_and_shapes() -> dict[str, tuple[int, ...]]:
    """torchvision resnet18().state_dict() names and shapes, written out from the architecture."""
    shapes: dict[str, tuple[int, ...]] = {}

    def bn(prefix: str, c: int) -> None:
        for s in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{s}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    shapes["conv1.weight"] = (64, 3, 7, 7)
    bn("bn1", 64)
    prev = 64
    for layer, c in zip((1, 2, 3, 4), (64, 128, 256, 512), strict=True):
        for block in (0, 1):
            p = f"layer{layer}.{block}"
            cin = prev if block == 0 else c
            shapes[f"{p}.conv1.weight"] = (c, cin, 3, 3)
            bn(f"{p}.bn1", c)
            shapes[f"{p}.conv2.weight"] = (c, c, 3, 3)
            bn(f"{p}.bn2", c)
            if layer > 1 and block == 0:
                shapes[f"{p}.downsample.0.weight"] = (c, prev, 1, 1)
                bn(f"{p}.downsample.1", c)
        prev = c
    shapes["fc.weight"] = (1000, 512)
    shapes["fc.bias"] = (1000,)
    return shapes


def test_torchvision_key_mapping():
    shapes = _torchvision_keys_and_shapes()
    assert len(shapes) == 122
    g = torch.Generator().manual_seed(0)
    sd = {
        k: (torch.tensor(7, dtype=torch.int64) if k.endswith("num_batches_tracked")
            else torch.rand(s, generator=g) + 0.1)
        for k, s in shapes.items()
    }
    model = ResNet18(in_channels=2, width=1.0)
    assert set(model.state_dict()) == set(shapes) - {"fc.weight", "fc.bias"}
    ignored = load_torchvision_state_dict(model, sd)
    assert ignored == ["fc.bias", "fc.weight"]
    w = model.conv1.weight
    assert torch.allclose(w[:, 0], sd["conv1.weight"].sum(1))
    assert torch.all(w[:, 1] == 0)  # the mask channel starts unused
    own = model.state_dict()
    for k in ("bn1.running_var", "layer1.0.conv1.weight", "layer3.1.bn2.bias", "layer4.0.downsample.0.weight",
              "layer2.0.downsample.1.running_mean", "layer4.1.bn1.num_batches_tracked"):
        assert torch.equal(own[k], sd[k]), k
    # through PlannerNet (paper preset encoder), with a DataParallel-style prefix
    net = PlannerNet(planner_preset("paper"))
    load_torchvision_state_dict(net.encoder, {f"module.{k}": v for k, v in sd.items()})
    assert torch.equal(net.encoder.layer2[1].conv2.weight, sd["layer2.1.conv2.weight"])
    # errors: wrong width, missing key, wrong shape
    with pytest.raises(PlannerError, match="width"):
        load_torchvision_state_dict(ResNet18(width=0.25), sd)
    bad = dict(sd)
    del bad["layer3.0.bn1.weight"]
    with pytest.raises(PlannerError, match="missing"):
        load_torchvision_state_dict(ResNet18(), bad)
    bad = dict(sd)
    bad["layer1.0.conv2.weight"] = torch.zeros(64, 64, 5, 5)
    with pytest.raises(PlannerError, match=r"layer1.0.conv2.weight"):
        load_torchvision_state_dict(ResNet18(), bad)


# ------------------------------------------------------------------------- several candidate paths
def test_anchors_detour_both_ways_and_end_at_the_goal():
    cfg = planner_preset("cpu", num_candidates=6)
    net = PlannerNet(cfg).eval()
    goal = torch.tensor([[6.0, 0.0, 0.0], [0.0, 3.0, 0.5]])
    anchors = net.anchor_paths(goal)
    assert anchors.shape == (2, 6, cfg.num_keypoints, 3)
    torch.testing.assert_close(anchors[:, :, -1], goal[:, None].expand(2, 6, 3), atol=1e-6, rtol=0)
    mid = anchors[0, :, cfg.num_keypoints // 2]
    # Straight, a climb, then left/right pairs mirrored about the goal line (y for a goal along x).
    assert float(mid[0, 1].abs()) < 1e-6 and float(mid[1, 2]) > 0.5
    torch.testing.assert_close(mid[2, 1], -mid[3, 1])
    assert float(mid[4, 1]) > float(mid[2, 1]) > 0.5
    # For a goal along +y the lateral direction is x (left of +y is -x).
    assert float(anchors[1, 2, 2, 0]) < -0.1
    # The untrained net's candidates lie on their anchors (centimetres).
    depth, _ = _inputs(2, cfg)
    with torch.no_grad():
        out = net(net.preprocess(depth), goal)
    assert out.candidates.shape == (2, 6, cfg.num_keypoints, 3) and out.scores.shape == (2, 6)
    assert float((out.candidates - anchors).norm(dim=-1).max()) < 0.1
    assert torch.equal(out.keypoints, out.candidates[torch.arange(2), out.chosen])


def _six_candidates() -> tuple[PlannerConfig, PlannerNet, torch.Tensor, torch.Tensor]:
    """A net with six candidates, two goals and candidates (2, 6, K, 3) near its anchors."""
    cfg = planner_preset("cpu", num_candidates=6)
    torch.manual_seed(0)
    net = PlannerNet(cfg).eval()
    goal = torch.tensor([[6.0, 0.0, 0.0], [2.0, 3.0, 0.5]])
    return cfg, net, goal, net.anchor_paths(goal) + 0.1 * torch.randn(2, 6, cfg.num_keypoints, 3)


def test_widened_candidates_scale_the_detour_and_are_judged_like_the_trained_ones():
    cfg, net, goal, cands = _six_candidates()
    K = cfg.num_keypoints
    wide = net.widened(cands, goal, (1.5, 2.5))
    assert wide.shape == (2, 18, K, 3)
    assert torch.equal(wide[:, :6], cands)
    line = net.straight_line(goal)[:, None, :-1]
    for i, f in enumerate((1.5, 2.5), start=1):
        torch.testing.assert_close(wide[:, 6 * i:6 * (i + 1), :-1] - line, f * (cands[:, :, :-1] - line))
        assert torch.equal(wide[:, 6 * i:6 * (i + 1), -1], cands[:, :, -1])  # where the path ends: kept
    for bad in ((0.0,), (float("nan"),), (-2.0,)):
        with pytest.raises(PlannerError, match="widening factors"):
            net.widened(cands, goal, bad)
    depth, _ = _inputs(2, cfg)
    with torch.no_grad():
        x = net.preprocess(depth)
        plain = net(x, goal)
        out = net(x, goal, widen=(1.5, 2.5))
        planned = net.plan(depth, goal, widen=(1.5, 2.5))
    assert out.candidates.shape == (2, 18, K, 3) and out.scores.shape == (2, 18)
    # the judge reads each candidate alone: adding widened ones changes nothing about the trained ones
    torch.testing.assert_close(out.scores[:, :6], plain.scores)
    torch.testing.assert_close(out.candidate_eta_logits[:, :6], plain.candidate_eta_logits)
    torch.testing.assert_close(out.candidates[:, 6:], net.widened(plain.candidates, goal, (1.5, 2.5))[:, 6:])
    assert torch.equal(out.chosen, choose_candidate(out.scores, out.candidate_eta_logits))
    assert torch.equal(out.keypoints, out.candidates[torch.arange(2), out.chosen])
    assert torch.equal(planned.widened, out.chosen >= 6)


def test_shifted_candidates_move_every_candidate_sideways_along_the_anchor_bump():
    cfg, net, goal, cands = _six_candidates()
    K = cfg.num_keypoints
    moved = net.shifted(cands, goal, (-0.6, 0.3))
    assert moved.shape == (2, 18, K, 3) and torch.equal(moved[:, :6], cands)
    bump = torch.sin(torch.pi * torch.arange(1, K + 1) / K)  # zero at the last key-point
    scale = (goal.norm(dim=-1) / 6.0).clamp(0.3, 1.5)
    horizontal = torch.nn.functional.normalize(goal[:, :2], dim=-1)
    left = torch.stack([-horizontal[:, 1], horizontal[:, 0], torch.zeros(2)], dim=-1)  # up × goal, level
    for i, s in enumerate((-0.6, 0.3), start=1):
        expected = s * scale[:, None, None] * bump[None, :, None] * left[:, None, :]  # (2, K, 3)
        torch.testing.assert_close(moved[:, 6 * i:6 * (i + 1)] - cands, expected[:, None].expand(2, 6, K, 3))
    with pytest.raises(PlannerError, match="candidate shifts"):
        net.shifted(cands, goal, (float("inf"),))
    depth, _ = _inputs(2, cfg)
    with torch.no_grad():
        plain = net(net.preprocess(depth), goal, widen=(1.5,))
        out = net(net.preprocess(depth), goal, widen=(1.5,), shift=(-0.3, 0.3))
        planned = net.plan(depth, goal, widen=(1.5,), shift=(-0.3, 0.3))
    # trained, widened, then all twelve of those shifted by each; the judge reads each alone
    assert out.candidates.shape == (2, 36, K, 3)
    torch.testing.assert_close(out.scores[:, :12], plain.scores)
    torch.testing.assert_close(out.candidates, net.shifted(plain.candidates, goal, (-0.3, 0.3)))
    assert torch.equal(planned.shifted, out.chosen >= 12)
    assert torch.equal(planned.widened, out.chosen % 12 >= 6)


@pytest.mark.slow
def test_winner_takes_all_keeps_the_detour_that_wins(box_map):
    """A pillar right on the line: the straight candidate collides, a detour does not; the loss
    trains the score towards a free detour and the chosen path clears the pillar after training."""
    torch.manual_seed(0)
    from mapkit.planner import candidate_loss

    net = PlannerNet(planner_preset("cpu", num_candidates=4, input_size=(32, 48), encoder_width=0.125))
    depth = torch.full((4, 48, 64), 5.0)
    goal = torch.tensor([[8.0, 0.0, 0.0]]).expand(4, 3)
    T = torch.eye(4).expand(4, 4, 4).clone()
    cfg = LossConfig(obstacle_softness=0.3)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(60):
        out = net(net.preprocess(depth), goal)
        loss, terms = candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=box_map, config=cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(terms["winner_collision_rate"]) == 0.0
    assert float(terms["collision_rate"]) == 0.0  # the chosen path clears it too (left or right: a tie)
    assert int(out.chosen[0]) != 0  # not the straight anchor


def test_anchor_pull_adds_the_losers_squared_distance_from_their_anchors(box_map):
    """Every candidate offset from its anchor by the same c: the pull adds exactly β‖c‖² per sample,
    whichever candidate wins; a negative weight is refused."""
    from mapkit.planner import candidate_loss

    net = PlannerNet(planner_preset("cpu", num_candidates=4, input_size=(32, 48), encoder_width=0.125))
    c = torch.tensor([0.3, -0.4, 0.2])
    with torch.no_grad():
        last = net.keypoint_mlp[-1]
        last.weight.zero_()
        last.bias.copy_(c.repeat(4 * net.config.num_keypoints))
    depth = torch.full((2, 48, 64), 5.0)
    goal = torch.tensor([[8.0, 0.0, 0.0], [6.0, 2.0, 0.5]])
    T = torch.eye(4).expand(2, 4, 4).clone()
    with torch.no_grad():
        out = net(net.preprocess(depth), goal)
        loss = {beta: candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=box_map,
                                     config=LossConfig(candidate_anchor_pull=beta))[0] for beta in (0.0, 0.5)}
    torch.testing.assert_close(loss[0.5] - loss[0.0], 0.5 * c.square().sum(), rtol=1e-5, atol=1e-6)
    with pytest.raises(PlannerError, match="candidate_anchor_pull"):
        LossConfig(candidate_anchor_pull=-1.0)


@pytest.fixture(scope="module")
def wall_map() -> EsdfMap:
    """0.1 m voxels over x in [-2, 7.9], y in [-6, 5.9], z in [-1, 1.9]: a wall across x = 3 (0.2 m
    thick, the whole height) from y = -6 up to y = 2; open beyond."""
    origin, shape = (-2.0, -6.0, -1.0), (100, 120, 30)
    x, y = (origin[a] + 0.1 * np.arange(shape[a]) for a in range(2))
    occ = np.zeros(shape, bool)
    occ[np.ix_((x > 2.85) & (x < 3.15), y < 2.0, np.ones(shape[2], bool))] = True
    esdf = signed_distance(occ, voxel_size=0.1, max_dist=20.0)
    return EsdfMap(esdf=esdf, esdf_raw=esdf, voxel_size=0.1, origin=origin)


def test_the_collision_penalty_lets_a_clear_candidate_win(wall_map):
    """Toward a goal straight behind the wall every candidate but the widest crosses it; the
    cheapest path (by obstacle, goal and smoothness cost) is one that crosses, so without the
    penalty the winner collides (with this seed's time allocation), and with it the clear one wins."""
    torch.manual_seed(0)
    net = PlannerNet(planner_preset("cpu", num_candidates=8, input_size=(32, 48), encoder_width=0.125))
    with torch.no_grad():
        net.keypoint_mlp[-1].weight.zero_()
        net.keypoint_mlp[-1].bias.zero_()
    depth = torch.full((1, 48, 64), 5.0)
    goal = torch.tensor([[6.0, 0.0, 0.0]])
    T = torch.eye(4)[None].clone()
    T[0, :3, 3] = torch.tensor([0.0, 0.5, 0.5])
    runs = {}
    with torch.no_grad():
        out = net(net.preprocess(depth), goal)
        for kappa in (0.0, 10.0):
            runs[kappa] = candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=wall_map,
                                         config=LossConfig(obstacle_softness=0.3, winner_collision_penalty=kappa))[1]
    assert float(runs[0.0]["winner_collision_rate"]) == 1.0
    assert float(runs[10.0]["winner_collision_rate"]) == 0.0


def test_depth_margins_against_a_wall_in_front():
    """Depth 4 m everywhere (a wall facing the camera): path points before it are in view with a
    positive margin, points behind it negative, points behind the camera out of view; a pole beside
    the path counts only when within the robot's disc."""
    from mapkit.planner import CameraInput, depth_margins, preprocess_depth
    from mapkit.sim import CameraModel, camera_extrinsics

    cam = CameraModel(width=160, height=120)
    T_bl, T_lo = camera_extrinsics()
    T_bc = torch.from_numpy(T_bl @ T_lo)
    calib = CameraInput.from_calibration(torch.from_numpy(cam.K), 160, 120, T_bc)
    depth = torch.full((1, 120, 160), 4.0)  # a wall 4 m in front of the camera
    x = preprocess_depth(depth, input_size=(96, 160), max_depth=10.0)
    K = 5
    straight = torch.linspace(1.2, 6.0, K)[:, None] * torch.tensor([1.0, 0.0, 0.0])
    behind = torch.linspace(-1.0, -5.0, K)[:, None] * torch.tensor([1.0, 0.0, 0.0])
    cand = torch.stack([straight, behind])[None]  # (1, 2, K, 3)
    f = depth_margins(cand, x, calib, max_depth=10.0).reshape(1, 2, -1, 2)
    xs = torch.cat([torch.zeros(1), straight[:, 0]])
    pts_x = torch.stack([xs[i] + (xs[i + 1] - xs[i]) * j / 3 for i in range(K) for j in (1, 2, 3)])
    in_view, margin = f[0, 0, :, 0], f[0, 0, :, 1]
    assert bool(in_view.all())
    z_camera = pts_x - float(T_bc[0, 3])  # the camera sits 8 cm ahead of the body origin
    np.testing.assert_allclose(margin.numpy(), ((4.0 - z_camera) / 2).clamp(-1, 1).numpy(), atol=0.03)
    assert not bool(f[0, 1, :, 0].any()) and not bool(f[0, 1, :, 1].any())
    # A pole 0.25 m beside the path at 2 m: seen by the point at 2 m, not by a point 1 m further aside.
    depth = torch.full((1, 120, 160), 9.0)
    u_pole = int(round(cam.K[0, 2] - cam.K[0, 0] * 0.25 / 2.0))  # 0.25 m to the left at 2 m depth
    depth[:, :, u_pole - 1 : u_pole + 2] = 2.0
    x = preprocess_depth(depth, input_size=(96, 160), max_depth=10.0)
    near = torch.tensor([[[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [4.0, 0.0, 0.0], [5.0, 0.0, 0.0]]])
    far_aside = near + torch.tensor([0.0, -1.0, 0.0])
    f = depth_margins(torch.stack([near, far_aside], dim=1), x, calib, max_depth=10.0).reshape(1, 2, -1, 2)
    at_2m = 5  # the sixth point (2 m along the path, last of the second segment)
    assert float(f[0, 0, at_2m, 1]) < 0.05 and float(f[0, 1, at_2m, 1]) > 1.0 - 1e-6


@pytest.mark.parametrize("shape", [(1, 96, 160), (3, 95, 161), (2, 33, 48)])
def test_nearest_depth_pyramid_cpu_path_equals_pooling_and_brute_force(shape):
    """The numpy minima used on the CPU equal torch's pooling exactly (odd and even sizes), and each
    full-resolution level is the plain minimum over its square window (a brute-force check)."""
    from mapkit.planner._depthcheck import WINDOWS, _pyramid_torch, nearest_depth_pyramid

    g = torch.Generator().manual_seed(3)
    B, h, w = shape
    x = torch.stack([torch.rand(B, h, w, generator=g), (torch.rand(B, h, w, generator=g) > 0.2).float()], dim=1)
    fast = nearest_depth_pyramid(x)
    level = torch.where(x[:, 1:2] > 0.5, x[:, :1], torch.ones_like(x[:, :1]))
    assert fast.shape == (B, len(WINDOWS), h, w) and fast.dtype == torch.float32
    assert torch.equal(fast, _pyramid_torch(level))
    padded = np.pad(level[:, 0].numpy(), ((0, 0), (1, 1), (1, 1)), constant_values=np.inf)
    brute = np.min([padded[:, 1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    np.testing.assert_array_equal(fast[:, 0].numpy(), brute)  # window 3


def test_prepare_inference_freezes_the_encoder_without_changing_the_plan():
    """The frozen encoder (ONNX Runtime) serves single-image plans with the eager encoder's
    features (float rounding), is not part of the state dict, and is dropped by train(); batches
    keep the eager one."""
    cfg = planner_preset("cpu")
    torch.manual_seed(0)
    net = PlannerNet(cfg).eval()
    depth, goal = _inputs(2, cfg)
    x = net.preprocess(depth)
    with torch.inference_mode():
        eager = net.encoder(x[:1])
        before = net(x[:1], goal[:1]).keypoints
    keys = set(net.state_dict())
    assert net.prepare_inference() is net and not net.training
    if net._frozen_encoder is None:
        pytest.skip("ONNX Runtime cannot freeze the encoder here")
    assert net.frozen_runtime == "onnxruntime"
    with torch.inference_mode():
        frozen, pyramid = net._frozen_encoder.module(x[:1])
        after = net(x[:1], goal[:1]).keypoints
        features, none = net._encode(x)  # a batch of two: the eager encoder
        assert torch.equal(features, net.encoder(x)) and none is None
    assert pyramid is None  # one candidate, no depth check: no pyramid to make
    assert not torch.equal(frozen, eager)  # really another implementation ...
    torch.testing.assert_close(frozen, eager, atol=1e-4, rtol=1e-4)  # ... of the same features
    torch.testing.assert_close(after, before, atol=1e-4, rtol=1e-4)
    assert set(net.state_dict()) == keys
    net.train()
    assert net._frozen_encoder is None and net.frozen_runtime is None


def test_onnx_runtime_makes_the_exact_pyramid_of_a_model_that_checks_its_paths():
    """With several candidates checked against the depth image, ONNX Runtime computes the nearest-depth
    pyramid with the features: exactly the numpy one (min-pooling has no rounding), and the forward
    pass uses it (the numpy one is not called)."""
    from mapkit.planner import CameraInput, _model
    from mapkit.planner._depthcheck import nearest_depth_pyramid

    cfg = planner_preset("cpu", num_candidates=6, depth_check=True)
    torch.manual_seed(0)
    net = PlannerNet(cfg).prepare_inference()
    if net.frozen_runtime != "onnxruntime":
        pytest.skip("ONNX Runtime cannot run the encoder here")
    depth, goal = _inputs(1, cfg)
    depth[0, 40:60, 60:100] = 1.5  # something near in view
    depth[0, :5] = float("nan")  # and pixels without a return
    x = net.preprocess(depth)
    camera = CameraInput.from_calibration(np.array([[80.0, 0, 80], [0, 80, 48], [0, 0, 1]]), 160, 96, np.eye(4))
    with torch.inference_mode():
        _features, made = net._frozen_encoder.module(x)
        assert made is not None and torch.equal(made, nearest_depth_pyramid(x))
        calls = []
        original = _model.nearest_depth_pyramid
        _model.nearest_depth_pyramid = lambda *a: calls.append(1) or original(*a)  # type: ignore[assignment]
        try:
            out = net(x, goal, camera=camera)
        finally:
            _model.nearest_depth_pyramid = original
    assert not calls and torch.equal(out.pyramid, made)


def test_a_second_goal_from_the_same_image_reuses_its_encoding():
    """``image=`` from an earlier pass gives exactly the output of a fresh pass for the new goal."""
    cfg = planner_preset("cpu")
    torch.manual_seed(0)
    net = PlannerNet(cfg).eval()
    depth, goal = _inputs(2, cfg)
    x = net.preprocess(depth[:1])
    cam = None
    if cfg.depth_check and cfg.num_candidates > 1:
        from mapkit.planner import CameraInput
        cam = CameraInput.from_calibration(torch.tensor([[100.0, 0, 100], [0, 100, 60], [0, 0, 1]]), 200, 120,
                                           torch.tensor([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]]))
    with torch.inference_mode():
        first = net(x, goal[:1], camera=cam)
        assert first.image is not None and first.image.x is x
        fresh = net(x, goal[1:], camera=cam)
        reused = net(x, goal[1:], camera=cam, image=first.image)
    for name in ("keypoints", "eta_logit", "candidates"):
        assert torch.equal(getattr(reused, name), getattr(fresh, name))
