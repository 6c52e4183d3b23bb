"""Stage prealign@<cfg>: noisy pose of map 2 -> map 2 warped into map 1's frame -> data/prealigned/<cfg>.

``--cfg A`` (a key of ``configurations``): pose noise of that configuration (r m, alpha deg;
sigma = r / 2.326 per axis), the splits ``fusion_data.prealign.splits`` (val and test in the
default run: the train split feeds only the ablation's per-configuration networks); train shards
get ``fusion_data.prealign.train_draws`` draws per pair. ``--cfg mixed``: the one model's training set (``training_noise``), train and
val splits only: each draw takes its noise level from the mixture
(:func:`traffictwin.evidential.noise.noise_scales`), ``training_noise.draws`` draws per training
pair. The standard-normal draw of pair ``pair_id`` / draw ``d`` depends only on
``(seed, fusion_data.prealign.seed, pair_id, d)``, so val/test noise is fixed once per pair and
shared (scaled) by all configurations. Shards map 1:1 to data/fusion's shards (same index and split).
Library: :func:`traffictwin.fusion.pairs.prealign_shard` (one pair: :func:`~traffictwin.fusion.pairs.prealign`).
"""

from __future__ import annotations

import time

from omegaconf import OmegaConf

from pipelines._common import (
    WORKER_STATE,
    map_shards,
    run_stage,
    setup_logging,
    stage_timer,
)
from pipelines._configuration import configuration
from pipelines._paths import FUSION_DATA, prealigned
from traffictwin.config import get
from traffictwin.fusion.config import (
    MIXED,
    fusion_data_config,
    grid_config,
    pose_configurations,
    training_noise,
)
from traffictwin.fusion.pairs import ShardNoise, prealign_shard
from traffictwin.io.shards import Dataset, DatasetWriter, shard_name


def _work(index: int) -> tuple[int, str, int]:
    s = WORKER_STATE
    noise = ShardNoise(s["seed"], s["draws"][index], s["r"], s["alpha"], s["mixture"])
    digest, count = prealign_shard(
        str(FUSION_DATA / s["names"][index]),
        str(s["out"] / shard_name(index)),
        noise,
        s["grid"],
        compresslevel=s["level"],
    )
    return index, digest, count


def main(argv: list[str] | None = None) -> None:
    name, noise, cfg = configuration(argv, __doc__.splitlines()[0], extra=(MIXED,))
    log = setup_logging()
    with stage_timer(f"prealign@{name}"):
        seed = get(cfg, "seed", int, min=0)
        fd = fusion_data_config(cfg)
        noise_seed = seed * 1009 + fd.prealign.seed
        grid = grid_config(cfg)
        src = Dataset(FUSION_DATA, kind="fusion")  # verifies every shard's SHA-256
        out = prealigned(name)
        if name == MIXED:
            tn = training_noise(cfg)
            configs = pose_configurations(cfg)
            mixture = (tn.sigmas(configs), tn.kind)
            train_draws, splits = tn.draws, ("train", "val")
            described = {
                "training_noise": {
                    "kind": tn.kind,
                    "configurations": {
                        c: {"r": configs[c].r, "alpha": configs[c].alpha} for c in tn.configurations
                    },
                }
            }
            r = alpha = 0.0
        else:
            mixture, train_draws, splits = None, fd.prealign.train_draws, tuple(fd.prealign.splits)
            described = {"configuration": {"r": noise.r, "alpha": noise.alpha}}
            r, alpha = noise.r, noise.alpha
        record = {
            **described,
            "noise_seed": noise_seed,
            "train_draws": train_draws,
            "grid": OmegaConf.to_container(cfg["grid"], resolve=True),
            "source_manifest": src.manifest_hash(),
        }
        writer = DatasetWriter(out, "prealigned", params=record, seed=seed)
        wanted = [i for i, sh in enumerate(src.shards) if sh.get("split") in splits]
        todo = [i for i in wanted if not writer.has_shard(i)]
        state = {
            "names": [sh["name"] for sh in src.shards],
            "draws": [train_draws if sh.get("split") == "train" else 1 for sh in src.shards],
            "out": out,
            "seed": noise_seed,
            "r": r,
            "alpha": alpha,
            "mixture": mixture,
            "grid": grid,
            "level": fd.compresslevel,
        }
        t0 = time.perf_counter()
        for i, digest, count in map_shards(
            _work, todo, workers=fd.workers, state=state, desc=f"prealign@{name}"
        ):
            writer.record_shard(i, shard_name(i), digest, count, src.shards[i].get("split"))
        m = writer.finalize(extra={"configuration": name, "source": "data/fusion"})
        log.info(
            "prealign@%s: %d samples %s in %.1f s",
            name,
            m["count"],
            m["split_counts"],
            time.perf_counter() - t0,
        )


if __name__ == "__main__":
    run_stage(main, "prealign")
