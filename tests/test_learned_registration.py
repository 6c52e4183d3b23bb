"""Learned registration: geometry, search, loss, fallback, bad input (fast, synthetic) and
stage train_registration@<cfg> + its evaluation rows on the ci DAG."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import run_record

from traffictwin.evidential.warp import pixel_from_metric, warp_masses
from traffictwin.fusion.evaluation import EvalSettings, evaluate_method
from traffictwin.fusion.learned_registration import (
    LearnedRegistration,
    RegistrationNetSpec,
    check_pair_inputs,
    correction_target,
    correction_to_pose,
    rotation_about,
    rotation_centres,
    warp_by,
)
from traffictwin.fusion.methods import METHODS, FusionInput
from traffictwin.fusion.registration_loss import registration_loss, soft_target
from traffictwin.fusion.registration_training import correction_errors, perturb
from traffictwin.fusion.training_figures import registration_learning_curves
from traffictwin.grid import GridSpec

GRID = GridSpec(rows=128, cols=96, cell=0.32)


def blobs(rng: np.random.Generator, grid: GridSpec = GRID, n: int = 14) -> np.ndarray:
    """Masses (2, H, W): a known free area with ``n`` occupied rectangles of random size."""
    h, w = grid.shape
    m = np.zeros((2, h, w), np.float32)
    m[0, 8:-8, 8:-8] = 0.7
    for _ in range(n):
        r, c = rng.integers(10, h - 16), rng.integers(10, w - 16)
        dh, dw = rng.integers(2, 7), rng.integers(2, 7)
        m[0, r : r + dh, c : c + dw] = 0.0
        m[1, r : r + dh, c : c + dw] = 0.8
    return m


class Occupancy(torch.nn.Module):
    """A hand-made encoder: the centred occupied mass, average-pooled to the stage's stride."""

    def __init__(self, stride: int) -> None:
        super().__init__()
        self.stride = stride

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        o = m[:, 1:2] - m[:, 1:2].mean((2, 3), keepdim=True)
        return torch.nn.functional.avg_pool2d(o, self.stride) if self.stride > 1 else o


def hand_net(fine_iterations: int = 2) -> LearnedRegistration:
    net = LearnedRegistration(RegistrationNetSpec(fine_iterations=fine_iterations), GRID).eval()
    net.coarse, net.fine = Occupancy(net.stride), Occupancy(net.fine_stride)
    with torch.no_grad():
        net.log_temp[:] = torch.tensor([4.0, 4.0])
    return net


# -- geometry -----------------------------------------------------------------------------------------
def test_correction_of_exact_pose_is_identity_and_round_trips() -> None:
    rng = np.random.default_rng(0)
    true = np.column_stack([rng.uniform(-20, 20, (5, 2)), rng.uniform(-3, 3, 5)])
    m, _ = correction_target(true, true, GRID)
    np.testing.assert_allclose(m, np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    noisy = true + np.column_stack([rng.normal(0, 2, (5, 2)), rng.normal(0, 0.2, 5)])
    m, _ = correction_target(noisy, true, GRID)
    back = correction_to_pose(m, noisy, GRID)
    np.testing.assert_allclose(back[:, :2], true[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (back[:, 2] - true[:, 2]))), 0, atol=1e-12)


def test_correction_of_a_pure_forward_offset_is_a_row_shift() -> None:
    # noisy pose 1.6 m further forward (+x): map 2' shows everything 5 cells (1.6 / 0.32) too far
    # up (row − 5); sampling it 5 rows up (M p = p − (0, 5)) undoes that
    m, c = correction_target(np.array([[11.6, 0.0, 0.0]]), np.array([[10.0, 0.0, 0.0]]), GRID)
    np.testing.assert_allclose(m[0], [[1, 0, 0], [0, 1, -5.0], [0, 0, 1]], atol=1e-9)
    p = pixel_from_metric(GRID)
    np.testing.assert_allclose(c[0], (p @ [11.6, 0.0, 1.0])[:2])  # the noisy sensor position
    np.testing.assert_allclose(c[0], [GRID.cols / 2 - 0.5, GRID.rows / 2 - 0.5 - 11.6 / 0.32])


