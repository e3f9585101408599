"""HRNetV2 backbone (Sun et al.), plain PyTorch, sized by a small config.

Structure (see /work/shared/reference/hma.md section 3): a stem of two stride-2 3x3 convolutions (1/4
resolution), stage 1 of Bottleneck blocks, then stages 2-4 that add one branch at half the resolution
each and repeat HighResolutionModules (BasicBlocks per branch, then an all-to-all fusion). The output
concatenates all branches upsampled (bilinear, align_corners=False) to the 1/4-resolution branch.

Tensors are NCHW float32. Any input size works: fusion resizes to the explicit size of each branch.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

BN_MOMENTUM = 0.1


@dataclass(frozen=True)
class HRNetConfig:
    """Widths and depths of the backbone.

    in_channels: image channels (1 = gray). stem_width: channels after the stem (64 upstream).
    stage1_blocks / stage1_planes: Bottleneck blocks of stage 1 and their inner width (output 4x).
    widths: branch widths (len 4, highest resolution first). modules: HighResolutionModules per stage
    2, 3, 4. blocks: BasicBlocks per branch in each module.
    """

    in_channels: int = 1
    stem_width: int = 64
    stage1_blocks: int = 1
    stage1_planes: int = 32
    widths: tuple[int, ...] = (16, 32, 64, 128)
    modules: tuple[int, ...] = (1, 1, 1)
    blocks: int = 2

    def __post_init__(self) -> None:
        if len(self.widths) != 4 or len(self.modules) != 3:
            raise ValueError("widths needs 4 entries and modules 3")
        if min(self.widths) < 1 or self.blocks < 1 or self.stage1_blocks < 1 or min(self.modules) < 1:
            raise ValueError("HRNet widths and depths must be positive")

    @property
    def out_channels(self) -> int:
        return int(sum(self.widths))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"], d["modules"] = list(self.widths), list(self.modules)
        return d


def conv3x3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


def bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, momentum=BN_MOMENTUM)


def resize_to(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Bilinear resize of ``x`` to the spatial size of ``ref`` (align_corners=False)."""
    return F.interpolate(x, size=ref.shape[2:], mode="bilinear", align_corners=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1, self.bn1 = conv3x3(cin, planes, stride), bn(planes)
        self.conv2, self.bn2 = conv3x3(planes, planes), bn(planes)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return F.relu(out + identity)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1, self.bn1 = nn.Conv2d(cin, planes, 1, bias=False), bn(planes)
        self.conv2, self.bn2 = conv3x3(planes, planes, stride), bn(planes)
        self.conv3, self.bn3 = nn.Conv2d(planes, planes * 4, 1, bias=False), bn(planes * 4)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = F.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        identity = x if self.downsample is None else self.downsample(x)
        return F.relu(out + identity)


def make_layer(block: type, cin: int, planes: int, n: int) -> nn.Sequential:
    down = None
    if cin != planes * block.expansion:
        down = nn.Sequential(nn.Conv2d(cin, planes * block.expansion, 1, bias=False), bn(planes * block.expansion))
    layers = [block(cin, planes, 1, down)]
    layers += [block(planes * block.expansion, planes) for _ in range(n - 1)]
    return nn.Sequential(*layers)


class HighResolutionModule(nn.Module):
    """Parallel BasicBlock branches followed by the all-to-all fusion (output_i = ReLU(sum_j f_ij(x_j)))."""

    def __init__(self, widths: list[int], blocks: int):
        super().__init__()
        n = len(widths)
        self.branches = nn.ModuleList([make_layer(BasicBlock, w, w, blocks) for w in widths])
        self.fuse = nn.ModuleList()
        for i in range(n):
            row = nn.ModuleList()
            for j in range(n):
                if j == i:
                    row.append(nn.Identity())
                elif j > i:  # lower resolution: 1x1 conv then upsample (in forward)
                    row.append(nn.Sequential(nn.Conv2d(widths[j], widths[i], 1, bias=False), bn(widths[i])))
                else:  # higher resolution: (i - j) stride-2 3x3 convs
                    steps = []
                    for k in range(i - j):
                        last = k == i - j - 1
                        cout = widths[i] if last else widths[j]
                        steps += [conv3x3(widths[j], cout, 2), bn(cout)]
                        if not last:
                            steps.append(nn.ReLU())
                    row.append(nn.Sequential(*steps))
            self.fuse.append(row)

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        xs = [branch(x) for branch, x in zip(self.branches, xs)]
        out = []
        for i, row in enumerate(self.fuse):
            acc = xs[i]
            for j, f in enumerate(row):
                if j == i:
                    continue
                y = f(xs[j])
                if j > i:
                    y = resize_to(y, xs[i])
                acc = acc + y
            out.append(F.relu(acc))
        return out


class HRNet(nn.Module):
    """HRNetV2: image (N, C, H, W) -> features (N, sum(widths), ceil(H/4), ceil(W/4))."""

    def __init__(self, cfg: HRNetConfig):
        super().__init__()
        self.cfg = cfg
        s = cfg.stem_width
        self.stem = nn.Sequential(conv3x3(cfg.in_channels, s, 2), bn(s), nn.ReLU(),
                                  conv3x3(s, s, 2), bn(s), nn.ReLU())
        self.layer1 = make_layer(Bottleneck, s, cfg.stage1_planes, cfg.stage1_blocks)
        prev = [cfg.stage1_planes * Bottleneck.expansion]
        self.transitions = nn.ModuleList()
        self.stages = nn.ModuleList()
        for k, n_modules in enumerate(cfg.modules):
            widths = list(cfg.widths[:k + 2])
            trans = nn.ModuleList()
            for b, w in enumerate(widths):
                if b < len(prev):
                    trans.append(nn.Identity() if prev[b] == w else
                                 nn.Sequential(conv3x3(prev[b], w), bn(w), nn.ReLU()))
                else:
                    trans.append(nn.Sequential(conv3x3(prev[-1], w, 2), bn(w), nn.ReLU()))
            self.transitions.append(trans)
            self.stages.append(nn.Sequential(*[HighResolutionModule(widths, cfg.blocks) for _ in range(n_modules)]))
            prev = widths

    @property
    def out_channels(self) -> int:
        return self.cfg.out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.layer1(self.stem(x))
        xs = [x]
        for trans, stage in zip(self.transitions, self.stages):
            new = []
            for b, t in enumerate(trans):
                src = xs[b] if b < len(xs) else xs[-1]
                new.append(t(src))
            xs = stage(new)
        base = xs[0]
        return torch.cat([base] + [resize_to(y, base) for y in xs[1:]], dim=1)


__all__ = ["HRNetConfig", "HRNet", "resize_to", "BasicBlock", "Bottleneck", "HighResolutionModule"]
