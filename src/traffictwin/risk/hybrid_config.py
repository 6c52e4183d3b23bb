"""The corridor hybrid risk predictor's features and training, :class:`HybridConfig` (the
``risk_hybrid`` group), without torch: :mod:`traffictwin.risk.predictors` builds and trains the
hybrid from it, and ``check_params`` validates ``risk_hybrid`` with it before any stage runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

#: the disparities a rule or hybrid can read: SGM's, or the learned stereo network's
#: (data/stereo_learned; ``traffictwin risk`` computes whichever the model reads)
HYBRID_DISPARITIES = ("disp_sgm", "disp_learned")


@dataclass(frozen=True)
class HybridConfig:
    """The hybrid's features and training. ``half_widths``: straight corridors (m);
    ``bin_edges``: lateral strips (m, left positive); ``max_distance``: distances beyond are
    "nothing" (m); ``speed_scale``: m/s → input; ``hidden``: MLP width (two hidden layers);
    ``epochs``/``batch_size``/``lr``/``weight_decay``: AdamW; ``huber_delta``: Huber loss on
    log THW (log s); ``thw_cap_s``: the THW that stands for "nothing ahead" (s); ``disparity``:
    the disparity the features are read from (one of :data:`HYBRID_DISPARITIES`)."""

    half_widths: tuple[float, ...] = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
    bin_edges: tuple[float, ...] = (-2.5, -1.5, -1.0, -0.5, 0.5, 1.0, 1.5, 2.5)
    max_distance: float = 80.0
    speed_scale: float = 30.0
    hidden: int = 64
    epochs: int = 200
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-3
    huber_delta: float = 0.5
    thw_cap_s: float = 10.0
    disparity: str = "disp_sgm"

    def __post_init__(self) -> None:
        if self.disparity not in HYBRID_DISPARITIES:
            raise ValueError(
                f"'disparity' must be one of {list(HYBRID_DISPARITIES)}, got {self.disparity!r}"
            )
        if not self.half_widths or any(w <= 0 for w in self.half_widths):
            raise ValueError(f"'half_widths' must be metres > 0, got {list(self.half_widths)}")
        e = list(self.bin_edges)
        if len(e) < 2 or any(b <= a for a, b in zip(e, e[1:])):
            raise ValueError(f"'bin_edges' must be >= 2 increasing metres, got {e}")
        for k in ("max_distance", "speed_scale", "lr", "huber_delta", "thw_cap_s"):
            if not getattr(self, k) > 0:
                raise ValueError(f"'{k}' must be > 0, got {getattr(self, k)}")
        for k in ("hidden", "epochs", "batch_size"):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"'{k}' must be >= 1, got {getattr(self, k)}")
        if self.weight_decay < 0:
            raise ValueError(f"'weight_decay' must be >= 0, got {self.weight_decay}")

    @property
    def n_features(self) -> int:
        return 1 + 2 * (len(self.half_widths) + len(self.bin_edges) - 1)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["half_widths"] = list(self.half_widths)
        d["bin_edges"] = list(self.bin_edges)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> HybridConfig:
        d = dict(d)
        for k in ("half_widths", "bin_edges"):
            if k in d:
                d[k] = tuple(float(v) for v in d[k])
        return cls(**d)
