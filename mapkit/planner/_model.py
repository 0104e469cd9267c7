"""The planner network: depth + goal → key-points and collision probability η, and the trajectory
through those key-points (Time Allocation Net + differentiable minimum snap)."""

from __future__ import annotations

import dataclasses
import logging
import math
import warnings
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from mapkit.planner._config import PlannerConfig
from mapkit.planner._depthcheck import (
    FEATURES_PER_POINT,
    POINTS_PER_SEGMENT,
    CameraInput,
    _pyramid_torch,
    depth_margins,
    nearest_depth_pyramid,
)
from mapkit.planner._errors import PlannerError
from mapkit.planner._flown import FLOWN_FEATURES, arclength_points, flown_features
from mapkit.planner._resnet import ResNet18
from mapkit.planner._timing import plan_timing
from mapkit.trajopt import TimeAllocationNet, TimeAllocationNetConfig, Trajectory, min_snap

log = logging.getLogger(__name__)


def choose_candidate(scores: torch.Tensor, eta_logits: torch.Tensor) -> torch.Tensor:
    """(B,) index of the best-scored candidate (scores (B, M)) among those the collision head expects
    to be free (η < 0.5); the best of all when it expects every one to collide (then η gates the plan)."""
    free = eta_logits < 0
    masked = torch.where(free, scores, torch.full_like(scores, -torch.inf))
    return torch.where(free.any(dim=1), masked.argmax(dim=1), scores.argmax(dim=1))


# ------------------------------------------------------------------------------ preprocessing
def preprocess_depth(depth: torch.Tensor, *, input_size: tuple[int, int], max_depth: float) -> torch.Tensor:
    """Depth images in metres → the network input (B, 2, h, w), float32.

    Args:
        depth: (B, H, W) or (H, W) float metres along the optical axis; NaN (and any non-finite or
            non-positive value) is invalid.
        input_size: (h, w) output pixels.
        max_depth: metres; valid depth is clipped to [0, max_depth] before resizing.

    Returns:
        (B, 2, h, w) float32, no NaN. Channel 0: depth / max_depth in [0, 1], averaged over the valid
        source pixels only (0 where none contributes: invalid depth is never made up). Channel 1: the
        fraction of valid source pixels behind each output pixel. Resized by "area" where the image
        shrinks along both axes, else bilinear.
    """
    if not isinstance(depth, torch.Tensor):
        raise PlannerError(f"depth must be a torch.Tensor (B, H, W) in metres, got {type(depth).__name__}")
    if depth.ndim == 2:
        depth = depth.unsqueeze(0)
    if depth.ndim != 3:
        raise PlannerError(f"depth must have shape (B, H, W) or (H, W), got {tuple(depth.shape)}")
    if not depth.is_floating_point():
        raise PlannerError(f"depth must be float metres (NaN invalid), got {depth.dtype}")
    if not max_depth > 0:
        raise PlannerError(f"max_depth must be > 0 metres, got {max_depth}")
    h, w = (int(v) for v in input_size)
    d = depth.to(torch.float32)
    valid = torch.isfinite(d) & (d > 0)
    filled = torch.where(valid, d.clamp(max=float(max_depth)), torch.zeros_like(d)) / float(max_depth)
    x = torch.stack([filled, valid.to(torch.float32)], dim=1)  # (B, 2, H, W)
    H, W = d.shape[-2:]
    if (H, W) != (h, w):
        if H >= h and W >= w:
            x = F.interpolate(x, size=(h, w), mode="area")
        else:
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)
    num, mask = x[:, 0], x[:, 1].clamp(0.0, 1.0)
    has = mask > 1e-6
    depth_n = torch.where(has, num / torch.where(has, mask, torch.ones_like(mask)), torch.zeros_like(num))
    mask = torch.where(has, mask, torch.zeros_like(mask))
    return torch.stack([depth_n.clamp(0.0, 1.0), mask], dim=1)


