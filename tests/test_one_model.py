"""One model per task (docs/design.md "One model per task"): the training-noise mixture, the
mixed training set, the precision choice, the one training driver and the registrations computed
once per pair / frame."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from traffictwin import resume
from traffictwin import trainer as common
from traffictwin.config import ConfigError
from traffictwin.evidential.noise import noise_sigmas
from traffictwin.fusion.config import (
    MIXED,
    training_noise,
    training_noise_description,
)
from traffictwin.grid import GridSpec

CONFIGS = {
    "A": {"r": 0.0, "alpha": 0.0},
    "B": {"r": 1.0, "alpha": 10.0},
    "D": {"r": 5.0, "alpha": 20.0},
}


def _cfg(**tn) -> object:
    return OmegaConf.create(
        {
            "configurations": CONFIGS,
            "training_noise": {"kind": "mixture", "configurations": None, "draws": 2, **tn},
        }
    )


# -- the training-noise mixture ------------------------------------------------------------------
def test_training_noise_defaults_to_every_configuration_and_checks_names() -> None:
    tn = training_noise(_cfg())
    assert tn.configurations == ["A", "B", "D"] and tn.draws == 2
    want = []
    for v in CONFIGS.values():
        s, y = noise_sigmas(v["r"], v["alpha"])
        want.append([s, s, y])
    np.testing.assert_allclose(tn.sigmas(_noise()), want)
    assert training_noise(_cfg(configurations=["B", "D"])).configurations == ["B", "D"]
    with pytest.raises(ConfigError, match="training_noise.configurations.*'Q'"):
        training_noise(_cfg(configurations=["A", "Q"]))
    with pytest.raises(ConfigError, match="training_noise.kind"):
        training_noise(_cfg(kind="gaussian"))
    bad = _cfg()
    bad.configurations[MIXED] = {"r": 1.0, "alpha": 1.0}
    with pytest.raises(ConfigError, match="'mixed' is reserved"):
        training_noise(bad)


def _noise() -> dict:
    from traffictwin.fusion.config import pose_configurations

    return pose_configurations(_cfg())


def test_scaled_kind_uses_the_largest_configuration_and_meta_describes_the_mixture() -> None:
    tn = training_noise(_cfg(kind="scaled"))
    assert (tn.largest(_noise()).r, tn.largest(_noise()).alpha) == (5.0, 20.0)
    s, y = noise_sigmas(5.0, 20.0)
    np.testing.assert_allclose(tn.sigmas(_noise()), [[s, s, y]])
    d = training_noise_description(_cfg(), MIXED)
    assert d == {"kind": "mixture", "configurations": CONFIGS}
    assert training_noise_description(_cfg(), "B") == CONFIGS["B"]


def test_prealign_shard_draws_each_rows_noise_level_from_the_mixture(tmp_path: Path) -> None:
    from traffictwin.evidential.dempster import dempster
    from traffictwin.fusion.pairs import ShardNoise, prealign_shard
    from traffictwin.io.shards import read_npz, write_npz_deterministic

    rng = np.random.default_rng(0)
    n, grid = 12, GridSpec(32, 32, 0.5)
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(n, 2, 32, 32))
    maps = np.moveaxis(d[..., :2], -1, 2).astype(np.float32)
    poses = np.zeros((n, 3))
    shard = {
        "map1": maps[:, 0],
        "map2": maps[:, 1],
        "label": np.asarray(dempster(maps[:, 0], maps[:, 1]), np.float32),
        "pose1": poses,
        "pose2": poses,
        "scenario": np.arange(n) // 4,
        "pair_id": 1000 * (np.arange(n) // 4) + np.arange(n) % 4,
    }
    write_npz_deterministic(tmp_path / "src.npz", shard)
    sig = training_noise(_cfg()).sigmas(_noise())
    out = tmp_path / "dst.npz"
    noise = ShardNoise(seed=7, draws=2, mixture=(sig, "mixture"))
    digest, count = prealign_shard(str(tmp_path / "src.npz"), str(out), noise, grid)
    a = read_npz(out)
    assert count == 2 * n and len(a["noise"]) == 2 * n
    # each row's noise = its standard-normal direction x one configuration's sigmas (stored)
    assert ((a["noise_sigma"][:, None, :] == sig[None]).all(-1).sum(1) == 1).all()
    z = a["noise"] / np.where(a["noise_sigma"] > 0, a["noise_sigma"], 1.0)
    assert np.all(np.abs(z[a["noise_sigma"][:, 0] > 0]) < 6)
    assert (a["noise"][a["noise_sigma"][:, 0] == 0] == 0).all()  # A: exactly noise-free
    # deterministic: the same bytes again
    again = tmp_path / "again.npz"
    assert prealign_shard(str(tmp_path / "src.npz"), str(again), noise, grid) == (digest, count)


# -- precision ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("flags", "want"),
    [
        ("fpu sse avx512f avx512_bf16 avx512_vnni", "bf16-mixed"),
        ("fpu sse amx_bf16 amx_tile", "bf16-mixed"),
        ("fpu sse avx2 avx512f avx512bw", "32-true"),  # bf16 emulated: slower than fp32
    ],
)
def test_auto_precision_is_bf16_only_with_native_bf16(tmp_path: Path, flags: str, want: str):
    info = tmp_path / "cpuinfo"
    info.write_text(f"processor\t: 0\nmodel name\t: X\nflags\t\t: {flags}\n")
    assert common.native_bf16_cpu(info) == (want == "bf16-mixed")
    assert common.resolve_precision("auto", "cpu", info) == want
    assert common.resolve_precision("32-true", "cpu", info) == "32-true"  # explicit: kept
    assert common.resolve_precision("bf16-mixed", "cpu", info) == "bf16-mixed"
    assert not common.native_bf16_cpu(tmp_path / "missing")  # another OS: fp32


def test_trainer_settings_resolve_auto_once() -> None:
    cfg = OmegaConf.create(
        {
            "trainer": {
                "accelerator": "cpu",
                "devices": 1,
                "num_nodes": 1,
                "strategy": "auto",
                "precision": "auto",
                "num_workers": 0,
            }
        }
    )
    s = common.TrainerSettings.from_cfg(cfg, source="p")
    assert s.precision in ("bf16-mixed", "32-true")
    assert s.precision == common.resolve_precision("auto", "cpu")


# -- the one training driver ----------------------------------------------------------------------
class _Toy(common.NetModule):
    """A linear model whose validation metric follows a fixed script: it improves, then stalls."""

    SCRIPT = (1.0, 0.5, 0.4, 0.45, 0.41, 0.42, 0.43, 0.44, 0.6, 0.7)

    def __init__(self) -> None:
        super().__init__(torch.nn.Linear(2, 1), torch.nn.functional.mse_loss, lr=0.01)

    def training_step(self, batch, batch_idx):
        x, y = batch
        loss = self.loss_fn(self.net(x), y)
        self.log("train/loss", loss, on_epoch=True, on_step=False)
        return loss

    def validation_step(self, batch, batch_idx):
        self.log("val/score", torch.tensor(self.SCRIPT[self.current_epoch]))


def _loaders():
    x = torch.randn(16, 2)
    ds = torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True))
    dl = torch.utils.data.DataLoader(ds, batch_size=8)
    return dl, torch.utils.data.DataLoader(ds, batch_size=8)


@pytest.mark.integration
def test_fit_run_keeps_the_best_epoch_and_stops_early(tmp_path: Path) -> None:
    L.seed_everything(0)
    train, val = _loaders()
    loop = common.FitLoop(monitor="val/score", max_epochs=10, patience=3, hint="toy.lr")
    tracking = common.TrackingSettings("toy", "toy", stage="toy", enabled=False)
    session = resume.Session(tmp_path / "resume", {"k": 1})
    with common.fit_run(
        _Toy(),
        (train, val),
        settings=common.TrainerSettings(precision="32-true"),
        loop=loop,
        tracking=tracking,
        session=session,
    ) as fitted:
        assert fitted is not None and fitted.run is None
        assert fitted.best_epoch == 2  # the lowest score of the script
        assert len(fitted.history.rows) == 6  # 3 epochs without improvement after epoch 2
        assert fitted.best_row()["val/score"] == pytest.approx(0.4)
        assert fitted.precision == "32-true" and fitted.seconds > 0
        assert set(fitted.best["state_dict"]) == {"net.weight", "net.bias"}
    assert not (tmp_path / "resume").exists()  # finished: the resume folder is gone


@pytest.mark.integration
def test_fit_run_keeps_the_resume_folder_when_the_caller_fails(tmp_path: Path) -> None:
    train, val = _loaders()
    loop = common.FitLoop(monitor="val/score", max_epochs=2)
    tracking = common.TrackingSettings("toy", "toy", stage="toy", enabled=False)
    with pytest.raises(RuntimeError, match="publishing failed"):
        with common.fit_run(
            _Toy(),
            (train, val),
            settings=common.TrainerSettings(precision="32-true"),
            loop=loop,
            tracking=tracking,
            session=resume.Session(tmp_path / "resume", {"k": 2}),
        ):
            raise RuntimeError("publishing failed")
    assert (tmp_path / "resume").exists()  # the next run resumes from there


# -- registrations computed once ---------------------------------------------------------------------
def test_classical_registration_runs_once_per_pair_for_every_method(monkeypatch) -> None:
    from traffictwin.fusion import methods, registration_batches
    from traffictwin.fusion import registration as reg

    calls: list[int] = []
    real = reg.register_pair

    def counting(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(registration_batches, "register_pair", counting)
    rng = np.random.default_rng(1)
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(3, 2, 32, 32)).astype(np.float32)
    maps = np.moveaxis(d[..., :2], -1, 2)
    x = methods.FusionInput(
        map1=maps[:, 0],
        map2=maps[:, 1],
        rel_pose_noisy=np.zeros((3, 3)),
        grid=GridSpec(32, 32, 0.5),
        pair_key=np.arange(3),
        memo={},
    )
    a = methods.fuse("registered", x)
    b = methods.fuse("registered", x.take(slice(1, 3)))  # a later batch of the same pairs
    assert len(calls) == 3  # once per pair, not once per method or batch
    np.testing.assert_array_equal(a.masses[1:], b.masses)
    # a reused registration still counts in the method's per-pair time
    reg_s = np.array([x.memo[("registered", k)].seconds for k in (1, 2)])
    assert (b.seconds >= reg_s).all()
    without = methods.FusionInput(**{**x.__dict__, "memo": None})
    methods.fuse("registered", without)
    assert len(calls) == 6  # no memo: computed again


def test_twin_registers_each_frame_once_for_every_method_using_the_pose(monkeypatch) -> None:
    from traffictwin.twin import fuse as tf

    calls: list[str] = []
    real = tf._register

    def counting(method, *a, **kw):
        calls.append(method.pose)
        return real(method, *a, **kw)

    monkeypatch.setattr(tf, "_register", counting)
    rng = np.random.default_rng(2)
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(3, 32, 32)).astype(np.float32)
    maps = np.moveaxis(d[..., :2], -1, 1)
    poses = np.zeros((3, 3))
    grid = GridSpec(32, 32, 0.5)
    shared: dict = {}
    a = tf.build_twin(maps, poses, grid, tf.TwinOptions("registered"), shared=shared)
    b = tf.build_twin(maps, poses, grid, tf.TwinOptions("naive"), shared=shared)
    c = tf.build_twin(maps, poses, grid, tf.TwinOptions("registered"), shared=shared)
    assert calls == ["registered", "noisy"]  # the second registered twin reused the first's
    np.testing.assert_array_equal(a.masses, c.masses)
    assert c.seconds >= shared[("registered", id(None))][-1]  # its registration time counted
    assert b.used.all()
