"""Previews are bounded by output pixels, and a twin refuses maps that are not a grid early.

Before: two 33 KB maps of shape (1, 4096) made ``traffictwin twin ... --method naive -o T`` take
47 s and 17.6 GB (the preview's ``scale = round(384 / h)`` upscaled each 1-row panel 384 times).
Everything that could allocate like that runs in a subprocess under an address-space limit.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from traffictwin.cli.previews import MAX_PREVIEW_PIXELS, preview_scale

ROOT = Path(__file__).resolve().parents[2]
LIMIT_AS = 3 << 30  # bytes of address space for the subprocesses (torch alone maps ~1 GB)


def _limited(code: str, *args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    wrapper = (
        f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({LIMIT_AS}, {LIMIT_AS}))\n"
        + code
    )
    return subprocess.run(
        [sys.executable, "-c", wrapper, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


@pytest.mark.parametrize(
    "shapes",
    [[(1, 4096)] * 3, [(16, 4096)] * 3, [(4096, 4096)] * 4, [(1, 1)] * 2, [(4096, 1)] * 17],
)
def test_the_preview_never_exceeds_its_pixel_budget(shapes) -> None:
    scale, step = preview_scale(shapes)
    h = -(-max(s[0] for s in shapes) // step)
    w = sum(-(-s[1] // step) for s in shapes) + 4 * (len(shapes) - 1)
    assert scale >= 1 and step >= 1
    assert (h * scale + 46) * (w * scale) <= MAX_PREVIEW_PIXELS, (scale, step)  # + the strips


def test_ordinary_maps_keep_their_preview_scale() -> None:
    assert preview_scale([(256, 176)] * 3) == (2, 1)  # round(384 / 256), as before
    assert preview_scale([(128, 96)] * 3) == (3, 1)


def test_a_one_row_preview_is_built_within_the_limit() -> None:
    code = textwrap.dedent(
        """
        import numpy as np
        from traffictwin.cli.previews import twin_preview
        m = np.stack([np.full((1, 4096), 0.3, np.float32), np.full((1, 4096), 0.2, np.float32)])
        img = twin_preview(m, [m, m])
        print(img.shape[0] * img.shape[1])
        """
    )
    proc = _limited(code)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert int(proc.stdout) <= MAX_PREVIEW_PIXELS  # the panels, titles and legend


def test_twin_refuses_a_map_that_is_not_a_grid_with_the_file_named(tmp_path) -> None:
    maps = []
    for k in (1, 2):
        p = tmp_path / f"m{k}.npz"
        np.savez(
            p,
            m_free=np.full((1, 4096), 0.3, np.float32),
            m_occ=np.full((1, 4096), 0.2, np.float32),
            cell=np.float64(0.5),
        )
        maps.append(str(p))
    code = textwrap.dedent(
        """
        import json, subprocess, sys, resource
        p = subprocess.run([sys.executable, "-m", "traffictwin.cli", *sys.argv[1:]],
                           capture_output=True, text=True, timeout=240)
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        print(json.dumps({"rc": p.returncode, "err": p.stderr, "rss_mb": rss}))
        """
    )
    out = tmp_path / "t"
    args = ["twin", *maps, "--pose", "0,0,0", "--pose", "0,0,0", "--method", "naive"]
    proc = _limited(code, *args, "-o", str(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout)
    assert got["rc"] == 1, got
    lines = got["err"].strip().splitlines()
    assert len(lines) == 1, got["err"]
    assert maps[0] in lines[0] and "1x4096 cells" in lines[0] and "at least 16" in lines[0]
    assert got["rss_mb"] < 200, got
    assert not list(tmp_path.glob("t*"))