# ------------------------------------------------------------------------------- outputs
@dataclass
class PlannerOutput:
    """What :meth:`PlannerNet.forward` predicts (body frame FLU, metres)."""

    keypoints: torch.Tensor
    """(B, K, 3) key-points; the last one is the trajectory's end point."""
    eta: torch.Tensor
    """(B,) collision probability in (0, 1); execute the plan only when eta < 0.5."""
    eta_logit: torch.Tensor
    """(B,) the logit of ``eta`` (for numerically exact BCE)."""
    candidates: torch.Tensor | None = None
    """(B, M, K, 3) every candidate path (M = ``num_candidates``, then any widened ones: ``forward``'s
    ``widen``, then all of those shifted sideways: ``shift``); ``keypoints`` is the chosen one."""
    candidate_eta_logits: torch.Tensor | None = None
    """(B, M) collision logits of each candidate."""
    scores: torch.Tensor | None = None
    """(B, M) score logits; the chosen candidate is their argmax (None when M = 1)."""
    chosen: torch.Tensor | None = None
    """(B,) int64 index of the chosen candidate."""
    pyramid: torch.Tensor | None = None
    """(B, L, h, w) the nearest-depth pyramid the judge read (``depth_check``), for later checks."""
    image: ImageFeatures | None = None
    """What the pass computed from the depth alone: pass it back as ``image=`` to plan another goal
    from the same image without encoding it again."""


@dataclass(frozen=True)
class ImageFeatures:
    """Per-image results of a forward pass (one image, ``image_index`` None)."""

    x: torch.Tensor
    """(1, 2, h, w) the preprocessed depth."""
    features: torch.Tensor
    """(1, C, h/32, w/32) the encoder's feature map."""
    pyramid: torch.Tensor | None
    """(1, L, h, w) the nearest-depth pyramid (``depth_check``), else None."""


@dataclass
class Plan:
    """A planned trajectory in the body frame at planning time (origin = the robot)."""

    trajectory: Trajectory
    """Minimum-snap trajectory through ``waypoints`` (batched, B elements), body frame."""
    waypoints: torch.Tensor
    """(B, K+1, 3): the origin, then the K key-points."""
    shares: torch.Tensor
    """(B, K) Time Allocation Net shares of the total time (softmax; sum to 1)."""
    durations: torch.Tensor
    """(B, K) segment durations, seconds (= shares × total_time)."""
    total_time: torch.Tensor
    """(B,) seconds, from the speed heuristic (no gradient)."""
    start: torch.Tensor
    """(B, 3, 3) start velocity / acceleration / jerk rows passed to min_snap."""
    keypoints: torch.Tensor
    """(B, K, 3) the predicted key-points (= waypoints[:, 1:])."""
    end_speed: torch.Tensor | None = None
    """(B,) m/s at the last key-point (0 = rest)."""
    min_segment: float = 0.0
    """Seconds every segment got at least; ``shares`` split the time above these minima."""
    eta: torch.Tensor | None = None
    """(B,) collision probability when the plan came from :meth:`PlannerNet.plan`, else None."""
    eta_logit: torch.Tensor | None = None
    """(B,) its logit, likewise."""
    widened: torch.Tensor | None = None
    """(B,) bool: the chosen candidate is a widened one (``widen``), when from :meth:`PlannerNet.plan`."""
    shifted: torch.Tensor | None = None
    """(B,) bool: the chosen candidate is a shifted one (``shift``), when from :meth:`PlannerNet.plan`."""


# ----------------------------------------------------------------------------------- network
@dataclass(frozen=True)
class _FrozenEncoder:
    """The encoder frozen for one input shape (not a submodule, not in the state dict): ``module`` maps a
    (1, 2, h, w) tensor to its features and the nearest-depth pyramid where the runtime computes it."""

    module: Any
    shape: tuple[int, ...]
    dtype: torch.dtype


class _EncoderGraph(nn.Module):
    """What ONNX Runtime runs: the encoder and, for a model with ``depth_check``, the nearest-depth pyramid."""

    def __init__(self, encoder: nn.Module, pyramid: bool) -> None:
        super().__init__()
        self.encoder, self.pyramid = encoder, pyramid

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if not self.pyramid:
            return (self.encoder(x),)
        level = torch.where(x[:, 1:2] > 0.5, x[:, :1], torch.ones_like(x[:, :1]))
        return self.encoder(x), _pyramid_torch(level)


