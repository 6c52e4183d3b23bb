"""Figures a newcomer can read: axis names follow what is plotted (the risk training curves per
objective), a row far above the others does not squash the rest (the fusion KLD box plot), an
empty chart says why, and the CLI previews title their panels. Checked by what the figures
draw (Axes read back; preview pixels), not by file size."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

PAPER_MSE = 0.0147


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> dict:
    """The risk figures by file name, kept instead of written."""
    from traffictwin.risk import figures

    figs: dict = {}
    monkeypatch.setattr(
        figures, "save_figure", lambda fig, path, **_: figs.__setitem__(Path(path).name, fig)
    )
    yield figs
    for fig in figs.values():
        plt.close(fig)


def _history(loss: float, val_mse: float, n: int = 4, val_loss: bool = True) -> pd.DataFrame:
    steps = np.arange(1, n + 1) * 64
    h = {"step": steps, "train/loss": loss / np.arange(1, n + 1), "val/mse": np.full(n, val_mse)}
    if val_loss:
        h["val/loss"] = loss * 0.9 / np.arange(1, n + 1)
    return pd.DataFrame(h)


def _labels(ax) -> list[str]:
    return [ln.get_label() for ln in ax.lines]


# ------------------------------------------------------------------ risk training curves


def test_training_curves_name_the_axis_after_each_objective(captured: dict) -> None:
    from traffictwin.risk import figures

    hist = {
        "headline": _history(1.6, 0.002),
        "headline_s1": _history(1.7, 0.0022),
        "paper": _history(0.06, 0.03),
        "headline_cls": _history(0.08, 0.004, val_loss=False),
    }
    objectives = {
        "headline": "log_thw",
        "headline_s1": "log_thw",
        "paper": "mse",
        "headline_cls": "mse_bce",
    }
    figures.plot_training_curves(hist, "c.png", paper_test_mse=PAPER_MSE, objectives=objectives)
    mse, log_thw, bce, val = captured["c.png"].axes
    # one panel per objective, each in its own units; then the validation MSE of every run
    assert mse.get_ylabel() == "loss: MSE of normalised risk (dimensionless)"
    assert log_thw.get_ylabel() == "loss: MSE of log THW ((log s)²)"
    assert "cross-entropy" in bce.get_ylabel()
    assert "log_thw" in log_thw.get_title() and "mse_bce" in bce.get_title()
    assert val.get_ylabel() == "MSE of normalised risk (dimensionless)"
    assert all(ax.get_xlabel() == "training step" for ax in (mse, bce, log_thw, val))
    # each run only on its objective's panel: training (solid) and validation (dashed) loss
    assert _labels(log_thw) == [
        "headline",
        "headline (validation)",
        "headline_s1",
        "headline_s1 (validation)",
    ]
    train, valid = log_thw.lines[:2]
    np.testing.assert_allclose(train.get_ydata(), hist["headline"]["train/loss"])
    np.testing.assert_allclose(valid.get_ydata(), hist["headline"]["val/loss"])
    assert train.get_linestyle() == "-" and valid.get_linestyle() == "--"
    assert _labels(bce) == ["headline_cls"]  # no val/loss column: no dashed line
    # the paper's test MSE (an MSE of normalised risk) only where the axis is in those units
    assert "paper test MSE" in _labels(mse) and "paper test MSE" in _labels(val)
    assert "paper test MSE" not in _labels(log_thw) and "paper test MSE" not in _labels(bce)
    (ref,) = [ln for ln in val.lines if ln.get_label() == "paper test MSE"]
    assert ref.get_ydata()[0] == pytest.approx(PAPER_MSE)
    # the validation panel: every run's val/mse, comparable across objectives, same colours
    assert _labels(val)[:4] == list(hist)
    np.testing.assert_allclose(val.lines[2].get_ydata(), hist["paper"]["val/mse"])
    assert val.lines[0].get_color() == log_thw.lines[0].get_color()
    assert all(ax.get_yscale() == "log" for ax in (mse, bce, log_thw, val))


def test_training_curves_of_one_objective_and_without_objectives(captured: dict) -> None:
    from traffictwin.risk import figures

    hist = {"headline": _history(1.6, 0.002), "headline_s2": _history(1.5, 0.002)}
    figures.plot_training_curves(
        hist, "log.png", paper_test_mse=PAPER_MSE, objectives={v: "log_thw" for v in hist}
    )
    tr, val = captured["log.png"].axes  # log-THW runs only: no normalised-risk loss panel
    assert tr.get_ylabel() == figures.OBJECTIVE_LOSS["log_thw"]
    assert "paper test MSE" not in _labels(tr) and "paper test MSE" in _labels(val)
    # no objective known: the evaluation's default (mse)
    figures.plot_training_curves({"v": _history(0.05, 0.03)}, "mse.png", paper_test_mse=PAPER_MSE)
    tr, val = captured["mse.png"].axes
    assert tr.get_ylabel() == figures.OBJECTIVE_LOSS["mse"] and "paper test MSE" in _labels(tr)
    # nothing to draw: the axes say so
    figures.plot_training_curves({"v": _history(0.05, 0.03).iloc[:0]}, "none.png")
    (val,) = captured["none.png"].axes
    assert [t.get_text() for t in val.texts] == ["no training history to draw"]


# ------------------------------------------------------------------ empty ROC


@pytest.mark.parametrize(
    ("positive", "want"),
    [
        (np.zeros(12, bool), "no critical frames in the test split\n(all 12 are uncritical)"),
        (np.ones(12, bool), "no uncritical frames in the test split\n(all 12 are critical)"),
    ],
)
def test_empty_roc_says_why(captured: dict, positive: np.ndarray, want: str) -> None:
    from traffictwin.risk import figures

    scores = {"net": np.linspace(0, 1, 12), "geometric_gt": np.linspace(1, 0, 12)}
    figures.plot_roc(positive, scores, "r.png", auc={"net": None})
    (ax,) = captured["r.png"].axes
    assert len(ax.lines) == 0  # no curve, no chance diagonal
    (text,) = ax.texts
    assert text.get_text() == f"{want}: ROC undefined"
    assert text.get_position() == (0.5, 0.5) and text.get_transform() == ax.transAxes
    assert (text.get_ha(), text.get_va()) == ("center", "center")
    # the axes keep their meaning: rates in [0, 1] with their names
    assert "false positive rate" in ax.get_xlabel() and "true positive rate" in ax.get_ylabel()
    assert ax.get_xlim() == (0, 1)


def test_roc_with_both_classes_draws_no_empty_note(captured: dict) -> None:
    from traffictwin.risk import figures

    pos = np.array([1, 0, 1, 0], bool)
    figures.plot_roc(pos, {"net": np.array([0.9, 0.5, 0.5, 0.1])}, "r.png")
    (ax,) = captured["r.png"].axes
    assert len(ax.texts) == 0 and _labels(ax) == ["net", "chance"]


# ------------------------------------------------------------------ fusion KLD box plot


def _box_height_in_axes(ax, box) -> float:
    """Height of a box (its quartiles) as a share of the axes' height, as drawn."""
    y = box.get_path().vertices[:, 1]
    to_axes = ax.transData + ax.transAxes.inverted()
    lo = to_axes.transform((0, y.min()))[1]
    hi = to_axes.transform((0, y.max()))[1]
    return float(hi - lo)