def test_rotation_about_fixes_its_centre_and_rotates() -> None:
    centre = torch.tensor([[30.0, 50.0]], dtype=torch.float64)
    m = rotation_about(
        torch.tensor([math.pi / 2], dtype=torch.float64),
        centre,
        torch.tensor([[1.0, 2.0]], dtype=torch.float64),
    )
    np.testing.assert_allclose(
        (m[0] @ torch.tensor([30.0, 50.0, 1.0], dtype=torch.float64)).numpy(), [31, 52, 1]
    )
    # (31, 50) is 1 px right of the centre; rotated by 90° it is 1 px below (+row), then shifted
    np.testing.assert_allclose(
        (m[0] @ torch.tensor([31.0, 50.0, 1.0], dtype=torch.float64)).numpy(), [31, 53, 1]
    )


def test_warp_by_is_opencv_inverse_map_warp() -> None:
    rng = np.random.default_rng(1)
    img = rng.random((1, 1, 40, 30)).astype(np.float32)
    m = rotation_about(
        torch.tensor([0.1]), torch.tensor([[12.0, 17.0]]), torch.tensor([[1.5, -0.7]])
    )
    ours = warp_by(torch.from_numpy(img), m, (40, 30))[0, 0].numpy()
    ref = cv2.warpAffine(
        img[0, 0],
        m[0, :2].numpy().astype(np.float64),
        (30, 40),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
    )
    np.testing.assert_allclose(ours[6:-6, 6:-6], ref[6:-6, 6:-6], atol=1e-5)


def test_warp_by_the_true_correction_matches_warping_the_raw_map() -> None:
    rng = np.random.default_rng(2)
    raw2 = blobs(rng)
    true = np.array([[8.0, -3.0, 2.5]])
    noisy = true + np.array([[1.2, -0.8, math.radians(7.0)]])
    pre = warp_masses(raw2, noisy[0], GRID)
    m, _ = correction_target(noisy, true, GRID)
    fixed = warp_by(torch.from_numpy(pre[None]), torch.from_numpy(m).float(), GRID.shape)[0].numpy()
    ref = warp_masses(raw2, true[0], GRID)
    known = (fixed.sum(0) > 0.05) & (ref.sum(0) > 0.05)
    assert known.sum() > 1000
    err = np.abs(fixed - ref)[:, known].mean()
    assert err < 0.25 * np.abs(pre - ref)[:, known].mean()


# -- search, targets, loss ------------------------------------------------------------------------------------
def synthetic_batch(rng: np.random.Generator, theta_deg: float, shift_px: tuple[float, float]):
    """Map 1 = blobs; map 2' = map 1 seen under the correction M (so that map2'(M p) = map1(p))."""
    m1 = torch.from_numpy(blobs(rng))[None]
    centre = torch.tensor([[40.0, 70.0]])
    m = rotation_about(torch.tensor([math.radians(theta_deg)]), centre, torch.tensor([shift_px]))
    m2 = warp_by(m1, torch.linalg.inv(m), GRID.shape)
    return torch.cat([m1, m2], 1), m, centre


@pytest.mark.parametrize(
    ("theta", "shift"), [(6.0, (3.0, -2.0)), (-17.0, (-9.0, 5.5)), (0.0, (0.0, 0.0))]
)
def test_cost_volume_search_recovers_a_known_motion(
    theta: float, shift: tuple[float, float]
) -> None:
    x, m_true, centre = synthetic_batch(np.random.default_rng(3), theta, shift)
    with torch.no_grad():
        out = hand_net().estimate(x, centre)
    t, r = correction_errors(out.m.double(), m_true.double(), centre.double(), GRID.cell)
    assert float(t) < 0.5 and float(r) < 1.0, (float(t), float(r))
    t0, r0 = correction_errors(out.m_coarse.double(), m_true.double(), centre.double(), GRID.cell)
    assert float(t0) < 1.5 and float(r0) < 3.0  # the coarse stage alone is within a bin or so


