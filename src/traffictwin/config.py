"""Configuration: compose ``conf/`` with Hydra, load ``params.yaml`` with checked access.

``conf/`` is the single source of truth; ``params.yaml`` is its resolved composition
(written by ``make params`` and by DVC's own Hydra composition on ``dvc exp run``).
Stages read params.yaml through :func:`load_params` and validate each group they use once, at
stage start, against a dataclass schema with :func:`typed` (schemas live beside the code that
uses them; bounds are declared with :func:`spec`): a wrong key, type or range fails before any
work, naming the dotted key. :func:`get` remains for single checked lookups.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml
from omegaconf import DictConfig, OmegaConf

from traffictwin.io.yamlio import safe_load

PROFILES = ("ci", "default", "paper")
_MISSING = object()
T = TypeVar("T")


class ConfigError(ValueError):
    """A parameter is missing, of the wrong type or out of range."""


def compose_config(
    conf_dir: str | Path, overrides: Sequence[str] = (), config_name: str = "config"
) -> dict[str, Any]:
    """Hydra composition of ``conf_dir`` with ``overrides``, resolved to plain containers."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    conf_dir = Path(conf_dir).resolve()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def dump_params(cfg: dict[str, Any], path: str | Path) -> None:
    """Write a composed config as params.yaml (atomically)."""
    from traffictwin.io.atomic import write_text_atomic

    header = (
        "# Generated from conf/ by `make params` (Hydra composition). Do not edit: edit conf/.\n"
    )
    write_text_atomic(path, header + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=False))


