"""Input sizes are read from file headers and refused before anything is decoded; a file that is
not a ``.npz`` archive gets one clear line.

Before: a 500 KB ``.npz`` of two 8000 x 8000 grids cost 5.6 GB of memory and 12 s before
``fuse`` refused it, a 250 KB 16000 x 16000 PNG 2.6 GB for ``risk``, a crafted ``|S400000000``
header 2.0 GB and 7.7 s. The fixtures write such files by streaming zeros through zlib (never
holding the grid or the image in memory). The refusal is checked to decode nothing (``np.load`` /
``cv2.imread`` are never called) and, in process, to take under 1 CPU-second and to allocate
little (``tracemalloc``: NumPy's allocations are traced, OpenCV's are not, hence the first
check); through the CLI the peak RSS of the refused command is under 200 MB and compared with
that of the same command on the small example input (torch alone is ~250 MB there). No wall-time
assertion through the CLI (interpreter start-up and imports dominate): re-measure by hand with
``/usr/bin/time -v python -m traffictwin.cli fuse BIG.npz ...``.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
import time
import tracemalloc
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from _cli_models import POSE1, POSE2, save_risk

from traffictwin import api
from traffictwin.io import limits

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_MAP1 = ROOT / "examples" / "fuse" / "ci" / "map1.npz"
EXAMPLE_MAP2 = ROOT / "examples" / "fuse" / "ci" / "map2.npz"
EXAMPLE_LEFT = ROOT / "examples" / "risk" / "000_left.png"
EXAMPLE_RIGHT = ROOT / "examples" / "risk" / "000_right.png"
BIG_GRID = 8000  # cells per side
BIG_IMAGE = 16000  # px per side
MB = 1 << 20


def write_big_npz(path: Path, n: int = BIG_GRID) -> Path:
    """A valid ``.npz`` of float32 zero grids ``m_free``, ``m_occ`` of ``n`` x ``n`` (~250 KB each)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key in ("m_free", "m_occ"):
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fh:
                header = {"descr": "<f4", "fortran_order": False, "shape": (n, n)}
                np.lib.format.write_array_header_1_0(fh, header)
                rows = bytes(4 * n * 100)
                for _ in range(n // 100):
                    fh.write(rows)
    return path


def write_big_png(path: Path, n: int = BIG_IMAGE) -> Path:
    """A valid 8-bit grayscale PNG of ``n`` x ``n`` zeros, written chunk by chunk."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    z = zlib.compressobj(9)
    rows = bytes(n + 1) * 100  # filter byte 0 + n zero pixels, 100 rows
    idat = b"".join(z.compress(rows) for _ in range(n // 100)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", n, n, 8, 0, 0, 0, 0)  # 8-bit grayscale
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")
    )
    return path


@pytest.fixture(scope="module")
def big(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("big")
    return {"npz": write_big_npz(d / "big.npz"), "png": write_big_png(d / "big.png")}


@pytest.fixture
def no_decoding(monkeypatch):
    """``np.load`` and ``cv2.imread`` fail the test if called."""

    def boom(*args, **kwargs):
        raise AssertionError(f"decoded {args[:1]} although the header says it is too large")

    monkeypatch.setattr(np, "load", boom)
    monkeypatch.setattr(cv2, "imread", boom)


#: CPU seconds a refusal may take (the target: refused within 1 s; CPU time, not wall time, so a
#: loaded machine does not fail it)
REFUSAL_CPU_S = 1.0


def _peak_traced(fn) -> tuple[int, BaseException | None]:
    """``fn()``'s traced peak allocation (bytes) and the exception it raised; fails the test when
    it took more than :data:`REFUSAL_CPU_S` of CPU time."""
    start = time.process_time()
    tracemalloc.start()
    try:
        fn()
        err = None
    except Exception as exc:  # noqa: BLE001 - returned for the caller's assertions
        err = exc
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    cpu = time.process_time() - start
    assert cpu < REFUSAL_CPU_S, f"took {cpu:.2f} CPU-s ({err!r})"
    return peak, err


def _one_line(text: str, *needles: str) -> str:
    lines = [ln for ln in str(text).strip().splitlines() if ln]
    assert len(lines) == 1, text
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ headers


def test_fixtures_are_small_on_disk_and_valid(big):
    assert big["npz"].stat().st_size < MB and big["png"].stat().st_size < MB
    heads = limits.npz_headers(big["npz"])
    assert {k: (h.shape, h.dtype.str) for k, h in heads.items()} == {
        "m_free": ((BIG_GRID, BIG_GRID), "<f4"),
        "m_occ": ((BIG_GRID, BIG_GRID), "<f4"),
    }
    assert limits.image_size(big["png"]) == ("PNG", BIG_IMAGE, BIG_IMAGE)


def test_npz_headers_decompress_nothing(big):
    peak, err = _peak_traced(lambda: limits.npz_headers(big["npz"]))
    assert err is None and peak < 5 * MB, (peak, err)
    assert list(limits.npz_headers(big["npz"], ["m_occ"])) == ["m_occ"]


@pytest.mark.parametrize(
    ("ext", "params"),
    [
        (".png", []),
        (".jpg", []),
        (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
        (".bmp", []),
        (".tif", []),
        (".tiff", [cv2.IMWRITE_TIFF_COMPRESSION, 1]),
        (".ppm", []),
        (".pgm", []),
        (".pbm", []),
    ],
)
def test_image_size_from_the_header_of_every_format_read(tmp_path, ext, params):
    img = np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    if ext in (".pgm", ".pbm"):
        img = img[..., 0]
    path = tmp_path / f"x{ext}"
    assert cv2.imwrite(str(path), img, params)
    assert limits.image_size(path)[1:] == (53, 37)
    assert api.read_image(path).shape == (37, 53, 3)


# ------------------------------------------------------------------ refused before decoding


def test_load_masses_refuses_a_huge_grid_before_decoding(big, no_decoding):
    peak, err = _peak_traced(lambda: api.load_masses(big["npz"]))
    assert isinstance(err, api.ApiError), err
    _one_line(err, str(big["npz"]), "'m_free'", "8000x8000", "limit 4096x4096", "MAX_GRID_CELLS")
    assert peak < 50 * MB, peak


def test_read_image_refuses_a_huge_image_before_decoding(big, no_decoding):
    peak, err = _peak_traced(lambda: api.read_image(big["png"]))
    assert isinstance(err, api.ApiError), err
    _one_line(err, str(big["png"]), "16000x16000", "limit 4096x4096", "MAX_IMAGE_PIXELS")
    assert peak < 50 * MB, peak


def test_limits_follow_the_environment(monkeypatch):
    m, _, _ = api.load_masses(EXAMPLE_MAP1)  # 128 x 96 cells
    assert api.read_image(EXAMPLE_LEFT).ndim == 3
    monkeypatch.setenv(limits.ENV_MAX_GRID_CELLS, str(m.shape[1] * m.shape[2] - 1))
    with pytest.raises(
        api.ApiError, match=r"128x96 = 12,288 cells.*from TRAFFICTWIN_MAX_GRID_CELLS"
    ):
        api.load_masses(EXAMPLE_MAP1)
    monkeypatch.setenv(limits.ENV_MAX_IMAGE_PIXELS, "100")
    with pytest.raises(
        api.ApiError, match=r"limit 10x10 = 100 \(from TRAFFICTWIN_MAX_IMAGE_PIXELS"
    ):
        api.read_image(EXAMPLE_LEFT)
    monkeypatch.setenv(limits.ENV_MAX_IMAGE_PIXELS, "many")
    with pytest.raises(api.ApiError, match="TRAFFICTWIN_MAX_IMAGE_PIXELS: expected a positive"):
        api.read_image(EXAMPLE_LEFT)


# ------------------------------------------------------------------ not a .npz


def test_text_and_a_renamed_npy_are_one_clear_line(tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("m_free = 0.5\nm_occ = 0.25\n")
    npy = tmp_path / "grid.npz"
    with open(npy, "wb") as fh:
        np.save(fh, np.zeros((4, 4), np.float32))
    obj = tmp_path / "obj.npz"
    np.savez(obj, m_free=np.array([{"a": 1}], dtype=object), m_occ=np.zeros((2, 2)))
    cases = {
        text: "not a zip archive",
        npy: "a single .npy array, not a zip archive",
        obj: "pickled data, never loaded",
    }
    for path, needle in cases.items():
        with pytest.raises(api.ApiError) as info:
            api.load_masses(path)
        line = _one_line(info.value, str(path), needle, "expected arrays m_free and m_occ")
        for bad in ("unsafely", "allow_pickle", "context manager", "TypeError"):
            assert bad not in line, line


def test_a_corrupt_image_header_is_one_line(tmp_path):
    for name, data in {
        "garbage.png": b"\x89PNG garbage",
        "short.png": b"\x89PNG\r\n\x1a\n\x00\x00",
        "text.jpg": b"hello",
        "trunc.jpg": b"\xff\xd8\xff\xe0\x00\x10JFIF",
    }.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(api.ApiError) as info:
            api.read_image(tmp_path / name)
        _one_line(info.value, name, "not a readable image")


# ------------------------------------------------------------------ through the CLI


_WRAPPER = textwrap.dedent(
    """
    import json, resource, subprocess, sys
    p = subprocess.run([sys.executable, "-m", "traffictwin.cli", *sys.argv[1:]],
                       capture_output=True, text=True, timeout=600)
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB on Linux
    print(json.dumps({"rc": p.returncode, "err": p.stderr, "rss_mb": rss / 1024}))
    """
)


def _cli(*args: str | Path, cwd: Path) -> dict:
    """Run ``traffictwin ARGS`` in a fresh wrapper process: its exit code, stderr, peak RSS (MB)."""
    proc = subprocess.run(
        [sys.executable, "-c", _WRAPPER, *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.integration  # four CLI subprocesses (~10 s)
def test_cli_refuses_huge_inputs_with_one_line_and_little_memory(big, tmp_path):
    risk = save_risk(tmp_path / "risk")
    poses = ["--pose1", POSE1, "--pose2", POSE2, "--model", tmp_path / "no-model"]
    fuse_small = _cli("fuse", EXAMPLE_MAP1, EXAMPLE_MAP2, *poses, "-o", "o", cwd=tmp_path)
    fuse_big = _cli("fuse", big["npz"], EXAMPLE_MAP2, *poses, "-o", "o", cwd=tmp_path)
    risk_small = _cli("risk", EXAMPLE_LEFT, EXAMPLE_RIGHT, "--model", risk, cwd=tmp_path)
    risk_big = _cli("risk", big["png"], EXAMPLE_RIGHT, "--model", risk, cwd=tmp_path)

    assert fuse_small["rc"] == 1 and "no-model" in fuse_small["err"], fuse_small  # maps read
    assert fuse_big["rc"] == 1, fuse_big
    _one_line(fuse_big["err"], "error", str(big["npz"]), "8000x8000", "limit 4096x4096")
    assert risk_small["rc"] == 0, risk_small
    assert risk_big["rc"] == 1, risk_big
    _one_line(risk_big["err"], "error", str(big["png"]), "16000x16000", "limit 4096x4096")
    # decoding the big grid took 5.6 GB and the image 2.6 GB; the refusals cost what the small
    # inputs cost (the fuse refusal does not even import torch)
    assert fuse_big["rss_mb"] < fuse_small["rss_mb"] + 100, (fuse_big, fuse_small)
    assert risk_big["rss_mb"] < risk_small["rss_mb"] + 100, (risk_big, risk_small)
    # the target: refused with < 200 MB (every image header is checked before the model,
    # and torch, load)
    assert fuse_big["rss_mb"] < 200 and risk_big["rss_mb"] < 200, (fuse_big, risk_big)
    assert not (tmp_path / "o.npz").exists()


# ------------------------------------------------------------------ byte sizes, not element counts


def write_crafted_npz(path: Path, descr: str, shape: tuple[int, ...], data: int = 64) -> Path:
    """An ``.npz`` whose ``m_free`` / ``m_occ`` headers announce ``descr`` x ``shape`` but whose
    members hold only ``data`` zero bytes after the header (what a crafted file may declare)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for key in ("m_free", "m_occ"):
            with zf.open(f"{key}.npy", "w") as fh:
                header = {"descr": descr, "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(fh, header)
                fh.write(bytes(data))
    return path


def test_load_masses_refuses_a_wide_dtype_before_allocating(tmp_path, no_decoding):
    # three elements pass the cell limit; each announces 400 MB (before: 1.2 GB allocated and
    # 7.7 s before the dtype was refused)
    path = write_crafted_npz(tmp_path / "wide.npz", "|S400000000", (3,))
    peak, err = _peak_traced(lambda: api.load_masses(path))
    assert isinstance(err, api.ApiError), err
    _one_line(err, str(path), "'m_free'", "'|S400000000'", "not numbers")
    assert peak < 5 * MB, peak


@pytest.mark.parametrize(
    ("descr", "shape", "needle"),
    [
        ("<f4", (-3, 4), "negative shape"),
        ("<f4", (2**40, 2**40), "announces"),  # 2**80 elements: no int64 overflow
        ("<f4", (100, 100), "the archive member holds 64"),  # header and data disagree
        ("|V400000000", (3,), "not numbers"),
        ("<U100000000", (3,), "not numbers"),
    ],
)
def test_npz_headers_refuse_what_the_header_cannot_honour(tmp_path, descr, shape, needle):
    path = write_crafted_npz(tmp_path / "c.npz", descr, shape)
    peak, err = _peak_traced(lambda: limits.npz_headers(path))
    assert isinstance(err, limits.InputError), err
    _one_line(err, str(path), "'m_free'", needle)
    assert peak < 5 * MB, peak


def test_the_byte_limit_counts_itemsize_times_elements(monkeypatch):
    heads = limits.npz_headers(EXAMPLE_MAP1)
    assert heads["m_free"].nbytes == heads["m_free"].size * heads["m_free"].dtype.itemsize
    monkeypatch.setenv(limits.ENV_MAX_ARRAY_BYTES, str(heads["m_free"].nbytes - 1))
    with pytest.raises(limits.InputTooLargeError, match="from TRAFFICTWIN_MAX_ARRAY_BYTES"):
        limits.npz_headers(EXAMPLE_MAP1)
    with pytest.raises(api.ApiError, match=r"'m_free' of shape 128x96 .* announces 49,152 bytes"):
        api.load_masses(EXAMPLE_MAP1)
    assert limits.npz_headers(EXAMPLE_MAP1, max_bytes=None)  # dataset shards: no byte limit
    monkeypatch.delenv(limits.ENV_MAX_ARRAY_BYTES)
    monkeypatch.setenv(limits.ENV_MAX_GRID_CELLS, "100")  # the byte limit follows the grid limit
    assert limits.max_array_bytes() == 100 * limits.GRID_ITEM_BYTES


def test_read_npz_checks_headers_before_decompressing(tmp_path):
    from traffictwin.io.npz import DatasetError, read_npz

    path = write_crafted_npz(tmp_path / "shard.npz", "|S400000000", (3,))
    peak, err = _peak_traced(lambda: read_npz(path))
    assert isinstance(err, DatasetError), err
    _one_line(err, str(path), "not numbers")
    assert peak < 5 * MB, peak
    path = write_crafted_npz(tmp_path / "short.npz", "<f8", (1000, 1000))
    peak, err = _peak_traced(lambda: read_npz(path))
    assert isinstance(err, DatasetError) and "announces 8,000,000 bytes" in str(err), err
    assert peak < 5 * MB, peak
