"""ResNet backbone in plain ``torch.nn`` (He et al. 2016), for DeepLabV3+.

No torchvision here (docs/design.md "Decisions"). The layout follows torchvision's ResNet v1.5
(stride on the 3x3 conv of a bottleneck): stem = 7x7/2 conv + BN + ReLU + 3x3/2 max-pool,
then four stages. ``replace_stride_with_dilation`` turns the stride of a stage into an atrous
dilation (DeepLabV3+ with output stride 16 dilates the last stage; 8 the last two).

Depth and width are configurable: ``block="bottleneck", layers=(3, 4, 6, 3), base_width=64`` is
ResNet-50 (the paper), ``block="basic", layers=(2, 2, 2, 2)`` ResNet-18, and a smaller
``base_width`` gives narrow variants for the CPU profile. Stage ``k`` has
``base_width * 2**k * expansion`` output channels (expansion 4 for bottleneck, 1 for basic).

The architecture, :class:`ResNetSpec` and :func:`resnet_spec`, lives in
:mod:`traffictwin.fusion.resnet_spec` (no torch, so that ``check_params`` validates it without
loading torch) and is re-exported here.
"""

from __future__ import annotations

import torch
from torch import nn

from traffictwin.fusion.resnet_spec import (  # noqa: F401 - re-exported: the spec's home is torch-free
    BLOCKS,
    MAX_BASE_WIDTH,
    MAX_BLOCKS_PER_STAGE,
    MAX_IN_CHANNELS,
    ResNetSpec,
    resnet_spec,
)


def conv3x3(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False)


def conv1x1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, stride=stride, bias=False)


class _Block(nn.Module):
    """A residual block. Subclasses define ``layers(cin, width, stride, dilation, first_dilation)``,
    which builds the convolutions (in parameter-initialisation order); the shortcut is
    ``downsample`` or the identity."""

    expansion = 1

    def __init__(
        self,
        cin: int,
        width: int,
        stride: int = 1,
        dilation: int = 1,
        downsample: nn.Module | None = None,
        first_dilation: int = 1,
    ) -> None:
        super().__init__()
        self.layers(cin, width, stride, dilation, first_dilation)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def shortcut(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.downsample is None else self.downsample(x)


class BasicBlock(_Block):
    """Two 3x3 convs with a residual connection (ResNet-18/34)."""

    expansion = 1

    def layers(self, cin: int, width: int, stride: int, dilation: int, first_dilation: int) -> None:
        self.conv1 = conv3x3(cin, width, stride, first_dilation)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = conv3x3(width, width, 1, dilation)
        self.bn2 = nn.BatchNorm2d(width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idt = self.shortcut(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + idt)


class Bottleneck(_Block):
    """1x1 reduce, 3x3 (carries stride/dilation, v1.5), 1x1 expand x4, residual (ResNet-50).

    ``first_dilation`` is the 3x3's dilation: the previous stage's for a stage's first block
    (as torchvision), the stage's own afterwards; ``dilation`` is unused here (BasicBlock's 2nd conv).
    """

    expansion = 4

    def layers(self, cin: int, width: int, stride: int, dilation: int, first_dilation: int) -> None:
        self.conv1 = conv1x1(cin, width)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = conv3x3(width, width, stride, first_dilation)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = conv1x1(width, width * 4)
        self.bn3 = nn.BatchNorm2d(width * 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idt = self.shortcut(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + idt)


class ResNet(nn.Module):
    """ResNet feature extractor; ``forward`` returns ``(low_level (stride 4), high_level (stride os))``."""

    def __init__(self, spec: ResNetSpec) -> None:
        super().__init__()
        self.spec = spec
        block = Bottleneck if spec.block == "bottleneck" else BasicBlock
        w = spec.base_width
        self.conv1 = nn.Conv2d(spec.in_channels, w, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(w)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self._cin = w
        self._dilation = 1
        self.layer1 = self._make_layer(block, w, spec.layers[0])
        self.layer2 = self._make_layer(
            block, w * 2, spec.layers[1], stride=2, dilate=spec.dilate[0]
        )
        self.layer3 = self._make_layer(
            block, w * 4, spec.layers[2], stride=2, dilate=spec.dilate[1]
        )
        self.layer4 = self._make_layer(
            block, w * 8, spec.layers[3], stride=2, dilate=spec.dilate[2]
        )
        self._init_weights()

    def _make_layer(
        self, block: type, width: int, blocks: int, stride: int = 1, dilate: bool = False
    ) -> nn.Sequential:
        prev_dilation = self._dilation
        if dilate:
            self._dilation *= stride
            stride = 1
        downsample = None
        if stride != 1 or self._cin != width * block.expansion:
            downsample = nn.Sequential(
                conv1x1(self._cin, width * block.expansion, stride),
                nn.BatchNorm2d(width * block.expansion),
            )
        mods = [
            block(
                self._cin, width, stride, self._dilation, downsample, first_dilation=prev_dilation
            )
        ]
        self._cin = width * block.expansion
        for _ in range(1, blocks):
            mods.append(
                block(self._cin, width, 1, self._dilation, None, first_dilation=self._dilation)
            )
        return nn.Sequential(*mods)

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        # zero-init the last BN of each residual branch: blocks start as identities (Goyal et al. 2017)
        for m in self.modules():
            if isinstance(m, Bottleneck):
                nn.init.zeros_(m.bn3.weight)
            elif isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        low = self.layer1(x)
        x = self.layer4(self.layer3(self.layer2(low)))
        return low, x