def test_kld_boxplot_keeps_small_boxes_readable_beside_a_degenerate_row() -> None:
    from traffictwin.fusion.figures import CONFIG_AXIS, CONFIG_NOTE, kld_boxplot

    rng = np.random.default_rng(0)
    cfgs = ["A", "D"]
    vals = {
        "naive": {"A": np.zeros(50), "D": rng.uniform(0.1, 0.4, 50)},  # exact zeros occur
        "dnn": {c: rng.uniform(0.01, 0.05, 50) for c in cfgs},
        "dnn[paper]": {c: rng.normal(1.85, 0.05, 50) for c in cfgs},  # degenerate, ~2 nats
    }
    fig = kld_boxplot(vals, cfgs, list(vals), ylabel="KLD(b)", noise={"A": (0, 0), "D": (5, 20)})
    try:
        ax = fig.axes[0]
        assert ax.get_yscale() == "symlog" and ax.get_ylim()[0] == 0
        assert ax.get_ylabel().startswith("KLD(b)\n(nats per cell; log scale")
        assert ax.get_xlabel() == f"{CONFIG_AXIS}\n{CONFIG_NOTE}"
        boxes = {p.get_gid(): p for p in ax.patches if p.get_gid()}
        # the network's box (quartiles ~0.02-0.04) stays a visible box: on a linear axis up to
        # ~2 it would be ~1 % of the height
        assert _box_height_in_axes(ax, boxes["dnn/D"]) > 0.05
        # every box is inside the axes, the degenerate one included; zeros sit at the bottom
        for gid, box in boxes.items():
            y = box.get_path().vertices[:, 1]
            assert ax.get_ylim()[0] <= y.min() and y.max() <= ax.get_ylim()[1], gid
        naive_a = boxes["naive/A"].get_path().vertices[:, 1]
        assert naive_a.min() == naive_a.max() == 0
        # the boxes still span the quartiles of the values they were given
        q = np.quantile(vals["dnn[paper]"]["D"], [0.25, 0.75])
        y = boxes["dnn[paper]/D"].get_path().vertices[:, 1]
        assert (y.min(), y.max()) == pytest.approx(tuple(q))
    finally:
        plt.close(fig)


