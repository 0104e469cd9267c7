"""ResNet-18 depth encoder (written here; no torchvision) and a loader for torchvision's weights.

The module names deliberately follow torchvision's ``resnet18`` (``conv1``, ``bn1``,
``layer1.0.conv1``, ..., ``layer2.0.downsample.0``), so a torchvision state dict maps onto it key by
key; only ``conv1.weight`` changes shape (RGB → depth channels) and ``fc.*`` is dropped (this encoder
has no classifier: it returns the last feature map).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from mapkit.planner._errors import PlannerError

BASE_CHANNELS = (64, 128, 256, 512)
"""Channels of layer1..layer4 of the standard ResNet-18 (``width=1``)."""
BLOCKS = (2, 2, 2, 2)
"""BasicBlocks per stage of ResNet-18."""


def scaled_channels(width: float) -> tuple[int, int, int, int]:
    """Stage channels for a width factor: ``max(8, round(c * width))`` for c in 64/128/256/512."""
    if not width > 0:
        raise PlannerError(f"encoder width must be > 0, got {width}")
    c1, c2, c3, c4 = (max(8, int(round(c * width))) for c in BASE_CHANNELS)
    return c1, c2, c3, c4


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
    """ResNet-18 feature extractor for depth images.

    Input (B, ``in_channels``, H, W) → feature map (B, :attr:`out_channels`, ceil(H/32), ceil(W/32))
    (stride 2 conv1, stride 2 max-pool, strides 1/2/2/2 in layer1..layer4). No global pooling and no
    classifier: the planner head keeps the spatial layout.

    Args:
        in_channels: input channels (the planner feeds 2: normalised depth and its valid mask).
        width: channel scale factor; 1.0 is the standard 64/128/256/512 network (the only width that
            can load torchvision weights), e.g. 0.25 gives 16/32/64/128 for the CPU preset.
    """

    layer1: nn.Sequential
    layer2: nn.Sequential
    layer3: nn.Sequential
    layer4: nn.Sequential
    """The four stages, set by name in ``__init__`` (torchvision's names, so its weights load)."""

    def __init__(self, *, in_channels: int = 1, width: float = 1.0) -> None:
        super().__init__()
        if in_channels < 1:
            raise PlannerError(f"in_channels must be >= 1, got {in_channels}")
        self.in_channels = int(in_channels)
        self.width = float(width)
        ch = scaled_channels(width)
        self.conv1 = nn.Conv2d(in_channels, ch[0], 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(ch[0])
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        prev = ch[0]
        for i, (c, n) in enumerate(zip(ch, BLOCKS, strict=True)):
            stride = 1 if i == 0 else 2
            blocks = [BasicBlock(prev, c, stride)] + [BasicBlock(c, c, 1) for _ in range(n - 1)]
            setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
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


def torchvision_resnet18_keys() -> list[str]:
    """Every key of torchvision's ``resnet18().state_dict()`` in its order (for checks and tests)."""
    bn = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
    keys = ["conv1.weight"] + [f"bn1.{s}" for s in bn]
    for layer in range(1, 5):
        for block in range(2):
            p = f"layer{layer}.{block}"
            keys += [f"{p}.conv1.weight"] + [f"{p}.bn1.{s}" for s in bn]
            keys += [f"{p}.conv2.weight"] + [f"{p}.bn2.{s}" for s in bn]
            if layer > 1 and block == 0:
                keys += [f"{p}.downsample.0.weight"] + [f"{p}.downsample.1.{s}" for s in bn]
    return keys + ["fc.weight", "fc.bias"]


def load_torchvision_state_dict(
    model: ResNet18, state_dict: Mapping[str, torch.Tensor], *, strict: bool = True
) -> list[str]:
    """Load torchvision ``resnet18`` weights (e.g. ImageNet, saved elsewhere with
    ``torch.save(torchvision.models.resnet18(weights=...).state_dict(), path)``) into ``model``.

    Mapping:
        - ``conv1.weight`` (64, 3, 7, 7): summed over the RGB axis into one kernel (64, 1, 7, 7), which
          responds to a depth image exactly as the RGB kernel responds to the same image replicated
          in three grey channels. It fills input channel 0 (depth); any further input channels of
          ``model`` (the planner's valid mask) get zero weights, so the loaded encoder starts as the
          ImageNet network on depth alone and learns to use the mask in training.
        - ``bn1.*``, ``layer{1..4}.{0,1}.{conv1,bn1,conv2,bn2}.*``,
          ``layer{2,3,4}.0.downsample.{0,1}.*``: copied unchanged (same names and shapes).
        - ``fc.*``: ignored (the encoder has no classifier).
        - A ``module.`` prefix (DataParallel checkpoints) is stripped.

    Args:
        model: a :class:`ResNet18` with ``width=1.0``.
        state_dict: torchvision key layout; tensors of any float dtype.
        strict: raise on missing or unexpected keys (default); otherwise load what matches.

    Returns:
        The torchvision keys that were ignored (``fc.*`` and, non-strict, any unexpected keys).

    Raises:
        PlannerError: width is not 1.0, keys are missing/unexpected (strict), or a shape differs.
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
    ignored = sorted(k for k in sd if k.startswith("fc."))
    unexpected = sorted(k for k in sd if k not in own and not k.startswith("fc."))
    missing = sorted(k for k in own if k not in sd)
    if strict and (missing or unexpected):
        raise PlannerError(
            "state dict is not a torchvision resnet18 one: "
            f"missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
            f"unexpected {unexpected[:5]}{'...' if len(unexpected) > 5 else ''}; "
            "save it with torch.save(torchvision.models.resnet18(...).state_dict(), path)"
        )
    new: dict[str, torch.Tensor] = {}
    for k, v in sd.items():
        if k not in own:
            continue
        v = torch.as_tensor(v)
        target = own[k]
        if k == "conv1.weight":
            if v.ndim != 4 or v.shape[0] != target.shape[0] or v.shape[2:] != target.shape[2:]:
                raise PlannerError(
                    f"conv1.weight has shape {tuple(v.shape)}, expected ({target.shape[0]}, C, 7, 7)"
                )
            w = torch.zeros_like(target)
            w[:, :1] = v.to(target.dtype).sum(dim=1, keepdim=True)
            v = w
        elif v.shape != target.shape:
            raise PlannerError(f"{k} has shape {tuple(v.shape)}, expected {tuple(target.shape)}")
        new[k] = v.to(target.dtype)
    model.load_state_dict(new, strict=strict)
    return ignored + (unexpected if not strict else [])
