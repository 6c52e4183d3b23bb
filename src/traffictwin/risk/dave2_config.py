"""What defines a DAVE-2-like risk network, :class:`Dave2Config` (its inputs, resolution, layers
and training objective, bounded), without torch: :class:`~traffictwin.risk.dave2.Dave2` builds from
it, and ``check_params`` validates the ``risk_model`` variants with it before any stage runs. The
architecture and the objectives: :mod:`traffictwin.risk.dave2`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

#: channel groups the network can be fed, with their channel counts
CHANNELS: dict[str, int] = {"rgb": 3, "disp_sgm": 1, "disp_gt": 1}
#: training objectives and their number of raw outputs
OBJECTIVES: dict[str, int] = {"mse": 1, "log_thw": 1, "mse_bce": 2}
RISK_CLIP = 20.0  # 1/s: risk = min(1/THW, RISK_CLIP) / RISK_CLIP (traffictwin.risk.metric.CLIP)

CONV_SPEC: tuple[tuple[int, int, int], ...] = (
    (24, 5, 2),
    (36, 5, 2),
    (48, 5, 2),
    (64, 3, 1),
    (64, 3, 1),
)
FC_SPEC: tuple[int, ...] = (1164, 100, 50, 10)

#: bounds of the architecture values (the paper: 66 x 200 px input, convs of <= 64 channels)
MAX_INPUT_SIDE = 4096
MAX_LAYERS = 16
MAX_CONV_CHANNELS = 2048
MAX_KERNEL = 15
MAX_FC_WIDTH = 65536


@dataclass(frozen=True)
class Dave2Config:
    """Everything that defines a risk network and how its inputs are prepared.

    ``inputs``: channel groups in stacking order (keys of :data:`CHANNELS`);
    ``height``, ``width``: model input resolution (px);
    ``use_speed``: feed the subject speed (m/s, divided by ``speed_scale``) to the FC head;
    ``disp_scale``: disparity (px at the source resolution) that maps to 1.0 after normalisation;
    ``dropout``: dropout probability before each hidden FC layer (0 = the paper's plain net);
    ``objective``: what the head outputs (:data:`OBJECTIVES`, module docstring); ``thw_cap_s``:
    the THW (s) that stands for "nothing ahead" (``log_thw``); ``critical_thw_s``: the THW
    threshold (s) of the classification head (``mse_bce``; required there, ``None`` = no head).
    """

    inputs: tuple[str, ...] = ("rgb", "disp_sgm")
    height: int = 66
    width: int = 200
    use_speed: bool = False
    speed_scale: float = 30.0
    disp_scale: float = 64.0
    dropout: float = 0.0
    objective: str = "mse"
    thw_cap_s: float = 10.0
    critical_thw_s: float | None = None
    conv: tuple[tuple[int, int, int], ...] = field(default=CONV_SPEC)
    fc: tuple[int, ...] = field(default=FC_SPEC)

    def __post_init__(self) -> None:
        if not self.inputs:
            raise ValueError("Dave2Config.inputs: at least one input channel group is required")
        bad = [c for c in self.inputs if c not in CHANNELS]
        if bad:
            raise ValueError(
                f"Dave2Config.inputs: unknown channel group(s) {bad}; expected a subset of {list(CHANNELS)}"
            )
        if len(set(self.inputs)) != len(self.inputs):
            raise ValueError(f"Dave2Config.inputs: duplicate channel groups in {list(self.inputs)}")
        if self.height < 1 or self.width < 1:
            raise ValueError(
                f"Dave2Config: height/width must be positive, got {self.height}×{self.width}"
            )
        if self.speed_scale <= 0 or self.disp_scale <= 0:
            raise ValueError("Dave2Config: speed_scale and disp_scale must be > 0")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"Dave2Config.dropout must be in [0, 1), got {self.dropout}")
        if self.objective not in OBJECTIVES:
            raise ValueError(
                f"Dave2Config.objective must be one of {list(OBJECTIVES)}, got {self.objective!r}"
            )
        if not self.thw_cap_s > 1.0 / RISK_CLIP:
            raise ValueError("Dave2Config: thw_cap_s must be > 0.05 s")
        if self.critical_thw_s is None:
            if self.objective == "mse_bce":
                raise ValueError("Dave2Config: objective 'mse_bce' needs critical_thw_s (s)")
        elif not self.critical_thw_s > 0:
            raise ValueError("Dave2Config: critical_thw_s must be > 0 s")
        # normalise list-ish fields (JSON round trips give lists)
        object.__setattr__(self, "inputs", tuple(self.inputs))
        object.__setattr__(self, "conv", tuple(tuple(int(v) for v in c) for c in self.conv))
        object.__setattr__(self, "fc", tuple(int(v) for v in self.fc))
        self._check_bounds()
        conv_output_shape(self.height, self.width, self.conv)  # raises when the input is too small
        from traffictwin.io.limits import check_parameter_budget

        check_parameter_budget(
            "Dave2Config", self.parameter_estimate(), "height/width, conv and fc"
        )

    def _check_bounds(self) -> None:
        """Architecture values (read from model meta) at most their bounds, before any layer is
        built: the paper's net is 5 convs of <= 64 channels and FC 1164-100-50-10."""
        from traffictwin.io.limits import check_at_most

        check_at_most("Dave2Config", "height", self.height, MAX_INPUT_SIDE)
        check_at_most("Dave2Config", "width", self.width, MAX_INPUT_SIDE)
        check_at_most("Dave2Config", "len(conv)", len(self.conv), MAX_LAYERS)
        check_at_most("Dave2Config", "len(fc)", len(self.fc), MAX_LAYERS)
        for i, c in enumerate(self.conv):
            if len(c) != 3 or min(c) < 1:
                raise ValueError(
                    f"Dave2Config.conv[{i}] must be (channels, kernel, stride) >= 1, got {list(c)}"
                )
            check_at_most("Dave2Config", f"conv[{i}] channels", c[0], MAX_CONV_CHANNELS)
            check_at_most("Dave2Config", f"conv[{i}] kernel", c[1], MAX_KERNEL)
            check_at_most("Dave2Config", f"conv[{i}] stride", c[2], MAX_KERNEL)
        for i, n in enumerate(self.fc):
            if n < 1:
                raise ValueError(f"Dave2Config.fc[{i}] must be >= 1, got {n}")
            check_at_most("Dave2Config", f"fc[{i}]", n, MAX_FC_WIDTH)

    def parameter_estimate(self) -> int:
        """Weights of the network (convs and FC layers, no biases)."""
        n, cin = 0, self.in_channels
        for ch, k, _s in self.conv:
            n, cin = n + cin * ch * k * k, ch
        c, h, w = conv_output_shape(self.height, self.width, self.conv)
        width = c * h * w + int(self.use_speed)
        for out in self.fc:
            n, width = n + width * out, out
        return int(n)

    @property
    def in_channels(self) -> int:
        return sum(CHANNELS[c] for c in self.inputs)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["inputs"] = list(self.inputs)
        d["conv"] = [list(c) for c in self.conv]
        d["fc"] = list(self.fc)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Dave2Config:
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"Dave2Config: unknown field(s) {sorted(unknown)}")
        d = dict(d)
        for k in ("inputs", "fc"):
            if k in d:
                d[k] = tuple(d[k])
        if "conv" in d:
            d["conv"] = tuple(tuple(c) for c in d["conv"])
        return cls(**d)


def conv_output_shape(
    height: int, width: int, conv: Sequence[Sequence[int]] = CONV_SPEC
) -> tuple[int, int, int]:
    """(channels, height, width) after the unpadded convolution stack; error if the input is too small."""
    h, w = int(height), int(width)
    for i, (_ch, k, s) in enumerate(conv):
        h, w = (h - k) // s + 1, (w - k) // s + 1
        if h < 1 or w < 1:
            raise ValueError(
                f"input resolution {height}×{width} is too small for the DAVE-2 conv stack "
                f"(spatial size vanishes at conv layer {i + 1}); use at least ~{_min_size(conv)} px per side"
            )
    return int(conv[-1][0]), h, w


def _min_size(conv: Sequence[Sequence[int]]) -> int:
    n = 1
    for _, k, s in reversed(conv):
        n = (n - 1) * s + k
    return n