def test_kld_boxplot_without_values_says_so() -> None:
    from traffictwin.fusion.figures import kld_boxplot

    fig = kld_boxplot({"dnn": {"A": [np.nan]}}, ["A"], ["dnn"])
    try:
        ax = fig.axes[0]
        assert not [p for p in ax.patches if p.get_gid()]
        (text,) = ax.texts
        assert text.get_text().startswith("no KLD values to draw")
        assert ax.get_legend() is None and ax.get_yscale() == "linear"
        assert ax.get_ylabel() == "KLD(label ‖ prediction) (nats per cell)"
    finally:
        plt.close(fig)


# ------------------------------------------------------------------ CLI previews


def _masses(h: int = 32, w: int = 24, occ: float = 0.0) -> np.ndarray:
    m = np.zeros((2, h, w), np.float32)
    m[0, h // 2 :] = 1.0  # free in the rear half, unknown in front
    m[1, 2:6, 4:10] = occ
    return m


def test_mass_panels_title_strip_above_each_panel() -> None:
    from traffictwin.cli import mass_panels
    from traffictwin.report.colours import legend_strip_bgr8, masses_to_bgr8

    m = _masses()
    plain = mass_panels([(m, None), (m, None)])
    img = mass_panels([(m, None), (m, None)], titles=["map 1", "fused"])
    strip = img[:24]
    assert img.shape == (plain.shape[0] + 24, plain.shape[1], 3) and img.dtype == np.uint8
    # below the strip: the same maps and the same legend as without titles
    assert np.array_equal(img[24:], plain)
    scale = 384 // 32
    assert tuple(img[24, 0]) == tuple(masses_to_bgr8(m)[0, 0])
    assert np.array_equal(img[-22:], legend_strip_bgr8(img.shape[1]))
    # each title is dark text on white, inside its own panel's columns, roughly centred
    w = 24 * scale
    dark = (strip < 128).all(axis=-1)
    assert dark.any() and (strip[~dark] > 100).all()
    for k in range(2):
        x0 = k * (w + 4 * scale)
        cols = np.flatnonzero(dark[:, x0 : x0 + w].any(axis=0))
        assert cols.size, k
        assert abs((cols.min() + cols.max()) / 2 - w / 2) < 0.15 * w
    gap = dark[:, w : w + 4 * scale]
    assert not gap.any()  # nothing drawn over the separator
    with pytest.raises(ValueError, match="1 titles for 2 panels"):
        mass_panels([(m, None), (m, None)], titles=["one"])


def test_a_long_title_is_fitted_to_its_panel() -> None:
    from traffictwin.cli import mass_panels

    m = _masses(h=192, w=64)  # scale 2: panels 128 px wide
    img = mass_panels([(m, None), (m, None)], titles=["x" * 80, "short"])
    dark = (img[:24] < 128).all(axis=-1)
    assert dark[:, :128].any() and not dark[:, 128 : 128 + 8].any()


def test_previews_title_their_panels(monkeypatch: pytest.MonkeyPatch) -> None:
    from traffictwin import cli

    seen: list = []
    real = cli.mass_panels
    monkeypatch.setattr(  # where the previews look it up (traffictwin.cli is a package)
        cli.previews,
        "mass_panels",
        lambda panels, titles=None, **kw: seen.append(titles) or real(panels, titles, **kw),
    )
    m = _masses(occ=1.0)
    u = 1.0 - m[0] - m[1]
    img = cli.preview_image(m, m, m, u)
    assert seen[-1] == ["map 1", "map 2 in map 1's frame", "fused (grey = uncertainty u)"]
    assert img.shape[0] == 24 + 32 * 12 + 22  # no axes without a cell size; one legend row
    img = cli.twin_preview(m, [m, m, np.zeros_like(m)])
    assert seen[-1] == [
        "twin (the maps fused)",
        "map 1 (reference)",
        "map 2 where the twin put it",
        "map 3: left out",
    ]
    assert img.shape[1] == 4 * 24 * 12 + 3 * 4 * 12
    # the titles are plain ASCII: OpenCV's Hershey font draws nothing else
    assert all(t.isascii() for titles in seen for t in titles)


def test_fuse_preview_has_metre_axes_the_ego_and_a_legend_for_every_colour() -> None:
    """The Quick start's `fuse` picture read without the docs: ticks in metres of map 1's frame
    (under each panel and left of them), map 1's vehicle marked at the grid's centre in every
    panel, and a legend that names the mixed colours (which a tiny model's blur is made of) and
    the marker, besides the three pure colours."""
    from traffictwin.cli import preview_image
    from traffictwin.cli.previews import AXIS_H, AXIS_W, EGO_BGR, LEGEND_H
    from traffictwin.report.colours import legend_strip_bgr8

    m = np.zeros((2, 128, 96), np.float32)  # the ci grid (0.64 m cells): all unknown
    m[:, 8:20, 8:20] = 0.5  # an olive patch: half free, half occupied
    u = 1.0 - m[0] - m[1]
    plain = preview_image(m, m, m, u)
    img = preview_image(m, m, m, u, cell=0.64)
    scale = 3  # 384 / 128
    h, w = 128 * scale, 96 * scale
    assert img.shape[1] == AXIS_W + plain.shape[1]
    assert img.shape[0] == 24 + h + AXIS_H + (plain.shape[0] - 24 - h)
    dark = (img < 100).all(axis=-1)
    # y ticks under the panels, x ticks left of them: drawn text and tick marks
    assert dark[24 + h : 24 + h + AXIS_H, AXIS_W : AXIS_W + w].any()
    assert dark[24 : 24 + h, :AXIS_W].any()
    assert not dark[24 : 24 + h, AXIS_W : AXIS_W + w].any()  # nothing dark over the map
    # the ego marker (blue, a colour no mass takes) at the centre of each panel
    blue = np.all(np.abs(img.astype(int) - EGO_BGR) < 40, axis=-1)
    for k in range(3):
        cx = AXIS_W + k * (w + 4 * scale) + w // 2
        assert blue[24 + h // 2 - 3 : 24 + h // 2 + 4, cx - 3 : cx + 4].any(), k
    assert not blue[24 : 24 + h, AXIS_W : AXIS_W + w // 3].any()  # only there
    # the legend: more than the three pure colours (the mixtures' swatch and the ego's)
    legend = img[24 + h + AXIS_H :]
    assert legend.shape[0] in (LEGEND_H, 2 * LEGEND_H)
    assert blue[24 + h + AXIS_H :].any()
    olive = np.array([0.5 * 0.15 + 0.5 * 0.85, 0.5 * 0.75 + 0.5 * 0.1, 0.5 * 0.2 + 0.5 * 0.1])
    olive_bgr = np.round(olive[::-1] * 255).astype(int)
    assert np.any(np.all(np.abs(legend.astype(int) - olive_bgr) < 12, axis=-1))
    assert not np.array_equal(legend[:LEGEND_H], legend_strip_bgr8(legend.shape[1]))