def test_soft_target_is_a_distribution_peaked_at_the_truth() -> None:
    angles = torch.tensor(np.radians(np.arange(-4, 5, 2.0)), dtype=torch.float64)
    centre = torch.tensor([[40.0, 70.0]], dtype=torch.float64)
    m = rotation_about(
        torch.tensor([math.radians(2.0)], dtype=torch.float64),
        centre,
        torch.tensor([[8.0, -4.0]], dtype=torch.float64),
    )
    t = soft_target(angles, 3, 4, m, centre, math.radians(1.0), 2.0)
    assert t.shape == (1, 5, 7, 7) and abs(float(t.sum()) - 1) < 1e-9
    k, dy, dx = np.unravel_index(int(t.argmax()), t.shape[1:])
    assert k == 3  # +2°
    # the correlation shift of that angle is R(−2°) s ≈ (7.85, −4.27) px → bins of 4 px: (+2, −1)
    assert (dx - 3, dy - 3) == (2, -1)


def test_loss_is_finite_and_trains_both_encoders() -> None:
    torch.manual_seed(0)
    rng = np.random.default_rng(4)
    xs, ms, cs = zip(
        *(synthetic_batch(rng, th, sh) for th, sh in ((5.0, (2.0, 1.0)), (-9.0, (-4.0, 3.0))))
    )
    x, m, c = torch.cat(xs), torch.cat(ms), torch.cat(cs)
    net = LearnedRegistration(RegistrationNetSpec(fine_iterations=2), GRID)
    label = x[:, :2]
    loss, parts = registration_loss(net, x, label, m, c, map_weight=1.0)
    assert torch.isfinite(loss) and set(parts) == {"ce_coarse", "ce_fine", "pose_l1", "kld_full"}
    loss.backward()
    for enc in (net.coarse, net.fine):
        assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in enc.parameters())


def test_perturbation_composes_with_the_target() -> None:
    """Warping map 2' by G and the target G⁻¹ M: the new target still aligns map 2 onto map 1."""
    x, m_true, centre = synthetic_batch(np.random.default_rng(5), 4.0, (2.0, -1.0))
    g = torch.Generator().manual_seed(0)
    x2, m2 = perturb(
        x, m_true, centre, sigma_px=4.0, sigma_rad=0.1, prob=1.0, grid_shape=GRID.shape, generator=g
    )
    assert not torch.allclose(x2[:, 2:], x[:, 2:])
    aligned = warp_by(x2[:, 2:], m2, GRID.shape)
    inner = (slice(None), slice(None), slice(20, -20), slice(20, -20))
    assert float((aligned - x[:, :2])[inner].abs().mean()) < 0.02
    same, m_same = perturb(
        x, m_true, centre, sigma_px=4.0, sigma_rad=0.1, prob=0.0, grid_shape=GRID.shape
    )
    assert same is x and m_same is m_true


# -- fallback, method, bad input -------------------------------------------------------------------------
def test_an_estimate_worse_than_the_noisy_pose_falls_back() -> None:
    x, _, _ = synthetic_batch(np.random.default_rng(6), 0.0, (0.0, 0.0))  # already aligned
    net = hand_net()
    bad = rotation_about(
        torch.tensor([0.3]), torch.tensor([[40.0, 70.0]]), torch.tensor([[9.0, 9.0]])
    )
    net.estimate = lambda inputs, centre: type("O", (), {"m": bad})()  # a wrong estimate
    r = net.register(x, torch.zeros(1, 3, dtype=torch.float64))
    assert not bool(r["accepted"][0]) and float(r["cc_est"][0]) < float(r["cc_noisy"][0])
    np.testing.assert_allclose(r["m_used"][0].numpy(), np.eye(3))
    np.testing.assert_allclose(r["warped"].numpy(), x[:, 2:].numpy(), atol=1e-6)


def test_learned_method_gives_masses_and_the_pose_table_columns() -> None:
    rng = np.random.default_rng(7)
    raw2 = np.stack([blobs(rng), blobs(rng)])
    true = np.array([[6.0, 2.0, 0.1], [-9.0, 4.0, 3.0]])
    noisy = true + np.array([[1.0, -0.5, 0.08], [-1.5, 0.7, -0.12]])
    pre = np.stack([warp_masses(raw2[i], noisy[i], GRID) for i in range(2)])
    map1 = np.stack([blobs(rng), blobs(rng)])
    inputs = np.concatenate([map1, pre], 1)
    x = FusionInput(
        inputs=inputs,
        map2=raw2,
        map1=map1,
        rel_pose_noisy=noisy,
        rel_pose_true=true,
        grid=GRID,
        model=hand_net(),
    )
    frame, _ = evaluate_method(
        METHODS["learned"], x, map1, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    assert len(frame) == 2 and (frame["ms"] > 0).all()
    for k in ("reg_success", "reg_accepted", "reg_trans_err_m", "est_rot_err_deg", "reg_cc_est"):
        assert k in frame
    s = METHODS["learned"].summary(frame, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0))
    assert (
        0 <= s["fallback_rate"] <= 1 and s["residual_trans_m_p90"] >= s["residual_trans_m_median"]
    )
    with pytest.raises(ValueError, match="model = \\(registration network, fusion network\\)"):
        METHODS["learned+network"](x)


