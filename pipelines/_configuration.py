"""``--cfg NAME`` of the per-configuration fusion stages (prealign@<cfg>, train_fusion@<cfg>)."""

from __future__ import annotations

import argparse

from omegaconf import DictConfig

from traffictwin.config import ConfigError
from traffictwin.evidential.noise import PoseNoise
from traffictwin.fusion.config import pose_configurations

from ._common import params


def configuration(argv: list[str] | None, description: str) -> tuple[str, PoseNoise, DictConfig]:
    """``--cfg NAME`` of a per-configuration stage: the name, its checked pose noise, the params."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument(
        "--cfg",
        required=True,
        help="pose-noise configuration (a key of `configurations` in params.yaml)",
    )
    name = ap.parse_args(argv).cfg
    p = params()
    configs = pose_configurations(p)
    if name not in configs:
        raise ConfigError(
            f"params.yaml: configuration '{name}' not in 'configurations' (has {sorted(configs)})"
        )
    return name, configs[name], p
