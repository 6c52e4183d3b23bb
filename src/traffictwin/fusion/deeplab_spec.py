"""The fusion network's architecture, :class:`DeepLabSpec` (what a checkpoint must match to be
loaded), without torch: :class:`~traffictwin.fusion.deeplab.DeepLabV3Plus` builds from it, and
``check_params`` validates ``fusion_model.architecture`` with it before any stage runs. The fields
and the three extensions beyond the paper: :mod:`traffictwin.fusion.deeplab`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from traffictwin.fusion.resnet_spec import ResNetSpec

EVIDENCE_ACTIVATIONS = ("relu", "exp")
#: bounds of the head's widths and rates (the paper's: ASPP 256, decoder 256, low-level 48)
MAX_CHANNELS = 2048
MAX_OUTPUTS = 64
MAX_RATE = 256
MAX_RATES = 8
RESIDUALS = ("none", "dempster")  # DeepLabSpec.residual: the plain network | Dempster + correction


@dataclass(frozen=True)
class DeepLabSpec:
    """Full architecture of the fusion network (what a checkpoint must match to be loaded).

    backbone: the ResNet; aspp_channels: width of every ASPP branch and of its projection
    (256 in DeepLabV3+); aspp_rates: atrous rates at output stride 16; low_level_channels:
    the decoder's projection of the stride-4 features (48); decoder_channels: the two 3x3
    decoder convs (256); num_outputs: evidence channels (2: free, occupied); aspp_dropout:
    dropout after the ASPP projection (0.1 as in the reference implementation);
    refine_channels: width of the stride-1 refinement head (0 = none, the paper's x4 upsampling);
    refine_dempster: the head also sees Dempster's combination of the two input grids;
    evidence: the output activation, ``relu`` (paper) or ``exp``;
    residual: ``none`` (the network predicts the evidence) or ``dempster`` (it predicts a
    zero-initialised correction of Dempster's combination's logits; needs ``exp`` evidence).
    """

    backbone: ResNetSpec = field(default_factory=ResNetSpec)
    aspp_channels: int = 256
    aspp_rates: tuple[int, ...] = (6, 12, 18)
    low_level_channels: int = 48
    decoder_channels: int = 256
    num_outputs: int = 2
    aspp_dropout: float = 0.1
    refine_channels: int = 0
    refine_dempster: bool = False
    evidence: str = "relu"
    residual: str = "none"

    def __post_init__(self) -> None:
        for name in ("aspp_channels", "low_level_channels", "decoder_channels", "num_outputs"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"deeplab {name} must be >= 1, got {getattr(self, name)}")
        if int(self.refine_channels) < 0:
            raise ValueError(f"deeplab refine_channels must be >= 0, got {self.refine_channels}")
        if self.refine_dempster and (self.refine_channels == 0 or self.backbone.in_channels != 4):
            raise ValueError(
                "deeplab refine_dempster needs refine_channels > 0 and 4 input channels "
                "[m_F1, m_O1, m_F2', m_O2']"
            )
        if self.evidence not in EVIDENCE_ACTIVATIONS:
            raise ValueError(
                f"deeplab evidence must be one of {EVIDENCE_ACTIVATIONS}, got {self.evidence!r}"
            )
        if not self.aspp_rates or any(int(r) < 1 for r in self.aspp_rates):
            raise ValueError(
                f"deeplab aspp_rates must be positive integers, got {self.aspp_rates!r}"
            )
        if not 0.0 <= self.aspp_dropout < 1.0:
            raise ValueError(f"deeplab aspp_dropout must be in [0, 1), got {self.aspp_dropout}")
        object.__setattr__(self, "aspp_rates", tuple(int(r) for r in self.aspp_rates))
        self._check_bounds()
        _check_residual(self)

    def _check_bounds(self) -> None:
        """Every width, count and rate at most its bound, and the whole network at most
        :data:`~traffictwin.io.limits.MAX_MODEL_PARAMETERS` weights (estimated from the convs:
        the paper's ResNet-50 head ~40 M), before any layer is built."""
        from traffictwin.io.limits import check_at_most, check_parameter_budget

        for name in ("aspp_channels", "low_level_channels", "decoder_channels", "refine_channels"):
            check_at_most("deeplab", name, int(getattr(self, name)), MAX_CHANNELS)
        check_at_most("deeplab", "num_outputs", int(self.num_outputs), MAX_OUTPUTS)
        check_at_most("deeplab", "len(aspp_rates)", len(self.aspp_rates), MAX_RATES)
        check_at_most("deeplab", "aspp_rates", max(self.aspp_rates), MAX_RATE)
        check_parameter_budget(
            "deeplab",
            self.parameter_estimate(),
            "backbone.block/layers/base_width and the head's widths",
        )

    def parameter_estimate(self) -> int:
        """Conv weights of the network (no biases or norms; within a few % of the real count)."""
        b = self.backbone
        e, w = b.expansion, int(b.base_width)
        n = b.in_channels * w * 49  # stem
        cin = w
        for i, blocks in enumerate(b.layers):
            wi = w * 2**i
            out = wi * e
            for j in range(blocks):
                c = cin if j == 0 else out
                if b.block == "bottleneck":
                    n += c * wi + wi * wi * 9 + wi * out
                else:
                    n += c * wi * 9 + wi * wi * 9
                if j == 0 and c != out:
                    n += c * out  # projection shortcut
            cin = out
        a, k = int(self.aspp_channels), len(self.aspp_rates)
        n += cin * a * (2 + 9 * k) + (k + 2) * a * a  # ASPP branches, pooling, projection
        lo, d = int(self.low_level_channels), int(self.decoder_channels)
        n += b.low_level_channels * lo + (a + lo) * d * 9 + d * d * 9 + d * int(self.num_outputs)
        r = int(self.refine_channels)
        n += (b.in_channels + int(self.num_outputs) + 2) * r * 9 + r * r * 9 if r else 0
        return int(n)

    @property
    def output_stride(self) -> int:
        return self.backbone.output_stride

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["backbone"] = self.backbone.as_dict()
        d["aspp_rates"] = list(self.aspp_rates)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DeepLabSpec:
        d = dict(d)
        bb = dict(d.pop("backbone", {}))
        for k in ("layers", "dilate"):
            if k in bb:
                bb[k] = tuple(bb[k])
        if "aspp_rates" in d:
            d["aspp_rates"] = tuple(d["aspp_rates"])
        return cls(backbone=ResNetSpec(**bb), **d)


def _check_residual(spec: DeepLabSpec) -> None:
    """The residual head's requirements (a ValueError naming the field otherwise)."""
    if spec.residual not in RESIDUALS:
        raise ValueError(f"deeplab residual must be one of {RESIDUALS}, got {spec.residual!r}")
    if spec.residual == "dempster" and (
        spec.evidence != "exp" or spec.backbone.in_channels != 4 or spec.num_outputs != 2
    ):
        raise ValueError(
            "deeplab residual 'dempster' needs evidence 'exp' (Dempster's masses as logits; "
            "a ReLU output cannot start at them), 4 input channels [m_F1, m_O1, m_F2', m_O2'] "
            f"and 2 outputs; got evidence {spec.evidence!r}, "
            f"{spec.backbone.in_channels} inputs, {spec.num_outputs} outputs"
        )
