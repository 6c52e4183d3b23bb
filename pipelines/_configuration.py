"""``--cfg NAME`` of the per-configuration fusion stages (prealign@<cfg>, register@<set>)."""

from __future__ import annotations

import argparse

from omegaconf import DictConfig

from traffictwin.config import ConfigError
from traffictwin.evidential.noise import PoseNoise
from traffictwin.fusion.config import pose_configurations

from ._common import params


def configuration(
    argv: list[str] | None, description: str, extra: tuple[str, ...] = ()
) -> tuple[str, PoseNoise | None, DictConfig]:
    """``--cfg NAME`` of a per-configuration stage: the name, its checked pose noise, the params.

    ``extra``: further accepted names (e.g. ``mixed``, the one model's training set), returned
    with noise ``None``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument(
        "--cfg",
        required=True,
        help="pose-noise configuration (a key of `configurations` in params.yaml)",
    )
    name = ap.parse_args(argv).cfg
    p = params()
    configs = pose_configurations(p)
    if name in extra:
        return name, None, p
    if name not in configs:
        also = f" or one of {list(extra)}" if extra else ""
        raise ConfigError(
            f"params.yaml: configuration '{name}' not in 'configurations' (has {sorted(configs)}){also}"
        )
    return name, configs[name], p
