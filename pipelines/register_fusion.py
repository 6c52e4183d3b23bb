"""Stage register@<set>: map 2 registered onto map 1 (Fourier-Mellin + ECC) -> data/registered/<set>.

``<set>``: a training set of data/prealigned, ``mixed`` (the one model's noise mixture) or a
configuration.

Training data of the hybrid ``registered+network`` (``fusion_variants`` with ``inputs:
registered``): the pairs of ``data/prealigned/<cfg>`` (the same noise draws), map 2 registered from
the noisy pose with ``evaluation.fusion.registration`` (the `registered` baseline's settings) and
warped by the pose it accepts. ``fusion_data.register.max_train_pairs`` / ``max_val_pairs`` evenly
spaced pairs of the train / val splits (registration costs ~80 ms per pair); test pairs are
registered by evaluate_fusion itself. Same shard schema as data/prealigned (+ rel_pose_registered,
reg_accepted). Library: :func:`traffictwin.fusion.registration_batches.register_prealigned`.
"""

from __future__ import annotations

import time

import numpy as np

from pipelines._common import WORKER_STATE, map_shards, run_stage, setup_logging, stage_timer
from pipelines._configuration import configuration
from pipelines._paths import FUSION_DATA, prealigned, registered
from traffictwin.config import ConfigError, get
from traffictwin.fusion.config import (
    MIXED,
    fusion_data_config,
    fusion_eval_config,
    grid_config,
    registered_configurations,
)
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.fusion.registration_batches import register_prealigned
from traffictwin.io.shards import (
    Dataset,
    DatasetError,
    DatasetWriter,
    shard_name,
    write_npz_deterministic,
)

CHUNK = 32  # pairs per output shard (and per worker task)
SPLITS = ("train", "val")


def _work(index: int) -> tuple[int, str, int]:
    import cv2

    cv2.setNumThreads(1)
    s = WORKER_STATE
    sl = s["chunks"][index]
    arrays = {k: v[sl] for k, v in s["arrays"].items()}
    out = register_prealigned(arrays, s["map2"][sl], s["grid"], s["params"])
    digest = write_npz_deterministic(s["out"] / shard_name(index), out, compresslevel=s["level"])
    return index, digest, len(out["inputs"])


def main(argv: list[str] | None = None) -> None:
    name, _, cfg = configuration(argv, __doc__.splitlines()[0], extra=(MIXED,))
    log = setup_logging()
    if name not in registered_configurations(cfg):
        raise ConfigError(
            f"params.yaml: configuration {name!r} is not in 'fusion_data.register.configurations'"
        )
    with stage_timer(f"register@{name}"):
        seed = get(cfg, "seed", int, min=0)
        fd = fusion_data_config(cfg)
        reg = fusion_eval_config(cfg).registration_params
        grid = grid_config(cfg)
        src = Dataset(prealigned(name), kind="prealigned")
        raw = Dataset(FUSION_DATA, kind="fusion")
        limits = {"train": fd.register.max_train_pairs, "val": fd.register.max_val_pairs}
        parts, map2, chunks, splits = [], [], [], []
        start = 0
        for split in SPLITS:
            a = src.load_all(split)
            if not len(a.get("pair_id", ())):
                raise DatasetError(f"{src.root}: split '{split}' is empty")
            idx = evenly_spaced(len(a["pair_id"]), limits[split])
            a = {k: v[idx] for k, v in a.items()}
            r = raw.load_all(split, keys=["map2", "pair_id"])
            where = {int(p): i for i, p in enumerate(r["pair_id"])}
            missing = [int(p) for p in a["pair_id"] if int(p) not in where]
            if missing:
                raise DatasetError(
                    f"{raw.root}: pair ids {missing[:5]} of {src.root} missing in split '{split}' (stale data?)"
                )
            map2.append(r["map2"][[where[int(p)] for p in a["pair_id"]]])
            parts.append(a)
            n = len(a["pair_id"])
            for s0 in range(0, n, CHUNK):  # shards never straddle splits
                chunks.append(slice(start + s0, start + min(n, s0 + CHUNK)))
                splits.append(split)
            start += n
        arrays = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        out = registered(name)
        record = {
            "configuration": name,
            "source_manifest": src.manifest_hash(),
            "registration": reg.__dict__,
            "limits": limits,
        }
        writer = DatasetWriter(out, "prealigned", params=record, seed=seed)
        state = {
            "chunks": chunks,
            "arrays": arrays,
            "map2": np.concatenate(map2),
            "grid": grid,
            "params": reg,
            "out": out,
            "level": fd.compresslevel,
        }
        todo = [i for i in range(len(chunks)) if not writer.has_shard(i)]
        t0 = time.perf_counter()
        for i, digest, count in map_shards(
            _work, todo, workers=fd.workers, state=state, desc=f"register@{name}"
        ):
            writer.record_shard(i, shard_name(i), digest, count, splits[i])
        m = writer.finalize(extra={"configuration": name, "source": f"data/prealigned/{name}"})
        log.info(
            "register@%s: %d pairs %s in %.1f s",
            name,
            m["count"],
            m["split_counts"],
            time.perf_counter() - t0,
        )


if __name__ == "__main__":
    run_stage(main, "register")
