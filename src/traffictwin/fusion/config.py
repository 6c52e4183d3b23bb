"""Typed configuration of the fusion problem: schemas of ``grid``, ``configurations``,
``fusion_data`` and ``evaluation.fusion``, validated once at stage start with
:func:`traffictwin.config.typed` (bounds via :func:`~traffictwin.config.spec`).

- :func:`grid_config` — ``grid`` → :class:`~traffictwin.grid.GridSpec` (rows/cols divisible by 16);
- :func:`pose_configurations` — ``configurations`` → ``{name: PoseNoise}`` in conf order (the
  one list of pose-noise configurations);
- :func:`fusion_data_config` — ``fusion_data`` → :class:`FusionDataConfig`;
  :meth:`FusionDataConfig.params` → :class:`~traffictwin.fusion.pairs.FusionDataParams`;
- :func:`fusion_eval_config` — ``evaluation.fusion`` → :class:`FusionEvalConfig`.

Every failure is a :class:`~traffictwin.config.ConfigError` naming the dotted key.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass
from typing import Any

from traffictwin.config import ConfigError, spec, typed
from traffictwin.evidential.noise import PoseNoise
from traffictwin.fusion.refinement import RefinementParams
from traffictwin.fusion.registration import RegistrationParams
from traffictwin.grid import GridSpec

__all__ = [
    "GridConfig",
    "PoseNoise",
    "LidarConfig",
    "IsmConfig",
    "SplitsConfig",
    "PrealignConfig",
    "FigureConfig",
    "FusionDataConfig",
    "FusionEvalConfig",
    "grid_config",
    "pose_configurations",
    "fusion_data_config",
    "fusion_eval_config",
    "MIXED",
    "NETWORK_MODEL",
    "PER_CONFIG",
    "TrainingNoise",
    "training_noise",
    "training_noise_description",
    "noise_sources",
]

NETWORK_STRIDE = 16  # rows and cols of the grid must be divisible by the network's output stride
#: most cells along each side of the grid (the paper's is 256 x 176; a pair of 1024 x 1024 maps
#: is 16 MB, its shard of pairs and the network's activations grow with it). Sizes that allocate
#: (grid sides, scenario and encounter counts) are bounded here, so a typo fails at config time
#: instead of in the allocator minutes in
MAX_GRID_SIDE = 1024
MAX_SCENARIOS = 100_000  # fusion_data.scenarios (paper: 625)
MAX_ENCOUNTERS = 1_000  # fusion_data.encounters_per_scenario and scenarios_per_shard (paper: 8, 5)


@dataclass
class GridConfig:
    """``grid``: cells along x (rows) and y (cols), m per cell."""

    rows: int = spec(MISSING, min=NETWORK_STRIDE, max=MAX_GRID_SIDE)
    cols: int = spec(MISSING, min=NETWORK_STRIDE, max=MAX_GRID_SIDE)
    cell: float = spec(MISSING, min=0.01)


def grid_config(cfg: Any) -> GridSpec:
    """The checked grid of params.yaml (positive, rows/cols divisible by 16 for the network)."""
    g = typed(cfg["grid"], GridConfig, key="grid")
    grid = GridSpec(g.rows, g.cols, g.cell)
    try:
        grid.check_divisible(NETWORK_STRIDE, "params.yaml: grid")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return grid


def pose_configurations(cfg: Any) -> dict[str, PoseNoise]:
    """``configurations`` of params.yaml, checked, in conf order (at least one)."""
    node = cfg["configurations"] if "configurations" in cfg else None
    if not node:
        raise ConfigError("params.yaml: 'configurations' must name at least one configuration")
    return {str(k): typed(v, PoseNoise, key=f"configurations.{k}") for k, v in node.items()}


# -- training_noise: the one model's noise (docs/design.md "One model per task") -----------------
MIXED = (
    "mixed"  # the training set with noise drawn across the configurations: data/prealigned/mixed
)


@dataclass
class TrainingNoise:
    """``training_noise``: the pose noise the one fusion network and the one learned registration
    train on. ``configurations``: keys of ``configurations`` (None = every configuration, so a new
    one joins the mixture); ``kind``: ``mixture`` (each draw takes one of them, uniformly) or
    ``scaled`` (the largest one's noise scaled by U(0, 1)); ``draws``: noise draws per training
    pair (validation: one per pair)."""

    kind: str = spec(MISSING, choices=("mixture", "scaled"))
    configurations: list[str] | None = spec(MISSING)
    draws: int = spec(MISSING, min=1)

    def sigmas(self, configs: dict[str, PoseNoise]) -> Any:
        """``(K, 3)`` per-axis sigmas (m, m, rad) of :attr:`configurations`, in their order."""
        import numpy as np

        from traffictwin.evidential.noise import noise_sigmas

        rows = [noise_sigmas(configs[c].r, configs[c].alpha) for c in self.names(configs)]
        if self.kind == "scaled":  # the largest configuration's noise, scaled by U(0, 1)
            big = self.largest(configs)
            rows = [noise_sigmas(big.r, big.alpha)]
        return np.array([[s, s, y] for s, y in rows], dtype=np.float64)

    def names(self, configs: dict[str, PoseNoise]) -> list[str]:
        """The configurations of the mixture (every one when :attr:`configurations` is None)."""
        return list(configs) if self.configurations is None else list(self.configurations)

    def largest(self, configs: dict[str, PoseNoise]) -> PoseNoise:
        """The configuration of the set with the largest translational noise (ties: rotation)."""
        return max((configs[c] for c in self.names(configs)), key=lambda n: (n.r, n.alpha))


def training_noise(cfg: Any) -> TrainingNoise:
    """``training_noise`` of params.yaml, its configurations checked against ``configurations``."""
    if "training_noise" not in cfg:
        raise ConfigError("params.yaml: 'training_noise' is missing")
    tn = typed(cfg["training_noise"], TrainingNoise, key="training_noise")
    configs = pose_configurations(cfg)
    if tn.configurations is None:
        tn.configurations = list(configs)
    bad = [c for c in tn.configurations if c not in configs]
    if bad or not tn.configurations:
        raise ConfigError(
            f"params.yaml: 'training_noise.configurations' = {list(tn.configurations)} must name "
            f"keys of 'configurations' (has {sorted(configs)})"
        )
    if MIXED in configs:
        raise ConfigError(
            f"params.yaml: configuration name {MIXED!r} is reserved for the mixed training noise"
        )
    return tn


def training_noise_description(cfg: Any, source: str) -> dict[str, Any]:
    """The noise of training set ``source`` as a model's meta records it: one configuration's
    ``{r, alpha}`` (m, deg) or the mixture's ``{kind, configurations: {name: {r, alpha}}}``."""
    configs = pose_configurations(cfg)
    if source != MIXED:
        return {"r": configs[source].r, "alpha": configs[source].alpha}
    tn = training_noise(cfg)
    return {
        "kind": tn.kind,
        "configurations": {
            c: {"r": configs[c].r, "alpha": configs[c].alpha} for c in tn.configurations
        },
    }


def noise_sources(cfg: Any) -> list[str]:
    """Every name a training set can have: the configurations and :data:`MIXED`."""
    return [*pose_configurations(cfg), MIXED]


# -- fusion_data ---------------------------------------------------------------------------------
@dataclass
class LidarConfig:
    azimuth_res_deg: float = spec(MISSING, min=0.01, max=10.0)
    max_range: float = spec(MISSING, min=2.0)
    min_range: float = spec(MISSING, min=0.0)
    range_noise: float = spec(MISSING, min=0.0)
    dropout: float = spec(MISSING, min=0.0, max=0.99)
    height: float = spec(MISSING, min=0.1)
    uniform_elevations: bool = MISSING


@dataclass
class IsmConfig:
    p_free: float = spec(MISSING, min=0.0, max=0.99)
    p_ground: float = spec(MISSING, min=0.0, max=0.99)
    p_occ: float = spec(MISSING, min=0.0, max=0.99)
    margin: float = spec(MISSING, min=0.0)


@dataclass
class SplitsConfig:
    train: float = spec(MISSING, min=0.0, max=1.0)
    val: float = spec(MISSING, min=0.0, max=1.0)
    test: float = spec(MISSING, min=0.0, max=1.0)

    def __post_init__(self) -> None:
        fr = (self.train, self.val, self.test)
        if abs(sum(fr) - 1) > 1e-6:
            raise ValueError(f"'fusion_data.splits' must sum to 1, got {fr}")


@dataclass
class PrealignConfig:
    """``fusion_data.prealign``: the noise seed, training draws and the splits prealign@<cfg>
    writes (the per-configuration train split only feeds the ablation's per-configuration
    networks; evaluation and the promotion gate read val and test)."""

    seed: int = spec(MISSING, min=0)
    train_draws: int = spec(MISSING, min=1)
    splits: list[str] = spec(MISSING)

    def __post_init__(self) -> None:
        bad = [s for s in self.splits if s not in ("train", "val", "test")]
        if bad or not self.splits:
            raise ValueError(
                f"'fusion_data.prealign.splits' must name train / val / test, got {self.splits}"
            )


@dataclass
class RegisterConfig:
    """``fusion_data.register``: stage register@<cfg> (training data of ``registered+network``)."""

    configurations: list[str] = spec(MISSING)
    max_train_pairs: int | None = spec(MISSING, min=1)
    max_val_pairs: int | None = spec(MISSING, min=1)


@dataclass
class FigureConfig:
    samples: int = spec(MISSING, min=1)


@dataclass
class FusionDataConfig:
    """``fusion_data`` (conf/fusion_data/base.yaml documents every key)."""

    scenarios: int = spec(MISSING, min=1, max=MAX_SCENARIOS)
    scenarios_per_shard: int = spec(MISSING, min=1, max=MAX_ENCOUNTERS)
    encounters_per_scenario: int = spec(MISSING, min=1, max=MAX_ENCOUNTERS)
    encounter_spacing: float = spec(MISSING, min=0.0)
    t_meet: float = spec(MISSING, min=0.0)
    meet_distance: list[float] = spec(MISSING, min=0.0)
    templates: list[str] = spec(MISSING)
    splits: SplitsConfig = MISSING
    workers: int = spec(MISSING, min=1)
    compresslevel: int = spec(MISSING, min=0, max=9)
    traffic: dict[str, Any] = spec(MISSING)
    lidar: LidarConfig = MISSING
    ism: IsmConfig = MISSING
    prealign: PrealignConfig = MISSING
    register: RegisterConfig = MISSING
    figure: FigureConfig = MISSING

    def __post_init__(self) -> None:
        from traffictwin.sim.traffic import DEFAULT_DENSITY
        from traffictwin.sim.world import TEMPLATES

        lid = self.lidar
        if not lid.max_range > lid.min_range:
            raise ValueError(
                f"'fusion_data.lidar.min_range' ({lid.min_range} m) must be below "
                f"'fusion_data.lidar.max_range' ({lid.max_range} m)"
            )
        if abs(360.0 / lid.azimuth_res_deg - round(360.0 / lid.azimuth_res_deg)) > 1e-6:
            raise ValueError(
                f"'fusion_data.lidar.azimuth_res_deg' must divide 360 deg, got {lid.azimuth_res_deg}"
            )
        bad = [t for t in self.templates if t not in TEMPLATES]
        if bad or not self.templates:
            raise ValueError(
                f"'fusion_data.templates' has unknown template name(s) {bad or '(empty)'}; expected from {list(TEMPLATES)}"
            )
        md = self.meet_distance
        if len(md) != 2 or not 0 <= md[0] < md[1]:
            raise ValueError(
                f"'fusion_data.meet_distance' must be [min, max] m with 0 <= min < max, got {md}"
            )
        if self.scenarios_per_shard >= 1 and self.scenarios % self.scenarios_per_shard:
            raise ValueError(
                f"'fusion_data.scenarios' ({self.scenarios}) must be a multiple of "
                f"'fusion_data.scenarios_per_shard' ({self.scenarios_per_shard})"
            )
        unknown = sorted(set(self.traffic) - set(DEFAULT_DENSITY))
        if unknown:  # the simulator's density keys: fail now, not inside a worker
            raise ValueError(
                f"'fusion_data.traffic' has unknown key(s) {unknown}; expected from {sorted(DEFAULT_DENSITY)}"
            )

    @property
    def n_shards(self) -> int:
        return self.scenarios // self.scenarios_per_shard

    @property
    def split_fractions(self) -> tuple[float, float, float]:
        return (self.splits.train, self.splits.val, self.splits.test)

    def params(self, grid: GridSpec) -> Any:
        """The shard parameters (:class:`~traffictwin.fusion.pairs.FusionDataParams`) on ``grid``."""
        from traffictwin.evidential.ism import IsmParams
        from traffictwin.fusion.pairs import FusionDataParams
        from traffictwin.sim.lidar import LidarSpec

        lid, ism = self.lidar, self.ism
        return FusionDataParams(
            grid=grid,
            lidar=LidarSpec(
                azimuth_res_deg=lid.azimuth_res_deg,
                max_range=lid.max_range,
                min_range=lid.min_range,
                range_noise=lid.range_noise,
                dropout=lid.dropout,
                height=lid.height,
                uniform=lid.uniform_elevations,
            ),
            ism=IsmParams(
                p_free=ism.p_free, p_ground=ism.p_ground, p_occ=ism.p_occ, margin=ism.margin
            ),
            scenarios_per_shard=self.scenarios_per_shard,
            encounters_per_scenario=self.encounters_per_scenario,
            encounter_spacing=self.encounter_spacing,
            t_meet=self.t_meet,
            meet_distance=(float(self.meet_distance[0]), float(self.meet_distance[1])),
            density={
                k: (tuple(v) if isinstance(v, (list, tuple)) else float(v))
                for k, v in self.traffic.items()
            },
            templates=tuple(self.templates),
        )


def fusion_data_config(cfg: Any) -> FusionDataConfig:
    """``fusion_data`` of params.yaml, checked."""
    return typed(cfg["fusion_data"], FusionDataConfig, key="fusion_data")


# -- evaluation.fusion ---------------------------------------------------------------------------
@dataclass
class FusionEvalConfig:
    """``evaluation.fusion`` (conf/evaluation/base.yaml documents every key). The configurations
    evaluated are the keys of ``configurations``."""

    split: str = spec(MISSING, choices=("train", "val", "test"))
    max_pairs: int | None = spec(MISSING, min=1)
    registered_max_pairs: int | None = spec(MISSING, min=1)
    cross_max_pairs: int | None = spec(MISSING, min=1)
    batch_size: int = spec(MISSING, min=1)
    device: str = MISSING
    kld_eps: float = spec(MISSING, min=0.0, max=0.1)
    auroc_bins: int = spec(MISSING, min=2)
    auroc_min_wrong: int = spec(MISSING, min=1)  # AUROC(u) withheld below this many wrong cells
    auroc_min_pairs: int = spec(MISSING, min=1)  # ... or wrong cells in fewer pairs than this
    trans_bins_m: list[float] = spec(MISSING, min=0.0)
    rot_bins_deg: list[float] = spec(MISSING, min=0.0)
    success_trans_m: float = spec(MISSING, min=0.0)
    success_rot_deg: float = spec(MISSING, min=0.0)
    qualitative_fraction: float = spec(MISSING, min=0.0, max=1.0)
    qualitative_pair: int = spec(MISSING, min=0)
    registration: dict[str, Any] = spec(
        MISSING
    )  # RegistrationParams fields (defaults for the rest)
    registration_workers: int = spec(MISSING, min=1)  # processes of the classical registration
    refinement: dict[str, Any] = spec(
        MISSING
    )  # RefinementParams fields: the ECC refinement of the learned registration's pose
    validation: dict[str, Any] = spec(
        MISSING
    )  # split, max_pairs, registration_grid, refinement_grid: settings chosen before the test pass

    def __post_init__(self) -> None:
        self.registration_params  # noqa: B018  (checks the keys and values now)
        self.refinement_params  # noqa: B018
        v = self.validation
        need = {"split", "max_pairs", "registration_grid", "refinement_grid"}
        if set(v) != need:
            raise ValueError(
                f"'evaluation.fusion.validation' must have exactly the keys {sorted(need)}, got {sorted(v)}"
            )
        if v["split"] == self.split:
            raise ValueError(
                f"'evaluation.fusion.validation.split' must differ from the evaluated split "
                f"'{self.split}' (settings are chosen on other pairs than they are judged on)"
            )
        if v["max_pairs"] is not None and int(v["max_pairs"]) < 1:
            raise ValueError(
                f"'evaluation.fusion.validation.max_pairs' must be >= 1 or null, got {v['max_pairs']}"
            )
        for k in ("registration_grid", "refinement_grid"):
            bad = {
                f: c for f, c in (v[k] or {}).items() if not isinstance(c, (list, tuple)) or not c
            }
            if bad:
                raise ValueError(
                    f"'evaluation.fusion.validation.{k}': each field needs a non-empty list of candidates, got {bad}"
                )

    @property
    def refinement_params(self) -> RefinementParams:
        """``refinement`` as :class:`~traffictwin.fusion.refinement.RefinementParams`."""
        try:
            return RefinementParams(**self.refinement)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"'evaluation.fusion.refinement': {exc}") from None

    @property
    def registration_params(self) -> RegistrationParams:
        """``registration`` as :class:`~traffictwin.fusion.registration.RegistrationParams`."""
        try:
            return RegistrationParams(**self.registration)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"'evaluation.fusion.registration': {exc}") from None


