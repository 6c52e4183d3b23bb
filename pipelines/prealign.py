"""Stage prealign@<cfg>: noisy pose of map 2 -> map 2 warped into map 1's frame -> data/prealigned/<cfg>.

Pose noise per configuration ``configurations.<cfg>`` (r m, alpha deg; sigma = r / 2.326 per
axis). The standard-normal draw of pair ``pair_id`` / draw ``d`` depends only on
``(seed, fusion_data.prealign.seed, pair_id, d)``, so val/test noise is fixed once per pair and
shared (scaled) by all configurations; train shards get ``fusion_data.prealign.train_draws``
draws per pair. Shards map 1:1 to data/fusion's shards (same index and split).
Library: :func:`traffictwin.fusion.pairs.prealign_shard`.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time

from tqdm import tqdm

from pipelines._common import ROOT, params, run_stage, setup_logging, stage_timer
from pipelines.generate_fusion import K, grid_from_params
from traffictwin.config import ConfigError, get
from traffictwin.fusion.pairs import prealign_shard
from traffictwin.io.shards import Dataset, DatasetWriter, shard_name

SRC = ROOT / "data" / "fusion"


def _work(args: tuple) -> tuple[int, str, int]:
    index, src, dst, seed, r, alpha, draws, grid, level = args
    digest, count = prealign_shard(src, dst, seed, r, alpha, draws, grid, compresslevel=level)
    return index, digest, count


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--cfg",
        required=True,
        help="pose-noise configuration (a key of `configurations` in params.yaml)",
    )
    args = ap.parse_args(argv)
    log = setup_logging()
    cfg = params()
    with stage_timer(f"prealign@{args.cfg}"):
        configs = get(cfg, "configurations", dict)
        if args.cfg not in configs:
            raise ConfigError(
                f"params.yaml: configuration '{args.cfg}' not in 'configurations' (has {sorted(configs)})"
            )
        r = get(cfg, f"configurations.{args.cfg}.r", float, min=0)
        alpha = get(cfg, f"configurations.{args.cfg}.alpha", float, min=0, max=180)
        seed = get(cfg, "seed", int, min=0)
        noise_seed = seed * 1009 + get(cfg, f"{K}.prealign.seed", int, min=0)
        train_draws = get(cfg, f"{K}.prealign.train_draws", int, min=1)
        workers = get(cfg, f"{K}.workers", int, min=1)
        level = get(cfg, f"{K}.compresslevel", int, min=0, max=9)
        grid = grid_from_params(cfg)
        src = Dataset(SRC, kind="fusion")  # verifies every shard's SHA-256
        out = ROOT / "data" / "prealigned" / args.cfg
        record = {
            "configuration": {"r": r, "alpha": alpha},
            "noise_seed": noise_seed,
            "train_draws": train_draws,
            "grid": get(cfg, "grid", dict),
            "source_manifest": src.manifest_hash(),
        }
        writer = DatasetWriter(out, "prealigned", params=record, seed=seed)
        jobs = []
        for i, sh in enumerate(src.shards):
            if writer.has_shard(i):
                continue
            draws = train_draws if sh.get("split") == "train" else 1
            jobs.append(
                (
                    i,
                    str(SRC / sh["name"]),
                    str(out / shard_name(i)),
                    noise_seed,
                    r,
                    alpha,
                    draws,
                    grid,
                    level,
                )
            )
        t0 = time.perf_counter()
        bar = tqdm(
            total=len(src.shards),
            initial=len(src.shards) - len(jobs),
            unit="shard",
            desc=f"prealign@{args.cfg}",
            file=sys.stderr,
        )
        done = []
        if workers > 1 and len(jobs) > 1:
            with mp.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
                for res in pool.imap_unordered(_work, jobs):
                    done.append(res)
                    bar.update(1)
        else:
            for job in jobs:
                done.append(_work(job))
                bar.update(1)
        bar.close()
        for i, digest, count in done:
            writer.record_shard(i, shard_name(i), digest, count, src.shards[i].get("split"))
        m = writer.finalize(extra={"configuration": args.cfg, "source": "data/fusion"})
        log.info(
            "prealign@%s: %d samples %s in %.1f s",
            args.cfg,
            m["count"],
            m["split_counts"],
            time.perf_counter() - t0,
        )


if __name__ == "__main__":
    run_stage(main, "prealign")