def test_bad_pairs_and_poses_are_named() -> None:
    good = np.zeros((2, 4, *GRID.shape), np.float32)
    with pytest.raises(ValueError, match="inputs: expected prealigned pairs \\(N, 4, 128, 96\\)"):
        check_pair_inputs(good[:, :, :64], np.zeros((2, 3)), GRID)
    with pytest.raises(ValueError, match="rel_pose_noisy: expected shape \\(2, 3\\)"):
        check_pair_inputs(good, np.zeros((3, 3)), GRID)
    with pytest.raises(ValueError, match=r"pair\(s\) \[1\] are NaN or infinite"):
        check_pair_inputs(good, np.array([[0, 0, 0], [np.nan, 0, 0]]), GRID)
    with pytest.raises(ValueError, match="coarse_stride must be 1, 2, 4 or 8"):
        RegistrationNetSpec(coarse_stride=3)
    with pytest.raises(ValueError, match="must be a finite number > 0"):
        RegistrationNetSpec(max_shift_m=float("nan"))


def test_rotation_centres_are_the_noisy_sensor_pixels() -> None:
    c = rotation_centres(np.array([[0.0, 0.0, 1.0], [3.2, -0.64, 0.0]]), GRID)
    np.testing.assert_allclose(c, [[47.5, 63.5], [49.5, 53.5]])


def test_learning_curves_plot_success_errors_and_loss() -> None:
    rows = [
        {
            "epoch": e,
            "val/success_rate": s,
            "val/trans_err_m": t,
            "val/rot_err_deg": r,
            "train/loss": 3 - e,
            "val/loss": 3.5 - e,
        }
        for e, (s, t, r) in enumerate(((0.2, 2.0, 4.0), (0.6, 0.7, 1.2), (0.8, 0.3, 0.5)))
    ]
    fig = registration_learning_curves(rows, "t")
    ax1, ax2, ax3 = fig.axes
    np.testing.assert_allclose(ax1.lines[0].get_ydata(), [20, 60, 80])
    assert ax1.get_ylabel() == "success rate (%)" and "m" in ax2.get_ylabel()
    assert [len(line.get_xdata()) for line in ax3.lines] == [3, 3]
    with pytest.raises(ValueError, match="no epochs"):
        registration_learning_curves([], "t")


# -- training -------------------------------------------------------------------------------------------------
def write_registration_data(
    root: Path, grid: GridSpec = GRID, n: int = 8, nan_pose: bool = False
) -> Path:
    """A small prealigned dataset with poses: map 2' = map 1's scene seen under a random noisy pose."""
    from traffictwin.io.shards import DatasetWriter

    rng = np.random.default_rng(11)
    wr = DatasetWriter(root, "prealigned", {"synthetic": True}, 0)
    for i, split in enumerate(["train", "train", "val"]):
        maps = np.stack([blobs(rng, grid) for _ in range(n)])
        true = np.zeros((n, 3))
        noisy = true + np.column_stack([rng.normal(0, 1.0, (n, 2)), rng.normal(0, 0.1, n)])
        if nan_pose and split == "val":
            noisy[1, 0] = np.nan
        pre = np.stack(
            [
                warp_masses(maps[k], noisy[k] if np.isfinite(noisy[k]).all() else true[k], grid)
                for k in range(n)
            ]
        )
        wr.add_shard(
            i,
            {
                "inputs": np.concatenate([maps, pre], 1).astype(np.float32),
                "label": maps.astype(np.float32),
                "rel_pose_noisy": noisy,
                "rel_pose_true": true,
                "pair_id": np.arange(n) + 1000 * i,
            },
            split=split,
            check=not nan_pose,  # the NaN-pose fixture: a shard with a valid hash, bad values
        )
    wr.finalize()
    return root


