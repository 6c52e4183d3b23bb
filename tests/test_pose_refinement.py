"""ECC refinement of a given pose estimate (the learned registration's coarse pose)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.test_registration import GRID, render, structured_world
from traffictwin.fusion.refinement import RefinementParams, refine_pose
from traffictwin.fusion.registration import RegistrationParams, ecc_align, pose_error, register_pair
from traffictwin.geometry import relative_pose


def _pair(seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    world, pw = structured_world(seed, GRID)
    p1 = np.array([2.0, -3.0, 0.2])
    p2 = np.array([12.0, 4.0, 0.7])
    return render(world, pw, p1, GRID), render(world, pw, p2, GRID), relative_pose(p1, p2)


@pytest.mark.parametrize("levels", [1, 2])
@pytest.mark.parametrize("off", [(0.8, -0.6, 3.0), (-0.7, 0.7, -2.5)])
def test_refines_a_coarse_pose_about_1m_3deg_off(off, levels):
    m1, m2, true = _pair()
    coarse = true + np.array([off[0], off[1], np.radians(off[2])])
    t0, r0 = pose_error(coarse, true)
    assert t0 > 0.9 and r0 > 2.4  # the start fails the success test (0.5 m, 1 deg)
    res = refine_pose(
        m1, m2, coarse, GRID, RefinementParams(ecc_levels=levels, max_trans_m=2.0, max_rot_deg=5.0)
    )
    t, r = pose_error(res.pose, true)
    assert res.accepted and res.ecc_ok
    assert t < 0.25 and r < 0.5, (t, r)
    assert res.cc_est > res.cc_start


def test_falls_back_to_the_start_when_the_refinement_moves_too_far():
    m1, m2, true = _pair()
    coarse = true + np.array([0.8, -0.6, np.radians(3.0)])
    # the right answer is ~1 m away: a bound of 0.3 m rejects it and keeps the start
    res = refine_pose(m1, m2, coarse, GRID, RefinementParams(max_trans_m=0.3, max_rot_deg=5.0))
    assert not res.accepted
    np.testing.assert_array_equal(res.pose, coarse)
    assert pose_error(res.estimate, coarse)[0] > 0.3


def test_falls_back_to_the_start_when_ecc_diverges_or_has_nothing_to_align():
    m1, m2, true = _pair()
    start = true + np.array([0.5, 0.5, 0.02])
    blank = np.zeros_like(m2)
    res = refine_pose(m1, blank, start, GRID)  # no overlap: nothing to align
    assert not res.accepted and not res.ecc_ok
    np.testing.assert_array_equal(res.pose, start)
    # structureless map 2 (a constant known plateau): ECC's correlation is undefined, it raises
    flat = np.stack([np.full(GRID.shape, 0.3, np.float32), np.full(GRID.shape, 0.3, np.float32)])
    res = refine_pose(m1, flat, start, GRID)
    assert not res.accepted
    np.testing.assert_array_equal(res.pose, start)


def test_ecc_align_pyramid_recovers_a_pixel_shift():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.random(GRID.shape).astype(np.float32), (0, 0), 3.0)
    shift = np.array([[1.0, 0.0, 2.5], [0.0, 1.0, -1.5], [0.0, 0.0, 1.0]])
    moved = cv2.warpAffine(img, shift[:2], (GRID.cols, GRID.rows), flags=cv2.INTER_LINEAR)
    mask = np.full(GRID.shape, 255, np.uint8)
    mask[:8], mask[-8:], mask[:, :8], mask[:, -8:] = 0, 0, 0, 0
    for levels in (1, 3):
        w, ok = ecc_align(img, moved, mask, mask, np.eye(3), 100, 1e-6, 5, levels)
        assert ok
        np.testing.assert_allclose(w[:2, 2], [2.5, -1.5], atol=0.05)
        np.testing.assert_allclose(w[:2, :2], np.eye(2), atol=1e-3)


def test_register_pair_accepts_a_pyramid_and_checks_its_settings():
    m1, m2, true = _pair()
    noisy = true + np.array([1.5, -2.0, np.radians(8.0)])
    res = register_pair(m1, m2, noisy, GRID, RegistrationParams(ecc_levels=2))
    t, r = pose_error(res.pose, true)
    assert res.accepted and t < 0.25 and r < 0.5
    with pytest.raises(ValueError, match="ecc_levels"):
        RefinementParams(ecc_levels=0)
    with pytest.raises(ValueError, match="map1"):
        refine_pose(np.zeros((2, 4, 4)), m2, true, GRID)


class _CoarseStub:
    """A stand-in learned registration that returns the noisy pose (identity correction)."""

    def register(self, inputs, noisy):  # noqa: ANN001, ANN201 - the LearnedRegistration interface
        import torch

        n = len(inputs)
        eye = torch.eye(3, dtype=torch.float64).expand(n, 3, 3).clone()
        return {
            "m": eye,
            "m_used": eye,
            "accepted": torch.ones(n, dtype=torch.bool),
            "cc_noisy": torch.zeros(n),
            "cc_est": torch.zeros(n),
            "warped": inputs[:, 2:],
        }


def test_refined_methods_are_registered_and_finish_the_coarse_pose():
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.evaluation import EvalSettings, evaluate_method
    from traffictwin.fusion.methods import METHODS, FusionInput

    pairs = [_pair(1), _pair(3)]
    map1 = np.stack([p[0] for p in pairs])
    map2 = np.stack([p[1] for p in pairs])
    true = np.stack([p[2] for p in pairs])
    noisy = true + np.array([[0.8, -0.6, np.radians(3.0)], [-0.7, 0.7, np.radians(-2.5)]])
    pre = np.stack([warp_masses(map2[i], noisy[i], GRID) for i in range(2)])
    x = FusionInput(
        inputs=np.concatenate([map1, pre], 1).astype(np.float32),
        map1=map1,
        map2=map2,
        rel_pose_noisy=noisy,
        rel_pose_true=true,
        grid=GRID,
        model=_CoarseStub(),
        refinement=RefinementParams(max_trans_m=2.0, max_rot_deg=5.0),
        pair_key=np.arange(2),
        memo={},
    )
    assert "raw" in METHODS["learned-refined"].needs and "model" in METHODS["learned-refined"].needs
    coarse, _ = evaluate_method(
        METHODS["learned"], x, map1, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    refined, _ = evaluate_method(
        METHODS["learned-refined"], x, map1, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    assert not coarse["reg_success"].any()  # the stub's pose is ~1 m / 3 deg off
    assert refined["reg_success"].all() and refined["reg_accepted"].all()
    assert (refined["reg_trans_err_m"] < 0.25).all() and (refined["ms"] > 0).all()
    s = METHODS["learned-refined"].summary(
        refined, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    assert s["success_rate"] == 1.0 and s["fallback_rate"] == 0.0
    # computed once per pair and shared through memo
    assert sum(1 for k in x.memo if k[0] == "learned-refined") == 1
    with pytest.raises(ValueError, match="model = \\(registration network, fusion network\\)"):
        METHODS["learned-refined+network"](x)
    with pytest.raises(ValueError, match="map1"):
        METHODS["learned-refined"](FusionInput(inputs=x.inputs, model=x.model, grid=GRID))


def test_settings_are_chosen_by_validation_success():
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.methods import FusionInput
    from traffictwin.fusion.registration_tuning import parameter_grid, validation_success

    m1, m2, true = _pair(1)
    noisy = true + np.array([0.8, -0.6, np.radians(3.0)])
    x = FusionInput(
        inputs=np.concatenate([m1, warp_masses(m2, noisy, GRID)])[None].astype(np.float32),
        map1=m1[None],
        map2=m2[None],
        rel_pose_noisy=noisy[None],
        rel_pose_true=true[None],
        grid=GRID,
        pair_key=np.arange(1),
        memo={},
    )
    cands = parameter_grid(
        RefinementParams(max_rot_deg=5.0), {"max_trans_m": [0.3, 2.0], "ecc_levels": [1, 2]}
    )
    assert [(c.max_trans_m, c.ecc_levels) for c in cands] == [
        (0.3, 1),
        (0.3, 2),
        (2.0, 1),
        (2.0, 2),
    ]
    rates = validation_success("learned-refined", [x], cands, 0.5, 1.0, registration=_CoarseStub())
    np.testing.assert_array_equal(
        rates, [0.0, 0.0, 1.0, 1.0]
    )  # the 0.3 m bound keeps the bad start
    assert int(np.argmax(rates)) == 2  # ties: the earlier (cheaper) candidate
    reg = parameter_grid(RegistrationParams(), {"ecc_levels": [1, 2]})
    np.testing.assert_array_equal(validation_success("registered", [x], reg, 0.5, 1.0), [1.0, 1.0])
    with pytest.raises(ValueError, match="not fields of RefinementParams"):
        parameter_grid(RefinementParams(), {"levels": [1]})
    with pytest.raises(ValueError, match="needs the learned registration"):
        validation_success("learned-refined", [x], cands, 0.5, 1.0)


def test_evaluate_fusion_chooses_settings_on_validation_pairs(monkeypatch: pytest.MonkeyPatch):
    import dataclasses
    from pathlib import Path

    import yaml
    from omegaconf import OmegaConf

    from pipelines.evaluate_fusion import choose_on_validation
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion import evaluation as ev
    from traffictwin.fusion.config import fusion_eval_config
    from traffictwin.io.npz import DatasetError

    root = Path(__file__).resolve().parents[1]
    cfg = OmegaConf.create(yaml.safe_load((root / "params.yaml").read_text()))
    fc = dataclasses.replace(
        fusion_eval_config(cfg),
        refinement={**fusion_eval_config(cfg).refinement, "max_rot_deg": 5.0},
        validation={
            "split": "val",
            "max_pairs": 1,
            "registration_grid": {"ecc_levels": [1]},
            "refinement_grid": {"max_trans_m": [0.3, 2.0]},
        },
    )
    m1, m2, true = _pair(1)
    noisy = true + np.array([0.8, -0.6, np.radians(3.0)])
    seen = []

    def load_sets(roots, split, max_pairs, grid):
        seen.append(split)
        d = {
            "inputs": np.concatenate([m1, warp_masses(m2, noisy, GRID)])[None].astype(np.float32),
            "rel_pose_noisy": noisy[None],
            "rel_pose_true": true[None],
        }
        return {c: d for c in roots}, np.array([1000])

    monkeypatch.setattr(ev, "load_test_sets", load_sets)
    monkeypatch.setattr(
        ev, "load_raw_pairs", lambda root, pid, split, grid: {"map1": m1[None], "map2": m2[None]}
    )
    out, record = choose_on_validation(fc, ["D"], GRID, {ev.LEARNED: {"D": _CoarseStub()}})
    assert seen == ["val"]  # never the evaluated (test) split
    assert out.refinement_params.max_trans_m == 2.0  # the 0.3 m bound keeps the bad start
    assert record["refinement"]["success_rate"] == [0.0, 1.0]
    assert record["refinement"]["chosen"] == {"max_trans_m": 2.0}
    assert record["registration"]["chosen"] == {"ecc_levels": 1}
    assert record["n_pairs_per_config"] == 1 and record["split"] == "val"
    # without a learned registration only the classical settings are searched
    _, record = choose_on_validation(fc, ["D"], GRID, {})
    assert "refinement" not in record and "registration" in record

    def no_pairs(*a, **k):
        raise DatasetError("data/prealigned/D: no split 'val'")

    monkeypatch.setattr(ev, "load_test_sets", no_pairs)
    same, record = choose_on_validation(fc, ["D"], GRID, {})
    assert same is fc and "no split 'val'" in record["skipped"]