class _OrtEncoder:
    """The encoder (and the pyramid) exported to ONNX and run by ONNX Runtime on one thread."""

    def __init__(self, encoder: nn.Module, example: torch.Tensor, pyramid: bool) -> None:
        import tempfile
        from pathlib import Path

        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.log_severity_level = 3
        with tempfile.TemporaryDirectory(prefix="mapkit-encoder-") as tmp:
            graph = Path(tmp) / "encoder.onnx"
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the TorchScript-based exporter's deprecation notices
                torch.onnx.export(_EncoderGraph(encoder, pyramid), (example,), graph, dynamo=False, opset_version=17,
                                  input_names=["x"], output_names=["features", "pyramid"][:1 + int(pyramid)])
            self.session = ort.InferenceSession(str(graph), options, providers=["CPUExecutionProvider"])

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        out = self.session.run(None, {"x": x.detach().contiguous().numpy()})
        return torch.from_numpy(out[0]), torch.from_numpy(out[1]) if len(out) > 1 else None


def _mlp(dims: list[int], activation: str = "relu") -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(dims) - 1):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2:
            layers.append(nn.ReLU(inplace=True) if activation == "relu" else nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


class PlannerNet(nn.Module):
    """Depth image + goal → K key-points and a collision probability η (the paper's upper level),
    plus its Time Allocation Net.

    Layers: ``encoder`` (:class:`ResNet18`, (B, 2, h, w) → (B, C, h/32, w/32)); ``goal_embed`` (Linear
    3 → E of goal / max_depth, concatenated over the feature map); ``head_conv`` (two 3×3 convs, average
    pooled to ``pooled_size``, flattened to F); ``keypoint_mlp`` (F → 3KM offsets); with one candidate
    ``eta_mlp`` (F → η logit), with several ``judge_mlp`` (features + a candidate's key-points + goal →
    its score and η logit); ``flown_mlp`` (``flown_samples``); ``tan`` (:class:`TimeAllocationNet`).

    Key-points are offsets (metres, body frame) from each candidate's anchor path (:meth:`anchor_paths`);
    the last layer starts near zero, so the untrained net flies its anchors. The last key-point is the
    trajectory's end; the goal cost pulls it to the goal, which need not be reached.
    """

    anchor_peaks: torch.Tensor
    """(M, 2) buffer: :meth:`PlannerConfig.anchors` (not saved in the state dict)."""

    def __init__(self, config: PlannerConfig | None = None) -> None:
        super().__init__()
        self._frozen_encoder: _FrozenEncoder | None = None  # prepare_inference()
        self.config = config or PlannerConfig()
        c = self.config
        K = c.num_keypoints
        self.encoder = ResNet18(in_channels=2, width=c.encoder_width)
        C = self.encoder.out_channels
        self.goal_embed = nn.Linear(3, c.goal_embed_dim)
        self.head_conv = nn.Sequential(
            nn.Conv2d(C + c.goal_embed_dim, c.conv_channels[0], 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(c.conv_channels[0], c.conv_channels[1], 3, padding=1),
            nn.ReLU(inplace=True),
            nn.AdaptiveAvgPool2d(tuple(c.pooled_size)),
        )
        flat = c.conv_channels[1] * c.pooled_size[0] * c.pooled_size[1] + (3 if c.velocity_input else 0)
        M = c.num_candidates
        act = c.head_activation
        self.keypoint_mlp = _mlp([flat, *c.mlp_hidden, 3 * K * M], act)
        # One path: η from the features (the paper). Several: one judge shared by every candidate.
        self.eta_mlp = _mlp([flat, *c.eta_hidden, M], act) if M == 1 else None
        checks = K * POINTS_PER_SEGMENT * FEATURES_PER_POINT if c.depth_check else 0
        self.judge_mlp = _mlp([flat + 3 * K + 3 + checks, *c.eta_hidden, 2], act) if M > 1 else None
        self.flown_mlp = _mlp([FLOWN_FEATURES * c.flown_samples + 1, *c.eta_hidden, 1], act) if c.flown_samples else None
        self.register_buffer("anchor_peaks", torch.tensor(c.anchors(), dtype=torch.float32), persistent=False)
        with torch.no_grad():
            last = self.keypoint_mlp[-1]
            assert isinstance(last, nn.Linear)  # _mlp ends with a Linear layer
            last.weight.mul_(0.01)  # the untrained net's paths lie within centimetres of their anchors
            last.bias.zero_()
        self.tan = TimeAllocationNet(TimeAllocationNetConfig(num_segments=K, hidden=tuple(c.tan_hidden),
                                                             v_max=c.cruise_speed, a_max=c.accel,
                                                             boundary_inputs=c.tan_boundary,
                                                             boundary_scale=c.tan_boundary_scale))

    # ------------------------------------------------------------------ deployment

    def prepare_inference(self) -> PlannerNet:
        """Put the net in ``eval()`` mode and keep a frozen copy of the encoder for single-image plans on
        the CPU, run by ONNX Runtime (with the nearest-depth pyramid of a ``depth_check`` model). Features
        differ from the eager encoder's by float rounding (~1e-6). Batches, other devices, gradients and
        training use the eager encoder; ``train()`` or loading weights drops the copy. Where ONNX Runtime
        cannot run the graph the eager one stays in use (:attr:`frozen_runtime` None)."""
        self.eval()
        self._frozen_encoder = None
        h, w = self.config.input_size
        example = torch.zeros(1, 2, h, w, dtype=next(self.encoder.parameters()).dtype)
        if example.device.type != "cpu" or example.dtype != torch.float32:
            return self
        try:
            module = _OrtEncoder(self.encoder, example, self.config.depth_check and self.config.num_candidates > 1)
            module(example)  # ONNX Runtime's first allocation: here, not in a plan
        except Exception as exc:  # noqa: BLE001 - a graph the runtime cannot run
            log.warning("the encoder could not be frozen for inference (%s); planning uses the eager encoder", exc)
            return self
        self._frozen_encoder = _FrozenEncoder(module, tuple(example.shape), example.dtype)
        return self

    @property
    def frozen_runtime(self) -> str | None:
        """What runs single-image encodings after :meth:`prepare_inference` (None: the eager encoder)."""
        return None if self._frozen_encoder is None else "onnxruntime"

    def train(self, mode: bool = True) -> PlannerNet:
        if mode:
            self._frozen_encoder = None
        return super().train(mode)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        self._frozen_encoder = None
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def _encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The encoder's features of x, and its nearest-depth pyramid when the frozen copy made it."""
        frozen = self._frozen_encoder
        if (frozen is not None and not self.training and not torch.is_grad_enabled()
                and tuple(x.shape) == frozen.shape and x.dtype == frozen.dtype and x.device.type == "cpu"):
            return frozen.module(x)
        return self.encoder(x), None

    # ------------------------------------------------------------------ pieces
    def preprocess(self, depth: torch.Tensor) -> torch.Tensor:
        """:func:`preprocess_depth` with this config's ``input_size`` and ``max_depth``."""
        return preprocess_depth(depth, input_size=self.config.input_size, max_depth=self.config.max_depth)

    def straight_line(self, goal: torch.Tensor) -> torch.Tensor:
        """(B, K, 3): the K equally spaced points (i / K) · goal, i = 1..K, on the origin → goal line."""
        K = self.config.num_keypoints
        frac = torch.arange(1, K + 1, dtype=goal.dtype, device=goal.device) / K
        return frac.reshape(1, K, 1) * goal.unsqueeze(1)

    def anchor_paths(self, goal: torch.Tensor, peaks: torch.Tensor | None = None) -> torch.Tensor:
        """(B, M, K, 3): each candidate's anchor: the straight line plus peak × sin(π i / K) along the
        goal direction's horizontal normal (lateral, left positive) and up (vertical), scaled by
        |goal| / 6 m within [0.3, 1.5]. ``peaks`` (M, 2): other (lateral, vertical) peaks than the config's."""
        K = self.config.num_keypoints
        line = self.straight_line(goal)  # (B, K, 3)
        frac = torch.arange(1, K + 1, dtype=goal.dtype, device=goal.device) / K
        bump = torch.sin(math.pi * frac)  # (K,)
        up = torch.zeros_like(goal)
        up[:, 2] = 1.0
        left = torch.cross(up, goal, dim=-1)
        norm = left.norm(dim=-1, keepdim=True)
        fallback = torch.zeros_like(goal)
        fallback[:, 1] = 1.0
        left = torch.where(norm > 1e-6, left / norm.clamp_min(1e-6), fallback)
        scale = (goal.norm(dim=-1) / 6.0).clamp(0.3, 1.5)  # (B,)
        peaks = (self.anchor_peaks if peaks is None else peaks).to(goal.dtype)  # (M, 2)
        offset = peaks[None, :, 0, None] * left[:, None] + peaks[None, :, 1, None] * up[:, None]  # (B, M, 3)
        offset = offset * scale[:, None, None]
        return line[:, None] + bump[None, None, :, None] * offset[:, :, None, :]

    def widened(self, candidates: torch.Tensor, goal: torch.Tensor, factors: tuple[float, ...]) -> torch.Tensor:
        """(B, M (1 + F), K, 3): ``candidates`` (B, M, K, 3) followed by each of them with its interior
        key-points' offsets from the straight line to ``goal`` scaled by each of the F ``factors`` (the
        last key-point, where the net ends its path, is kept)."""
        if not all(math.isfinite(f) and f > 0 for f in factors):
            raise PlannerError(f"widening factors must be finite and > 0, got {factors}")
        line = self.straight_line(goal)[:, None]  # (B, 1, K, 3)
        detour = candidates - line
        detour[..., -1, :] = 0.0
        return torch.cat([candidates] + [candidates + detour * (f - 1.0) for f in factors], dim=1)

    def shifted(self, candidates: torch.Tensor, goal: torch.Tensor, shifts: tuple[float, ...]) -> torch.Tensor:
        """(B, M (1 + S), K, 3): ``candidates`` (B, M, K, 3) followed by all of them moved sideways by
        each of the S ``shifts`` (metres, left positive) at the middle of the path, along the anchors'
        bump (zero at the start and at the last key-point) and their scale with the goal's distance."""
        if not all(math.isfinite(s) for s in shifts):
            raise PlannerError(f"candidate shifts must be finite metres, got {shifts}")
        unit = self._lateral_bump(goal)[:, None]  # (B, 1, K, 3)
        return torch.cat([candidates] + [candidates + s * unit for s in shifts], dim=1)

    def _lateral_bump(self, goal: torch.Tensor) -> torch.Tensor:
        """(B, K, 3): the offset of a 1 m left detour anchor from the straight line to ``goal``."""
        line = self.straight_line(goal)
        left = self.anchor_paths(goal, torch.tensor([[1.0, 0.0]], dtype=goal.dtype, device=goal.device))
        return left[:, 0] - line

    def forward(self, x: torch.Tensor, goal: torch.Tensor, image_index: torch.Tensor | None = None,
                camera: CameraInput | None = None, velocity: torch.Tensor | None = None,
                image: ImageFeatures | None = None, widen: tuple[float, ...] = (),
                shift: tuple[float, ...] = ()) -> PlannerOutput:
        """Predict key-points and η.

        Args:
            x: (B, 2, h, w) preprocessed depth (:meth:`preprocess`), h, w = ``config.input_size``; or
                (U, 2, h, w) distinct images with ``image_index``.
            goal: (B, 3) goal in the body frame (FLU), metres.
            image_index: (B,) int64, the image of x each goal is planned from (None: x[i] for goal i).
                Several goals per image run the encoder once per image (training's batches).
            camera: calibration per goal (B) or one for all; required when ``config.depth_check``.
            velocity: (B, 3) body-frame velocity, m/s (``config.velocity_input``; None = at rest).
            image: ``PlannerOutput.image`` of an earlier pass on the same ``x`` (one image): its
                features and pyramid are reused (a second goal from the same frame).
            widen: factors of :meth:`widened` candidates judged and chosen among like the trained ones
                (several candidates only; () none).
            shift: sideways shifts (m) of :meth:`shifted` candidates (of the trained and the widened
                ones), judged and chosen among likewise (several candidates only; () none).

        Returns:
            :class:`PlannerOutput` with keypoints (B, K, 3), eta (B,), eta_logit (B,).
        """
        c = self.config
        self._check_inputs(x, goal, image_index, camera)
        goal = goal.to(x.dtype)
        made = None  # the pyramid, when the frozen encoder made it with the features
        if image is None:
            encoded, made = self._encode(x)
        else:
            encoded = image.features
        flat = self._head(encoded if image_index is None else encoded[image_index], goal, velocity)
        B, M = goal.shape[0], c.num_candidates
        candidates = self.anchor_paths(goal) + self.keypoint_mlp(flat).reshape(B, M, c.num_keypoints, 3)
        if widen and M > 1:
            candidates = self.widened(candidates, goal, widen)
        if shift and M > 1:
            candidates = self.shifted(candidates, goal, shift)
        pyramid: torch.Tensor | None = None
        scores: torch.Tensor | None = None
        if self.judge_mlp is None:
            assert self.eta_mlp is not None  # one candidate: an η head instead of a judge (__init__)
            logits = self.eta_mlp(flat).reshape(B, candidates.shape[1])
            chosen = torch.zeros(B, dtype=torch.long, device=x.device)
        else:
            if c.depth_check:  # once per image, then shared by its goals
                pyramid = image.pyramid if image is not None and image.pyramid is not None else made
                if pyramid is None:
                    pyramid = nearest_depth_pyramid(x)
                if image_index is not None:
                    pyramid = pyramid[image_index]
            scores, logits = self._judge(flat, candidates, goal, x, camera=camera, pyramid=pyramid)
            chosen = choose_candidate(scores, logits)
        rows = torch.arange(B, device=x.device)
        logit = logits[rows, chosen]
        own = None if image_index is not None or x.shape[0] != 1 else ImageFeatures(x, encoded, pyramid)
        return PlannerOutput(keypoints=candidates[rows, chosen], eta=torch.sigmoid(logit), eta_logit=logit,
                             candidates=candidates, candidate_eta_logits=logits, scores=scores, chosen=chosen,
                             pyramid=pyramid, image=own)

    def _head(self, feat: torch.Tensor, goal: torch.Tensor, velocity: torch.Tensor | None) -> torch.Tensor:
        """(B, F) flattened head features of the encoder's (B, C, h', w') features with the goal embedded
        (and the velocity appended with ``velocity_input``)."""
        c = self.config
        B, _, fh, fw = feat.shape
        g = self.goal_embed(goal / c.max_depth)
        feat = torch.cat([feat, g.reshape(B, -1, 1, 1).expand(B, g.shape[1], fh, fw)], dim=1)
        flat = self.head_conv(feat).flatten(1)
        if c.velocity_input:
            v = (torch.zeros_like(goal) if velocity is None
                 else torch.as_tensor(velocity, dtype=goal.dtype, device=goal.device).reshape(-1, 3).expand(B, 3))
            flat = torch.cat([flat, v / c.cruise_speed], dim=1)
        return flat

    def _check_inputs(self, x: torch.Tensor, goal: torch.Tensor, image_index: torch.Tensor | None,
                      camera: CameraInput | None) -> None:
        """Raise :class:`PlannerError` for inputs :meth:`forward` cannot plan from."""
        c = self.config
        if x.ndim != 4 or x.shape[1] != 2 or tuple(x.shape[2:]) != tuple(c.input_size):
            raise PlannerError(
                f"x must be preprocessed depth (B, 2, {c.input_size[0]}, {c.input_size[1]}), got "
                f"{tuple(x.shape)}; pass raw depth through PlannerNet.preprocess first"
            )
        B = x.shape[0] if image_index is None else image_index.shape[0]
        if c.depth_check and c.num_candidates > 1 and camera is None:
            raise PlannerError("this model checks its paths against the depth image: pass the camera's calibration "
                               "(camera=CameraInput.from_calibration(K, width, height, T_body_camera))")
        if goal.shape != (B, 3):
            raise PlannerError(f"goal must have shape (B={B}, 3) in the body frame, got {tuple(goal.shape)}")

    def _judge(self, flat: torch.Tensor, candidates: torch.Tensor, goal: torch.Tensor, x: torch.Tensor, *,
               camera: CameraInput | None, pyramid: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(scores, η logits), each (B, M), of the candidates (B, M, K, 3) from the image features `flat`
        (B, F), the goal and, with ``depth_check``, each candidate checked against the depth `x` (B rows)
        through the nearest-depth `pyramid` (B rows)."""
        c = self.config
        assert self.judge_mlp is not None  # several candidates (__init__)
        B, M = candidates.shape[:2]
        parts = [flat[:, None].expand(B, M, flat.shape[1]), candidates.detach().flatten(2) / c.max_depth,
                 (goal / c.max_depth)[:, None].expand(B, M, 3)]
        if c.depth_check:
            assert camera is not None  # required with depth_check and several candidates (_check_inputs)
            cam = camera.expand(B).to(x.device)
            parts.append(depth_margins(candidates.detach(), x, cam, max_depth=c.max_depth,
                                       pyramid=pyramid).to(x.dtype))
        per = torch.cat(parts, dim=2)
        judged = self.judge_mlp(per)  # (B, M, 2)
        return judged[..., 0], judged[..., 1]

    def flown_logits(self, features: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """η logits (...) of the flown-path head from what it reads at a trajectory's N points
        (..., N, FLOWN_FEATURES) (:func:`flown_features`) and the trajectory's length within
        ``flown_horizon`` (...), metres."""
        c = self.config
        if self.flown_mlp is None:
            raise PlannerError("this model has no flown-path head (flown_samples=0); fit one with mapkit lab tune-judge")
        if features.shape[-2:] != (c.flown_samples, FLOWN_FEATURES) or features.shape[:-2] != lengths.shape:
            raise PlannerError(f"features must be (..., {c.flown_samples}, {FLOWN_FEATURES}) with lengths (...), got "
                               f"{tuple(features.shape)} and {tuple(lengths.shape)}")
        per = torch.cat([features.flatten(-2), (lengths / c.flown_horizon).clamp(max=1.0)[..., None]], dim=-1)
        return self.flown_mlp(per.to(next(self.flown_mlp.parameters()).dtype))[..., 0]

    def judge_flown(self, out: PlannerOutput, trajectories: Trajectory, x: torch.Tensor,
                    camera: CameraInput, *, recent: torch.Tensor | None = None) -> PlannerOutput:
        """``out`` with the flown-path head's η for every candidate and the best-scored one it expects
        free chosen (:func:`choose_candidate`). ``trajectories``: each candidate's trajectory as flown,
        B·M of them in the order of ``out.candidates`` (B, M, K, 3), in the body frame of the image
        ``x`` (B, 2, h, w) they were planned from; ``recent`` (B, P, 3): points of the flight's last
        ``flown_history`` seconds of frames in that body frame (None: the image alone)."""
        c = self.config
        assert out.candidates is not None  # every forward pass fills it
        B, M = out.candidates.shape[:2]
        points, lengths = arclength_points(trajectories, horizon=c.flown_horizon, count=c.flown_samples)
        features = flown_features(points.reshape(B, M, -1, 3), x, camera, max_depth=c.max_depth, pyramid=out.pyramid,
                                  recent=recent)
        logits = self.flown_logits(features, lengths.reshape(B, M).to(features.dtype)).to(x.dtype)
        chosen = (torch.zeros(B, dtype=torch.long, device=logits.device) if out.scores is None
                  else choose_candidate(out.scores, logits))
        rows = torch.arange(B, device=logits.device)
        logit = logits[rows, chosen]
        return dataclasses.replace(out, keypoints=out.candidates[rows, chosen], eta=torch.sigmoid(logit),
                                   eta_logit=logit, candidate_eta_logits=logits, chosen=chosen)

    def trajectory(
        self,
        keypoints: torch.Tensor,
        *,
        start_velocity: torch.Tensor | None = None,
        start_acceleration: torch.Tensor | None = None,
        end_speed: torch.Tensor | None = None,
        corridor: float | None = None,
    ) -> Plan:
        """Key-points → minimum-snap trajectory (differentiable w.r.t. the key-points).

        Waypoints are [origin, k1, ..., kK]. The total time is :func:`mapkit.planner.total_time` (no
        gradient), every segment gets ``min_segment_time`` and the TAN splits the rest (its shares reach
        the trajectory detached: the TAN learns from U_T alone, as in the paper), and
        :func:`mapkit.trajopt.min_snap` joins the start state to ``end_speed`` along the last segment.

        Args:
            keypoints: (B, K, 3) metres, body frame.
            start_velocity: (B, 3) m/s in the body frame (default zero).
            start_acceleration: (B, 3) m/s² in the body frame (default zero).
            end_speed: (B,) m/s at the last key-point (default zero: rest).
            corridor: the flight corridor's half-width (metres) around each key-point segment: the
                interior key-points then bound the path instead of pinning it (None: through them).

        Returns:
            :class:`Plan` (``eta`` None).
        """
        c = self.config
        K = c.num_keypoints
        if keypoints.ndim != 3 or keypoints.shape[1:] != (K, 3):
            raise PlannerError(f"keypoints must have shape (B, {K}, 3), got {tuple(keypoints.shape)}")
        B = keypoints.shape[0]
        start = torch.zeros(B, 3, 3, dtype=keypoints.dtype, device=keypoints.device)
        for row, (name, v) in enumerate((("start_velocity", start_velocity), ("start_acceleration", start_acceleration))):
            if v is None:
                continue
            v = torch.as_tensor(v, dtype=keypoints.dtype, device=keypoints.device)
            if v.shape == (3,):
                v = v.expand(B, 3)
            if v.shape != (B, 3):
                raise PlannerError(f"{name} must have shape (B={B}, 3) or (3,), got {tuple(v.shape)}")
            start[:, row] = v
        speed = torch.zeros(B, dtype=keypoints.dtype, device=keypoints.device)
        if end_speed is not None:
            speed = torch.broadcast_to(torch.as_tensor(end_speed, dtype=keypoints.dtype, device=keypoints.device), (B,))
        waypoints = torch.cat([torch.zeros_like(keypoints[:, :1]), keypoints], dim=1)
        timing = plan_timing(waypoints, start, speed, c, tan=self.tan)
        traj = min_snap(waypoints, timing.durations, start=start, end=timing.end, corridor=corridor)
        return Plan(
            trajectory=traj, waypoints=waypoints, shares=timing.shares, durations=timing.durations,
            total_time=timing.total, start=start, keypoints=keypoints, end_speed=speed,
            min_segment=c.min_segment_time,
        )

    def plan(
        self,
        depth: torch.Tensor,
        goal: torch.Tensor,
        *,
        start_velocity: torch.Tensor | None = None,
        start_acceleration: torch.Tensor | None = None,
        end_speed: torch.Tensor | None = None,
        corridor: float | None = None,
        camera: CameraInput | None = None,
        widen: tuple[float, ...] = (),
        shift: tuple[float, ...] = (),
    ) -> Plan:
        """Depth image(s) in metres + goal → :class:`Plan` (preprocess, forward, trajectory).

        Args:
            depth: (B, H, W) float metres, NaN invalid (any size; resized to ``input_size``).
            goal: (B, 3) body frame metres.
            start_velocity, start_acceleration: (B, 3) body frame, see :meth:`trajectory`.
            end_speed: (B,) m/s at the last key-point (0: rest).
            corridor: see :meth:`trajectory`; camera: see :meth:`forward`.
            widen, shift: widened and shifted candidates, see :meth:`forward`.
        """
        x = self.preprocess(depth)
        goal = torch.as_tensor(goal, dtype=x.dtype, device=x.device)
        if goal.ndim == 1:
            goal = goal.unsqueeze(0)
        out = self(x, goal, camera=camera, velocity=start_velocity, widen=widen, shift=shift)
        p = self.trajectory(out.keypoints, start_velocity=start_velocity, start_acceleration=start_acceleration,
                            end_speed=end_speed, corridor=corridor)
        p.eta, p.eta_logit = out.eta, out.eta_logit
        if out.chosen is not None:
            unshifted = self.config.num_candidates * (1 + (len(widen) if self.config.num_candidates > 1 else 0))
            p.widened = (out.chosen % unshifted) >= self.config.num_candidates
            p.shifted = out.chosen >= unshifted
        return p

