"""The ResNet backbone's architecture, :class:`ResNetSpec` (and :func:`resnet_spec` for the
standard depths), without torch: the network (:mod:`traffictwin.fusion.resnet`) builds from it,
and ``check_params`` validates ``fusion_model.architecture`` with it before any stage runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

BLOCKS = ("basic", "bottleneck")
#: bounds of the architecture values (model meta is read from files): ResNet-152 has 36 blocks
#: in a stage, the paper's ResNet-50 a base width of 64
MAX_BLOCKS_PER_STAGE = 64
MAX_BASE_WIDTH = 256
MAX_IN_CHANNELS = 64


@dataclass(frozen=True)
class ResNetSpec:
    """Architecture of a ResNet backbone.

    block: "basic" (ResNet-18/34) or "bottleneck" (ResNet-50/101); layers: blocks per stage;
    base_width: channels of the stem and of stage 1's 3x3 convs (64 in the paper);
    in_channels: input channels (4 = two mass maps); dilate: which of stages 2-4 use dilation
    instead of stride (output stride 16 = (False, False, True)).
    """

    block: str = "basic"
    layers: tuple[int, ...] = (2, 2, 2, 2)
    base_width: int = 64
    in_channels: int = 4
    dilate: tuple[bool, bool, bool] = (False, False, True)

    def __post_init__(self) -> None:
        if self.block not in BLOCKS:
            raise ValueError(f"resnet block must be one of {BLOCKS}, got {self.block!r}")
        if len(self.layers) != 4 or any(int(n) < 1 for n in self.layers):
            raise ValueError(f"resnet layers must be 4 positive block counts, got {self.layers!r}")
        if self.base_width < 1 or self.in_channels < 1:
            raise ValueError(
                f"resnet base_width and in_channels must be >= 1, got {self.base_width}, {self.in_channels}"
            )
        if len(self.dilate) != 3:
            raise ValueError(f"resnet dilate must have 3 flags (stages 2-4), got {self.dilate!r}")
        from traffictwin.io.limits import check_at_most

        check_at_most("resnet", "base_width", self.base_width, MAX_BASE_WIDTH)
        check_at_most("resnet", "in_channels", self.in_channels, MAX_IN_CHANNELS)
        for i, n in enumerate(self.layers):
            check_at_most("resnet", f"layers[{i}]", int(n), MAX_BLOCKS_PER_STAGE)
        object.__setattr__(self, "layers", tuple(int(n) for n in self.layers))
        object.__setattr__(self, "dilate", tuple(bool(d) for d in self.dilate))

    @property
    def expansion(self) -> int:
        return 4 if self.block == "bottleneck" else 1

    @property
    def low_level_channels(self) -> int:
        """Channels of stage 1's output (stride 4), the decoder's low-level features."""
        return self.base_width * self.expansion

    @property
    def out_channels(self) -> int:
        """Channels of stage 4's output."""
        return self.base_width * 8 * self.expansion

    @property
    def output_stride(self) -> int:
        return 4 * 2 ** sum(1 for d in self.dilate if not d)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["layers"] = list(self.layers)
        d["dilate"] = list(self.dilate)
        return d


def resnet_spec(
    depth: int,
    base_width: int = 64,
    in_channels: int = 4,
    dilate: Sequence[bool] = (False, False, True),
) -> ResNetSpec:
    """Standard depths: 18/34 (basic), 50/101/152 (bottleneck)."""
    table = {
        18: ("basic", (2, 2, 2, 2)),
        34: ("basic", (3, 4, 6, 3)),
        50: ("bottleneck", (3, 4, 6, 3)),
        101: ("bottleneck", (3, 4, 23, 3)),
        152: ("bottleneck", (3, 8, 36, 3)),
    }
    if depth not in table:
        raise ValueError(f"resnet depth must be one of {sorted(table)}, got {depth}")
    block, layers = table[depth]
    return ResNetSpec(
        block=block,
        layers=layers,
        base_width=base_width,
        in_channels=in_channels,
        dilate=tuple(dilate),
    )