def fit_small(root: Path, out: Path, grid: GridSpec = GRID, tracking=None, **train_kw):
    from traffictwin.fusion.registration_training import (
        RegistrationSettings,
        RegistrationTrainConfig,
        fit_registration,
    )
    from traffictwin.fusion.training_data import TrainingSet
    from traffictwin.trainer import ModelOutputs, TrainerSettings

    kw = dict(
        batch_size=4,
        max_epochs=2,
        train_samples_per_epoch=8,
        val_samples=0,
        early_stopping_patience=2,
        lr=2e-3,
        weight_decay=0.0,
        augment_prob=0.5,
        augment_scale=1.0,
        map_weight=0.5,
    )
    kw.update(train_kw)
    return fit_registration(
        TrainingSet(root, "D", {"r": 2.0, "alpha": 10.0}, grid, 3),
        model=RegistrationSettings(RegistrationNetSpec(), RegistrationTrainConfig(**kw), 0.0),
        trainer_settings=TrainerSettings(num_threads=1),
        outputs=ModelOutputs(
            out / "model.ckpt", out / "model_meta.json", out / "metrics.json", out / "curves.csv"
        ),
        tracking=tracking,
    )


def test_fit_registration_publishes_a_loadable_model(tmp_path: Path) -> None:
    from traffictwin.fusion.registration_training import load_registration_model

    res = fit_small(write_registration_data(tmp_path / "pre"), tmp_path / "out")
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["epochs"] == 2 and 0 <= m["val/success_rate"] <= 1 and np.isfinite(m["val/loss"])
    assert "train/kld_full" in m  # the fused-map term was on (map_weight > 0)
    assert res.meta["selection_metric"] == "val/loss" and res.meta["problem"] == "registration"
    net = load_registration_model(tmp_path / "out", expected_grid=GRID, expected_cfg="D")
    assert net.meta["cfg"] == "D" and not net.training
    assert (tmp_path / "out" / "curves.csv").read_text().count("\n") == 3  # header + 2 epochs


