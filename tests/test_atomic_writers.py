"""The one CSV writer and the one figure writer (traffictwin.io.atomic): the bytes each former
caller wrote with its own to_csv / savefig arguments, written atomically."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from traffictwin.io.atomic import save_figure, write_csv_atomic  # noqa: E402

FRAME = pd.DataFrame({"a": [1, 2], "x": [1 / 3, np.nan], "s": ["p", "q"]})


@pytest.mark.parametrize("float_format", ["%.6g", "%.9g", None])
def test_csv_bytes_equal_to_csv(tmp_path: Path, float_format: str | None) -> None:
    out = write_csv_atomic(tmp_path / "sub" / "t.csv", FRAME, float_format=float_format)
    assert out == tmp_path / "sub" / "t.csv"
    expected = FRAME.to_csv(index=False, float_format=float_format, lineterminator="\n")
    assert out.read_bytes() == expected.encode()
    assert [p.name for p in out.parent.iterdir()] == ["t.csv"]  # no temp file left
    if float_format == "%.6g":
        assert out.read_text() == "a,x,s\n1,0.333333,p\n2,,q\n"


def _figure() -> plt.Figure:
    fig, ax = plt.subplots(figsize=(2, 1.5))
    ax.plot([0, 1, 2], [0, 1, 0])
    return fig


@pytest.mark.parametrize(
    "kwargs",
    [
        {"dpi": 110, "bbox_inches": "tight"},  # risk and fusion figures
        {"dpi": 90, "bbox_inches": None, "metadata": {"Software": None}},  # fusion data figure
        {"dpi": 110, "bbox_inches": None},  # the stereo resolution benchmark
    ],
)
def test_figure_bytes_equal_savefig(tmp_path: Path, kwargs: dict) -> None:
    direct = {k: v for k, v in kwargs.items() if v is not None}
    ref = _figure()
    ref.savefig(tmp_path / "ref.png", format="png", **direct)
    plt.close(ref)
    fig = _figure()
    out = save_figure(fig, tmp_path / "f.png", **kwargs)
    assert out == tmp_path / "f.png"
    assert out.read_bytes() == (tmp_path / "ref.png").read_bytes()
    assert not plt.fignum_exists(fig.number)  # closed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png", "ref.png"]


def test_figure_defaults_are_110_dpi_tight(tmp_path: Path) -> None:
    ref = _figure()
    ref.savefig(tmp_path / "ref.png", format="png", dpi=110, bbox_inches="tight")
    plt.close(ref)
    out = save_figure(_figure(), tmp_path / "f.png")
    assert out.read_bytes() == (tmp_path / "ref.png").read_bytes()