def fusion_eval_config(cfg: Any) -> FusionEvalConfig:
    """``evaluation.fusion`` of params.yaml, checked."""
    return typed(cfg["evaluation"]["fusion"], FusionEvalConfig, key="evaluation.fusion")


# -- fusion_variants -----------------------------------------------------------------------------
INPUT_METHODS = {"prealigned": "dnn", "registered": "registered+network"}  # data family -> method


@dataclass
class FusionVariant:
    """``fusion_variants.<name>``: a fusion network trained beside the one network (``train_fusion``).

    config: the noise of its training pairs, ``mixed`` (``training_noise``: evaluated at every
    configuration, like the one network) or one pose-noise configuration (a key of
    ``configurations``: a per-configuration network, evaluated at that configuration only, as the
    paper trained them); inputs: ``prealigned`` (map 2 warped by the noisy pose,
    ``data/prealigned/<config>``; evaluated as method ``dnn``) or ``registered`` (map 2 warped by
    the classical registration estimate, ``data/registered/<config>``; method
    ``registered+network``, row ``registered+network[registered-trained]``: the default hybrid is
    the one network on registered pairs); loss: ``fusion_model.loss.name`` for this network
    (null = default; a registered loss, :data:`~traffictwin.fusion.loss_registry.LOSSES`: checked
    with ``fusion_model`` by :meth:`~traffictwin.fusion.model_config.FusionModelConfig.hparams`,
    so the data stages that read the variants do not depend on the losses).
    """

    config: str = spec(MISSING)
    inputs: str = spec(MISSING, choices=tuple(INPUT_METHODS))
    loss: str | None = spec(None)

    @property
    def method(self) -> str:
        """The registry method that runs it: ``dnn`` or ``registered+network``."""
        return INPUT_METHODS[self.inputs]