def test_bad_training_data_fails_naming_it_and_writes_nothing(tmp_path: Path) -> None:
    from traffictwin.io.shards import DatasetError

    root = write_registration_data(tmp_path / "pre", nan_pose=True)
    with pytest.raises(
        DatasetError, match=r"pre/shard-00002.npz: array 'rel_pose_noisy' holds 1 NaN"
    ):
        fit_small(root, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    with pytest.raises(DatasetError, match=r"array 'inputs' must be \(N, 4, 64, 48\)"):
        fit_small(
            write_registration_data(tmp_path / "pre2"),
            tmp_path / "out",
            grid=GridSpec(64, 48, 0.32),
        )
    assert not (tmp_path / "out").exists()


# -- stage on the ci DAG -------------------------------------------------------------------------------------
@pytest.mark.slow
def test_train_registration_stage_and_evaluation_rows(ci_dag: Path) -> None:
    from traffictwin.fusion.registration_training import load_registration_model

    # one learned registration for every noise level, trained on the mixture
    d = ci_dag / "models" / "registration" / "learned"
    meta = json.loads((d / "model_meta.json").read_text())
    assert meta["cfg"] == "mixed" and meta["problem"] == "registration"
    assert sorted(meta["noise"]["configurations"]) == ["A", "B", "C", "D"]
    assert not {"mlflow_run_id", "mlflow_model_uri", "data_root"} & set(meta)
    rec = run_record(ci_dag, "train_registration")
    assert rec["run_id"] and rec["precision"] in ("bf16-mixed", "32-true")
    net = load_registration_model(d, expected_cfg="mixed")
    assert isinstance(net, LearnedRegistration)
    metrics = json.loads((ci_dag / "reports" / "metrics" / "train_registration.json").read_text())
    assert 0 <= metrics["val/success_rate"] <= 1 and np.isfinite(metrics["val/trans_err_m"])
    assert metrics["samples_seen"] > 0 and "train_seconds" not in metrics
    assert (ci_dag / "reports" / "figures" / "learning_curves" / "train_registration.png").exists()
    fusion = json.loads((ci_dag / "reports" / "metrics" / "fusion.json").read_text())
    for cfg in ("A", "B", "C", "D"):
        row = fusion["test"][cfg]["learned"]
        assert {
            "success_rate",
            "fallback_rate",
            "residual_trans_m_p90",
            "residual_rot_deg_p90",
        } <= set(row)
        assert run_record(ci_dag, "evaluate_fusion")["ms_per_pair"][cfg]["learned"] > 0
        assert "success_rate" in fusion["diff"][cfg]["learned"]["vs_registered"]
    # the registered-pairs network (one, mixed noise) as its head at every configuration
    assert all("learned+network" in fusion["test"][c] for c in ("A", "B", "C", "D"))
    for name in (
        "learned_success_vs_registered",
        "learned_kld_vs_registered",
        "learned_success_at_D",
        "learned_success_gain_at_D",
    ):
        assert fusion["targets"][name]["status"] in ("pass", "fail", "not evaluated")
    runtime = run_record(ci_dag, "evaluate_fusion")["targets"]["learned_runtime_ms"]
    assert runtime["status"] in ("pass", "fail") and "learned_runtime_ms" not in fusion["targets"]
    with pytest.raises(Exception, match="expected 'B'"):
        load_registration_model(ci_dag / "models" / "registration" / "learned", expected_cfg="B")


def test_registration_gate_evaluator_scores_a_logged_model(
    mlflow_uri, tmp_path, monkeypatch
) -> None:
    """The promotion gate's evaluator loads the MLflow-logged network and scores its fused map
    (Dempster after the learned warp) with the fusion metrics, given the noisy poses."""
    from dataclasses import asdict

    import mlflow

    from traffictwin.fusion.gate_eval import registration_evaluator
    from traffictwin.fusion.registration_training import PROBLEM
    from traffictwin.trainer import log_model, model_checkpoint

    monkeypatch.chdir(tmp_path)
    net = LearnedRegistration(RegistrationNetSpec(), GRID).eval()
    rng = np.random.default_rng(8)
    m1 = np.stack([blobs(rng), blobs(rng)])
    inputs = np.concatenate([m1, m1], 1).astype(np.float32)  # map 2' = map 1: already aligned
    mlflow.set_experiment("fusion")
    grid = {"rows": GRID.rows, "cols": GRID.cols, "cell": GRID.cell}
    ckpt = model_checkpoint(PROBLEM, asdict(net.spec), net.state_dict(), {"grid": grid})
    with mlflow.start_run():
        uri = log_model(ckpt, ckpt["traffictwin"], net, inputs[:1], name="model")
    out = registration_evaluator(inputs, m1, np.zeros((2, 3)), batch_size=1)(uri)
    # the gate's numbers are named by its split (validation: the test split is read once)
    assert out["val/n"] == 2 and math.isfinite(out["val/kld_fou_mean"])
    assert out["val/dice_occ"] > 0.99  # nothing to correct: the fallback keeps the aligned map


def test_fit_registration_logs_a_safe_model_the_gate_can_register(
    tmp_path: Path, mlflow_uri: str, monkeypatch
) -> None:
    """With tracking, the trained registration goes to MLflow as weights + JSON (no pickle); the
    gate registers it sealed, and the registry loader rebuilds the local checkpoint's network."""
    from traffictwin.fusion.registration_training import load_registration_model
    from traffictwin.mlops import model_artifact as art
    from traffictwin.mlops import registry as reg
    from traffictwin.trainer import TrackingSettings

    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)
    res = fit_small(
        write_registration_data(tmp_path / "pre"),
        tmp_path / "out",
        tracking=TrackingSettings("fusion", "registration-D", profile="test"),
    )
    mv = reg.ensure_version(cl, "traffictwin-fusion-learned-D", res.run_id)
    assert mv.run_id == res.run_id and art.SHA_TAG in mv.tags
    local = load_registration_model(tmp_path / "out")
    for uri in (res.model_uri, reg.version_uri("traffictwin-fusion-learned-D", 1)):
        logged = reg.load_registered(uri, load_registration_model, cl=cl)
        assert logged.meta["cfg"] == "D" and logged.meta["grid"] == local.meta["grid"]
        for (k, a), b in zip(local.state_dict().items(), logged.state_dict().values(), strict=True):
            assert torch.equal(a, b), k