def load_params(path: str | Path) -> DictConfig:
    """Load a params file (the composed conf/, params.yaml) as OmegaConf and check the profile name."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: not found (run `make params` to compose it from conf/)")
    try:
        data = safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    cfg = OmegaConf.create(data)
    get(cfg, "profile.name", str, choices=PROFILES, source=path)
    get(cfg, "seed", int, min=0, source=path)
    return cfg


def get(
    cfg: Any,
    key: str,
    typ: type | tuple[type, ...] | None = None,
    *,
    min: float | None = None,
    max: float | None = None,
    choices: Iterable[Any] | None = None,
    default: Any = _MISSING,
    source: str | Path = "params.yaml",
) -> Any:
    """Fetch dotted ``key`` from ``cfg`` and check it.

    ``typ``: expected type(s) (``int`` rejects bools; ``float`` accepts ints);
    ``min``/``max``: inclusive bounds; ``choices``: allowed values.
    Raises :class:`ConfigError` naming ``source``, ``key`` and the expectation.
    """
    node: Any = cfg
    for part in key.split("."):
        if isinstance(node, (dict, DictConfig)) and part in node:
            node = node[part]
        else:
            if default is not _MISSING:
                return default
            raise ConfigError(f"{source}: key '{key}' is missing")
    value = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value, resolve=True)
    if typ is not None:
        types = typ if isinstance(typ, tuple) else (typ,)
        ok = any(_is_type(value, t) for t in types)
        if not ok:
            names = " or ".join(t.__name__ for t in types)
            raise ConfigError(
                f"{source}: '{key}' must be {names}, got {value!r} ({type(value).__name__})"
            )
        if float in types and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
    if (min is not None or max is not None) and not _finite(value):
        raise ConfigError(f"{source}: '{key}' must be a finite number, got {value!r}")
    if min is not None and value < min:
        raise ConfigError(f"{source}: '{key}' must be >= {min}, got {value!r}")
    if max is not None and value > max:
        raise ConfigError(f"{source}: '{key}' must be <= {max}, got {value!r}")
    if choices is not None:
        allowed = list(choices)
        if value not in allowed:
            raise ConfigError(f"{source}: '{key}' must be one of {allowed}, got {value!r}")
    return value


def _finite(value: Any) -> bool:
    """False for a NaN or infinite float (a bounded setting must be a number: NaN passes every
    ``<`` comparison); True for everything else."""
    import math

    return not isinstance(value, float) or math.isfinite(value)


def _is_type(value: Any, t: type) -> bool:
    if t is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if t is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if t is list:
        return isinstance(value, (list, tuple)) or OmegaConf.is_list(value)
    if t is dict:
        return isinstance(value, dict) or OmegaConf.is_dict(value)
    return isinstance(value, t)


def flatten(cfg: Any, prefix: str = "", sep: str = ".") -> dict[str, Any]:
    """Flatten nested dicts/lists to ``{"a.b.c": value}`` (for MLflow params)."""
    if isinstance(cfg, DictConfig) or OmegaConf.is_list(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    out: dict[str, Any] = {}
    if isinstance(cfg, dict):
        for k, v in cfg.items():
            out.update(flatten(v, f"{prefix}{k}{sep}", sep))
    elif isinstance(cfg, (list, tuple)) and any(isinstance(v, (dict, list)) for v in cfg):
        for i, v in enumerate(cfg):
            out.update(flatten(v, f"{prefix}{i}{sep}", sep))
    else:
        out[prefix[: -len(sep)] if prefix else ""] = cfg
    return out


# --------------------------------------------------------------------------- typed configuration
def spec(
    default: Any = dataclasses.MISSING,
    *,
    min: float | None = None,
    max: float | None = None,
    choices: Iterable[Any] | None = None,
    factory: Callable[[], Any] | None = None,
) -> Any:
    """A dataclass field with bounds, checked by :func:`typed` (``min``/``max`` inclusive).

    ``factory`` builds mutable defaults (lists, dicts, nested dataclasses).
    """
    meta = {"min": min, "max": max, "choices": None if choices is None else tuple(choices)}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def typed(node: Any, schema: type[T], *, key: str = "", source: str | Path = "params.yaml") -> T:
    """Validate ``node`` (a mapping) against the dataclass ``schema`` and return an instance.

    Unknown keys, missing keys and wrong types fail through OmegaConf's structured-config check;
    bounds declared with :func:`spec` are checked afterwards on every nested field. Every failure
    is a :class:`ConfigError` naming ``source`` and the full dotted key (``key`` prefixes it).
    """
    from omegaconf.errors import OmegaConfBaseException

    if OmegaConf.is_config(node):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, dict):
        raise ConfigError(
            f"{source}: '{key or '<root>'}' must be a mapping, got {type(node).__name__}"
        )
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), node)
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        full = ".".join(p for p in (key, str(getattr(exc, "full_key", "") or "")) if p)
        msg = str(exc).splitlines()[0]
        raise ConfigError(f"{source}: '{full or key}': {msg}") from None
    except (TypeError, ValueError) as exc:  # a schema's __post_init__ check
        raise ConfigError(f"{source}: '{key}': {exc}") from None
    _check_bounds(obj, key, source)
    return obj  # type: ignore[return-value]


def _check_bounds(obj: Any, key: str, source: str | Path) -> None:
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            full = f"{key}.{f.name}" if key else f.name
            lo, hi, choices = (
                f.metadata.get("min"),
                f.metadata.get("max"),
                f.metadata.get("choices"),
            )
            if (
                value is not None
                and not isinstance(value, (list, dict))
                and not dataclasses.is_dataclass(value)
            ):
                if (lo is not None or hi is not None) and not _finite(value):
                    raise ConfigError(f"{source}: '{full}' must be a finite number, got {value!r}")
                if lo is not None and value < lo:
                    raise ConfigError(f"{source}: '{full}' must be >= {lo}, got {value!r}")
                if hi is not None and value > hi:
                    raise ConfigError(f"{source}: '{full}' must be <= {hi}, got {value!r}")
                if choices is not None and value not in choices:
                    raise ConfigError(
                        f"{source}: '{full}' must be one of {list(choices)}, got {value!r}"
                    )
            elif isinstance(value, list):
                for i, v in enumerate(value):
                    if lo is not None and isinstance(v, (int, float)) and v < lo:
                        raise ConfigError(f"{source}: '{full}[{i}]' must be >= {lo}, got {v!r}")
                    if hi is not None and isinstance(v, (int, float)) and v > hi:
                        raise ConfigError(f"{source}: '{full}[{i}]' must be <= {hi}, got {v!r}")
                    if choices is not None and v not in choices:
                        raise ConfigError(
                            f"{source}: '{full}[{i}]' must be one of {list(choices)}, got {v!r}"
                        )
                    _check_bounds(v, f"{full}[{i}]", source)
            else:
                _check_bounds(value, full, source)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_bounds(v, f"{key}.{k}" if key else str(k), source)
