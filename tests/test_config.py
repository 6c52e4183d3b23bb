"""params.yaml is the composition of conf/; the loader names bad keys."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from traffictwin.config import ConfigError, compose_config, flatten, get, load_params

ROOT = Path(__file__).resolve().parents[1]


def test_params_yaml_equals_composition_of_conf(tmp_path: Path) -> None:
    """The committed params.yaml is the composition of the committed conf/ (read from git: a run
    in this checkout, e.g. the Quick start's `dvc exp run -S profile=ci`, rewrites the workspace's)."""
    from conftest import committed, committed_tree

    params = yaml.safe_load(committed("params.yaml"))
    composed = compose_config(committed_tree("conf", tmp_path))
    assert params == composed, "params.yaml is stale: run `make params` after editing conf/"


@pytest.mark.parametrize("profile", ["ci", "default", "paper"])
def test_every_profile_composes(profile: str) -> None:
    cfg = compose_config(ROOT / "conf", [f"profile={profile}"])
    assert cfg["profile"]["name"] == profile


def test_paper_profile_uses_gpu_trainer() -> None:
    cfg = compose_config(ROOT / "conf", ["profile=paper"])
    assert cfg["trainer"]["accelerator"] == "gpu"


def test_unknown_profile_is_rejected_by_hydra() -> None:
    with pytest.raises(Exception, match="nope"):
        compose_config(ROOT / "conf", ["profile=nope"])


def test_load_params_rejects_unknown_profile(tmp_path: Path) -> None:
    cfg = compose_config(ROOT / "conf")
    cfg["profile"]["name"] = "huge"
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError, match=r"profile\.name.*one of"):
        load_params(p)


def test_load_params_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "params.yaml")


def test_get_checks_type_range_and_presence() -> None:
    cfg = {"a": {"n": -3, "flag": True, "x": 2, "name": "q"}}
    with pytest.raises(ConfigError, match=r"'a\.n' must be >= 1, got -3"):
        get(cfg, "a.n", int, min=1)
    with pytest.raises(ConfigError, match=r"'a\.flag' must be int"):
        get(cfg, "a.flag", int)
    with pytest.raises(ConfigError, match=r"key 'a\.missing' is missing"):
        get(cfg, "a.missing", int)
    with pytest.raises(ConfigError, match="one of"):
        get(cfg, "a.name", str, choices=["p"])
    assert get(cfg, "a.x", float) == 2.0 and isinstance(get(cfg, "a.x", float), float)
    assert get(cfg, "a.missing", int, default=7) == 7


def test_flatten() -> None:
    assert flatten({"a": {"b": 1, "c": [1, 2]}, "d": "x"}) == {"a.b": 1, "a.c": [1, 2], "d": "x"}