PER_CONFIG = "per-config"  # row tag of networks trained on one configuration's noise only
REGISTERED_TRAINED = "registered-trained"  # row tag of networks trained on registered pairs


def variant_row(method: str, loss: str | None, default_loss: str, per_config: bool = False) -> str:
    """The evaluation's row name of a variant network: ``method[tags]`` with the tags
    ``registered-trained`` (a ``registered+network`` variant: a network of its own, trained on
    registered pairs; plain ``registered+network`` is the one network on registered pairs),
    ``per-config`` (trained on one configuration's noise) and the loss (when not the default):
    ``dnn[paper]``, ``dnn[per-config]``, ``registered+network[registered-trained]``; a
    prealigned variant with neither tag is plain ``dnn``."""
    tags = [REGISTERED_TRAINED] if method == INPUT_METHODS["registered"] else []
    tags += [PER_CONFIG] if per_config else []
    if loss not in (None, default_loss):
        tags.append(str(loss))
    return f"{method}[{','.join(tags)}]" if tags else method


def fusion_variants(cfg: Any) -> dict[str, FusionVariant]:
    """``fusion_variants`` of params.yaml, checked against ``configurations`` and the registered
    configurations (``fusion_data.register.configurations``); may be empty."""
    node = cfg["fusion_variants"] if "fusion_variants" in cfg else None
    configs = pose_configurations(cfg)
    registered = registered_configurations(cfg)
    out: dict[str, FusionVariant] = {}
    for k, v in (node or {}).items():
        var = typed(v, FusionVariant, key=f"fusion_variants.{k}")
        if var.config not in configs and var.config != MIXED:
            raise ConfigError(
                f"params.yaml: 'fusion_variants.{k}.config' = {var.config!r} is neither {MIXED!r} "
                f"nor a key of 'configurations' (has {sorted(configs)})"
            )
        if var.inputs == "registered" and var.config not in registered:
            raise ConfigError(
                f"params.yaml: 'fusion_variants.{k}' trains on registered pairs of {var.config!r}, "
                f"but 'fusion_data.register.configurations' is {registered}"
            )
        if str(k) == NETWORK_MODEL:
            raise ConfigError(
                f"params.yaml: 'fusion_variants.{k}' clashes with the one network (models/fusion/{k})"
            )
        out[str(k)] = var
    return out


NETWORK_MODEL = "network"  # models/fusion/network: the one fusion network (stage train_fusion)


def registered_configurations(cfg: Any) -> list[str]:
    """``fusion_data.register.configurations``: training sets (``mixed`` or configurations) whose
    pairs are also registered."""
    sources = noise_sources(cfg)
    reg = typed(cfg["fusion_data"]["register"], RegisterConfig, key="fusion_data.register")
    bad = [c for c in reg.configurations if c not in sources]
    if bad:
        raise ConfigError(
            f"params.yaml: 'fusion_data.register.configurations' has {bad}, neither {MIXED!r} nor "
            f"keys of 'configurations' (has {sorted(pose_configurations(cfg))})"
        )
    return list(reg.configurations)
