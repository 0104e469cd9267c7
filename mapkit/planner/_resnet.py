"""ResNet-18 depth encoder (written here; no torchvision) and a loader for torchvision's weights.

The module names follow torchvision's ``resnet18``, so its state dict maps onto this one key by key
(``conv1.weight`` changes shape for the depth channels; ``fc.*``, the classifier, is dropped).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from mapkit.planner._errors import PlannerError

BASE_CHANNELS = (64, 128, 256, 512)
"""Channels of layer1..layer4 of the standard ResNet-18 (``width=1``), two BasicBlocks each."""


class BasicBlock(nn.Module):
    """Two 3×3 conv-BN layers with an identity (or 1×1 conv-BN ``downsample``) shortcut."""

    def __init__(self, in_ch: int, out_ch: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 feature extractor: (B, ``in_channels``, H, W) → (B, :attr:`out_channels`, ceil(H/32),
    ceil(W/32)), no pooling or classifier (the planner head keeps the spatial layout).

    Args:
        in_channels: input channels (the planner feeds 2: normalised depth and its valid mask).
        width: channel scale, ``max(8, round(c × width))`` for c in 64/128/256/512; only 1.0 loads
            torchvision weights.
    """

    layer1: nn.Sequential
    layer2: nn.Sequential
    layer3: nn.Sequential
    layer4: nn.Sequential
    """The four stages, set by name in ``__init__``."""

    def __init__(self, *, in_channels: int = 1, width: float = 1.0) -> None:
        super().__init__()
        if in_channels < 1:
            raise PlannerError(f"in_channels must be >= 1, got {in_channels}")
        self.in_channels = int(in_channels)
        self.width = float(width)
        if not width > 0:
            raise PlannerError(f"encoder width must be > 0, got {width}")
        ch = [max(8, int(round(c * width))) for c in BASE_CHANNELS]
        self.conv1 = nn.Conv2d(in_channels, ch[0], 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(ch[0])
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        prev = ch[0]
        for i, c in enumerate(ch):
            setattr(self, f"layer{i + 1}", nn.Sequential(BasicBlock(prev, c, 1 if i == 0 else 2), BasicBlock(c, c, 1)))
            prev = c
        self.out_channels: int = prev
        """Channels of the returned feature map."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, in_channels, H, W) → (B, out_channels, ceil(H/32), ceil(W/32))."""
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise PlannerError(
                f"ResNet18 expects input (B, {self.in_channels}, H, W), got {tuple(x.shape)}"
            )
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer1(x)
        x = self.layer2(x)
        x = self.layer3(x)
        return self.layer4(x)


def load_torchvision_state_dict(model: ResNet18, state_dict: Mapping[str, torch.Tensor]) -> list[str]:
    """Load torchvision ``resnet18`` weights (e.g. ImageNet, saved elsewhere with
    ``torch.save(torchvision.models.resnet18(weights=...).state_dict(), path)``) into ``model``.

    ``conv1.weight`` is summed over its RGB axis into the depth channel (the response to a depth image
    is the RGB kernel's to the same image in three grey channels); further input channels (the valid
    mask) get zero weights. Every other key is copied unchanged, ``fc.*`` is ignored, and a ``module.``
    prefix (DataParallel checkpoints) is stripped.

    Args:
        model: a :class:`ResNet18` with ``width=1.0``.
        state_dict: torchvision key layout; tensors of any float dtype.

    Returns:
        The torchvision keys that were ignored (``fc.*``).

    Raises:
        PlannerError: width is not 1.0, keys are missing or unexpected, or a shape differs.
    """
    if not isinstance(model, ResNet18):
        raise PlannerError(f"model must be a mapkit ResNet18, got {type(model).__name__}")
    if model.width != 1.0:
        raise PlannerError(
            f"torchvision resnet18 weights need an encoder of width 1.0, got width={model.width}; "
            "use the 'paper' preset (or encoder_width=1.0) to load them"
        )
    sd = {(k[len("module."):] if k.startswith("module.") else k): v for k, v in state_dict.items()}
    own = model.state_dict()
    unexpected = sorted(k for k in sd if k not in own and not k.startswith("fc."))
    missing = sorted(k for k in own if k not in sd)
    if missing or unexpected:
        raise PlannerError(
            "state dict is not a torchvision resnet18 one: "
            f"missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
            f"unexpected {unexpected[:5]}{'...' if len(unexpected) > 5 else ''}; "
            "save it with torch.save(torchvision.models.resnet18(...).state_dict(), path)"
        )
    model.load_state_dict({k: _converted(k, torch.as_tensor(sd[k]), target) for k, target in own.items()})
    return sorted(k for k in sd if k.startswith("fc."))


def _converted(key: str, value: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """torchvision's ``value`` of ``key`` in the dtype and shape of this encoder's ``target``."""
    if key == "conv1.weight":
        if value.ndim != 4 or value.shape[0] != target.shape[0] or value.shape[2:] != target.shape[2:]:
            raise PlannerError(f"conv1.weight has shape {tuple(value.shape)}, expected ({target.shape[0]}, C, 7, 7)")
        w = torch.zeros_like(target)
        w[:, :1] = value.to(target.dtype).sum(dim=1, keepdim=True)
        return w
    if value.shape != target.shape:
        raise PlannerError(f"{key} has shape {tuple(value.shape)}, expected {tuple(target.shape)}")
    return value.to(target.dtype)
