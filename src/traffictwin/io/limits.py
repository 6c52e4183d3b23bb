"""Input sizes read from file headers, checked before anything is decoded.

A 500 KB ``.npz`` can hold an 8000 × 8000 grid (5.6 GB of memory once decoded and stacked), a
770 KB PNG a 16000 × 16000 image (2.6 GB): the compressed size says nothing about the cost of
reading a file. The readers here look only at headers:

- :func:`npz_headers`: shape and dtype of every array of an ``.npz`` from the ``.npy`` header at
  the start of each zip member (``zipfile`` streams the member, so only its first bytes are
  decompressed);
- :func:`image_size`: width and height of a PNG (IHDR chunk), JPEG (SOF marker), BMP (DIB
  header), TIFF (first IFD) or PNM (PBM/PGM/PPM text header) — the formats the CLI and
  :func:`traffictwin.api.read_image` take — without decoding a pixel.

Limits (module defaults, overridable per process by environment variables, read at each call):

- :data:`MAX_GRID_CELLS` (``TRAFFICTWIN_MAX_GRID_CELLS``): elements of one grid array, 4096 × 4096;
- :data:`MAX_ARRAY_BYTES` (``TRAFFICTWIN_MAX_ARRAY_BYTES``): bytes (dtype itemsize × elements) of
  one array of an input ``.npz``; unset, 16 bytes (complex128, the widest element a grid may
  have) × the grid limit, 256 MiB by default: the element
  count alone says nothing of the cost (a 1 MB file whose header says ``|S400000000``, shape (3,),
  announces 1.2 GB). :func:`npz_headers` also refuses arrays that do not hold numbers (strings,
  raw bytes, records, Python objects), negative dimensions, and members whose size in the zip
  directory differs from what their header announces;
- :data:`MAX_IMAGE_PIXELS` (``TRAFFICTWIN_MAX_IMAGE_PIXELS``): pixels (width × height) of one
  image, 4096 × 4096.

Errors are one line naming the file (and array), what was found and what was expected:
:class:`InputFormatError` for a file whose header cannot be read, :class:`InputTooLargeError`
for one over a limit; both are :class:`InputError` (a ``ValueError``).
"""

from __future__ import annotations

import math
import os
import struct
import threading
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

#: elements of one grid array (cells), 4096 × 4096
MAX_GRID_CELLS = 4096 * 4096
#: pixels (width × height) of one image, 4096 × 4096
MAX_IMAGE_PIXELS = 4096 * 4096
#: bytes of one element of the widest grid (complex128): the byte limit is this × the cell limit
GRID_ITEM_BYTES = 16
#: bytes of one array of an input ``.npz`` (a complex128 grid of :data:`MAX_GRID_CELLS` cells)
MAX_ARRAY_BYTES = GRID_ITEM_BYTES * MAX_GRID_CELLS
#: dtype kinds an array of a ``.npz`` may hold: bool, integers, floats, complex numbers
NUMERIC_KINDS = "biufc"
#: weights of one network a model folder or config may describe (the paper's ResNet-50
#: DeepLabV3+ has ~40 M, the DAVE-2 net at 320 x 160 px ~27 M): architecture values are read from
#: model meta and params, and a typo (``base_width: 4096``) would otherwise reach the allocator
MAX_MODEL_PARAMETERS = 250_000_000
ENV_MAX_GRID_CELLS = "TRAFFICTWIN_MAX_GRID_CELLS"
ENV_MAX_ARRAY_BYTES = "TRAFFICTWIN_MAX_ARRAY_BYTES"
ENV_MAX_IMAGE_PIXELS = "TRAFFICTWIN_MAX_IMAGE_PIXELS"
NPY_MAGIC = b"\x93NUMPY"
IMAGE_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "PBM/PGM/PPM")
_MAX_NPY_HEADER = 10_000  # bytes, numpy's own default bound for a .npy header
#: numpy parses a .npy header with ast.literal_eval, which CPython 3.11 cannot run in two threads
#: at once ("SystemError: AST constructor recursion depth mismatch"): every header parse of the
#: package holds this lock (:mod:`traffictwin.io.npz` uses it for the threaded shard loads too)
NPY_HEADER_LOCK = threading.Lock()


class InputError(ValueError):
    """An input file that is refused before it is decoded (one line naming the file)."""


class InputFormatError(InputError):
    """A file whose header is not what its reader expects (not a zip, not a known image)."""


class InputTooLargeError(InputError):
    """A file whose header announces more cells / pixels / bytes than the limit."""


#: ``max_bytes`` default of :func:`npz_headers`: :func:`max_array_bytes` at call time
_DEFAULT_LIMIT = -1


@dataclass(frozen=True)
class ArrayHeader:
    """What an ``.npy`` header says: ``shape``, ``dtype``, the element count ``size`` and the
    bytes of its data ``nbytes`` (itemsize × size; Python integers, no overflow)."""

    shape: tuple[int, ...]
    dtype: np.dtype

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        return self.dtype.itemsize * self.size


def _env_limit(name: str, default: int, unit: str) -> int:
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        value = int(raw)
    except ValueError:
        value = 0
    if value < 1:
        raise InputError(f"{name}: expected a positive integer number of {unit}, got {raw!r}")
    return value


def max_grid_cells() -> int:
    """The grid limit (cells): ``TRAFFICTWIN_MAX_GRID_CELLS`` or :data:`MAX_GRID_CELLS`."""
    return _env_limit(ENV_MAX_GRID_CELLS, MAX_GRID_CELLS, "cells")


def max_array_bytes() -> int:
    """The array limit (bytes): ``TRAFFICTWIN_MAX_ARRAY_BYTES``, or :data:`GRID_ITEM_BYTES` ×
    :func:`max_grid_cells` (:data:`MAX_ARRAY_BYTES` by default)."""
    return _env_limit(ENV_MAX_ARRAY_BYTES, GRID_ITEM_BYTES * max_grid_cells(), "bytes")


def max_image_pixels() -> int:
    """The image limit (pixels): ``TRAFFICTWIN_MAX_IMAGE_PIXELS`` or :data:`MAX_IMAGE_PIXELS`."""
    return _env_limit(ENV_MAX_IMAGE_PIXELS, MAX_IMAGE_PIXELS, "pixels")


def _limit_text(limit: int, default: int, env: str) -> str:
    side = int(round(limit**0.5))
    shown = f"{side}x{side} = {limit:,}" if side * side == limit else f"{limit:,}"
    return (
        f"{shown} (the default; set {env} to change it)"
        if limit == default
        else f"{shown} (from {env})"
    )


def check_grid_cells(shape: Iterable[int], what: str) -> None:
    """:class:`InputTooLargeError` naming ``what`` when an array of ``shape`` has more elements
    than :func:`max_grid_cells`."""
    shape = tuple(int(s) for s in shape)
    cells = int(np.prod(shape, dtype=np.int64)) if shape else 1
    limit = max_grid_cells()
    if cells > limit:
        raise InputTooLargeError(
            f"{what} has shape {'x'.join(map(str, shape))} = {cells:,} cells, more than the limit "
            f"{_limit_text(limit, MAX_GRID_CELLS, ENV_MAX_GRID_CELLS)}"
        )


def check_at_most(owner: str, name: str, value: float, bound: float) -> None:
    """``ValueError`` naming ``owner.name``, its value and the bound when ``value > bound`` (an
    architecture value read from model meta or params)."""
    if value > bound:
        raise ValueError(f"{owner}.{name} is {value}, more than its bound {bound}")


def check_parameter_budget(owner: str, parameters: int, fields: str) -> None:
    """``ValueError`` when an architecture's estimated weight count exceeds
    :data:`MAX_MODEL_PARAMETERS`, naming the fields that set it."""
    if parameters > MAX_MODEL_PARAMETERS:
        raise ValueError(
            f"{owner}: {fields} make ~{parameters:,} weights, more than the bound "
            f"{MAX_MODEL_PARAMETERS:,}"
        )


# ============================================================================ .npz


def _read_npy_header(fh: BinaryIO, where: str) -> ArrayHeader:
    fmt = np.lib.format
    try:
        with NPY_HEADER_LOCK:
            major, minor = fmt.read_magic(fh)
            if (major, minor) == (1, 0):
                shape, _fortran, dtype = fmt.read_array_header_1_0(fh, _MAX_NPY_HEADER)
            elif (major, minor) in ((2, 0), (3, 0)):  # 3.0 differs only in the encoding
                shape, _fortran, dtype = fmt.read_array_header_2_0(fh, _MAX_NPY_HEADER)
            else:
                raise ValueError(f"unsupported .npy format version {major}.{minor}")
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, SyntaxError) as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputFormatError(f"{where}: not a readable .npy array header ({msg})") from None
    return ArrayHeader(tuple(int(s) for s in shape), np.dtype(dtype))


def _check_array(head: ArrayHeader, what: str, limit: int | None) -> None:
    """Refuse, from its header, an array that holds no numbers, has a negative dimension or
    announces more than ``limit`` bytes (``None``: no byte limit)."""
    if head.dtype.hasobject:
        raise InputFormatError(f"{what} holds Python objects (pickled data, never loaded)")
    if head.dtype.kind not in NUMERIC_KINDS or head.dtype.subdtype is not None:
        raise InputFormatError(
            f"{what} has dtype {head.dtype.str!r}, not numbers (expected bool, integer, float "
            "or complex elements)"
        )
    if any(s < 0 for s in head.shape):
        raise InputFormatError(f"{what}: its header announces a negative shape {head.shape}")
    if limit is not None and head.nbytes > limit:
        shape = "x".join(map(str, head.shape)) or "()"
        raise InputTooLargeError(
            f"{what} of shape {shape} and dtype {head.dtype.str!r} announces {head.nbytes:,} "
            f"bytes, more than the limit {limit:,} ("
            + (
                f"from {ENV_MAX_ARRAY_BYTES})"
                if os.environ.get(ENV_MAX_ARRAY_BYTES, "").strip()
                else f"{GRID_ITEM_BYTES} bytes x the grid limit; set {ENV_MAX_ARRAY_BYTES} to "
                "change it)"
            )
        )


def npz_headers(
    path: str | os.PathLike,
    keys: Iterable[str] | None = None,
    *,
    max_bytes: int | None = _DEFAULT_LIMIT,
) -> dict[str, ArrayHeader]:
    """Shape and dtype of the arrays of the ``.npz`` at ``path`` (only ``keys`` when given; the
    key of member ``name.npy`` is ``name``), read from the ``.npy`` headers: no array data is
    decompressed. Members that are not ``.npy`` files are left out.

    Raises :class:`InputFormatError` when the file is not a zip archive (text, a bare ``.npy``
    renamed ``.npz``, ...), a header is unreadable, an array holds no numbers (Python objects,
    strings, raw bytes, records), has a negative dimension, or its member's size in the zip
    directory is not the header's length plus itemsize × elements; :class:`InputTooLargeError`
    when an array announces more than ``max_bytes`` bytes (default :func:`max_array_bytes`;
    ``None``: no byte limit, for dataset shards whose size the config bounds).
    """
    p = Path(path)
    limit = max_array_bytes() if max_bytes == _DEFAULT_LIMIT else max_bytes
    wanted = None if keys is None else set(keys)
    out: dict[str, ArrayHeader] = {}
    try:
        with open(p, "rb") as fh:
            try:
                zf = zipfile.ZipFile(fh)
            except zipfile.BadZipFile:
                fh.seek(0)
                what = (
                    "it is a single .npy array, not a zip archive"
                    if fh.read(len(NPY_MAGIC)) == NPY_MAGIC
                    else "not a zip archive"
                )
                raise InputFormatError(
                    f"{p}: not a readable .npz file: {what} "
                    "(a .npz is a zip of .npy arrays, as numpy.savez writes it)"
                ) from None
            with zf:
                for info in zf.infolist():
                    if info.is_dir() or not info.filename.endswith(".npy"):
                        continue
                    key = info.filename[: -len(".npy")]
                    if wanted is not None and key not in wanted:
                        continue
                    with zf.open(info) as member:
                        head = _read_npy_header(member, f"{p}: array '{key}'")
                        header_len = member.tell()
                    _check_array(head, f"{p}: array '{key}'", limit)
                    if info.file_size != header_len + head.nbytes:
                        raise InputFormatError(
                            f"{p}: array '{key}': its header announces {head.nbytes:,} bytes of "
                            f"data, the archive member holds {info.file_size - header_len:,} "
                            "(a corrupt or crafted file)"
                        )
                    out[key] = head
    except InputFormatError:
        raise
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        NotImplementedError,
        OSError,
        EOFError,
    ) as exc:
        msg = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputFormatError(
            f"{p}: not a readable .npz file ({type(exc).__name__}: {msg})"
        ) from None
    return out


# ============================================================================ images


def _png_size(fh: BinaryIO) -> tuple[int, int]:
    head = fh.read(24)  # signature, IHDR length and type, width, height
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise ValueError("PNG without an IHDR chunk")
    return struct.unpack(">II", head[16:24])


def _jpeg_size(fh: BinaryIO) -> tuple[int, int]:
    fh.seek(2)  # after SOI
    sof = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
    standalone = {0x01, *range(0xD0, 0xD9)}  # TEM, RSTn, SOI: no length field
    while True:
        b = fh.read(1)
        if not b:
            raise ValueError("JPEG without a frame header (SOF marker)")
        if b != b"\xff":
            continue
        marker = fh.read(1)
        while marker == b"\xff":  # fill bytes
            marker = fh.read(1)
        if not marker:
            raise ValueError("JPEG without a frame header (SOF marker)")
        m = marker[0]
        if m in standalone or m == 0x00:
            continue
        if m in (0xD9, 0xDA):  # EOI, or scan data before any frame header
            raise ValueError("JPEG without a frame header (SOF marker)")
        length = fh.read(2)
        if len(length) < 2:
            raise ValueError("truncated JPEG segment")
        n = struct.unpack(">H", length)[0]
        if m in sof:
            seg = fh.read(5)
            if len(seg) < 5:
                raise ValueError("truncated JPEG frame header")
            h, w = struct.unpack(">HH", seg[1:5])
            return w, h
        if n < 2:
            raise ValueError("corrupt JPEG segment length")
        fh.seek(n - 2, os.SEEK_CUR)


def _bmp_size(fh: BinaryIO) -> tuple[int, int]:
    head = fh.read(26)
    if len(head) < 26:
        raise ValueError("truncated BMP header")
    dib = struct.unpack("<I", head[14:18])[0]
    if dib == 12:  # BITMAPCOREHEADER: 16-bit unsigned sizes
        w, h = struct.unpack("<HH", head[18:22])
    else:
        w, h = struct.unpack("<ii", head[18:26])
    return abs(w), abs(h)  # a negative height is a top-down bitmap


def _tiff_size(fh: BinaryIO) -> tuple[int, int]:
    head = fh.read(8)
    order = "<" if head[:2] == b"II" else ">"
    if struct.unpack(order + "H", head[2:4])[0] != 42:
        raise ValueError("BigTIFF or unknown TIFF variant")
    fh.seek(struct.unpack(order + "I", head[4:8])[0])
    raw = fh.read(2)
    if len(raw) < 2:
        raise ValueError("truncated TIFF directory")
    n = struct.unpack(order + "H", raw)[0]
    entries = fh.read(12 * n)
    if len(entries) < 12 * n:
        raise ValueError("truncated TIFF directory")
    dims: dict[int, int] = {}
    for i in range(n):
        tag, typ = struct.unpack(order + "HH", entries[12 * i : 12 * i + 4])
        if tag in (256, 257):  # ImageWidth, ImageLength: SHORT or LONG
            val = entries[12 * i + 8 : 12 * i + 12]
            dims[tag] = struct.unpack(
                order + ("H" if typ == 3 else "I"), val[: 2 if typ == 3 else 4]
            )[0]
    if 256 not in dims or 257 not in dims:
        raise ValueError("TIFF directory without ImageWidth/ImageLength")
    return dims[256], dims[257]


def _pnm_size(fh: BinaryIO) -> tuple[int, int]:
    fh.seek(2)
    fields: list[int] = []
    token = b""
    while len(fields) < 2:
        c = fh.read(1)
        if not c:
            raise ValueError("truncated PNM header")
        if c == b"#":  # a comment runs to the end of the line
            while c not in (b"\n", b"\r", b""):
                c = fh.read(1)
            c = b" "
        if c.isspace():
            if token:
                fields.append(int(token))
                token = b""
        elif c.isdigit() and len(token) < 12:
            token += c
        else:
            raise ValueError("malformed PNM header")
    return fields[0], fields[1]


def image_size(path: str | os.PathLike) -> tuple[str, int, int]:
    """``(format, width, height)`` (px) of the image at ``path`` from its header only.

    Raises :class:`InputFormatError` (``"not a readable image"``) for a file that is none of
    :data:`IMAGE_FORMATS` or whose header is truncated or corrupt.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            sig = fh.read(8)
            fh.seek(0)
            if sig.startswith(b"\x89PNG\r\n\x1a\n"):
                kind, (w, h) = "PNG", _png_size(fh)
            elif sig.startswith(b"\xff\xd8"):
                kind, (w, h) = "JPEG", _jpeg_size(fh)
            elif sig.startswith(b"BM"):
                kind, (w, h) = "BMP", _bmp_size(fh)
            elif sig[:4] in (b"II*\x00", b"MM\x00*"):
                kind, (w, h) = "TIFF", _tiff_size(fh)
            elif sig[:1] == b"P" and sig[1:2] in b"123456" and sig[2:3].isspace():
                kind, (w, h) = "PNM", _pnm_size(fh)
            else:
                raise InputFormatError(
                    f"{p}: not a readable image (not one of {', '.join(IMAGE_FORMATS)})"
                )
    except InputFormatError:
        raise
    except OSError as exc:
        raise InputFormatError(f"{p}: not a readable image ({exc.strerror or exc})") from None
    except (ValueError, struct.error) as exc:
        raise InputFormatError(f"{p}: not a readable image (corrupt header: {exc})") from None
    if w < 1 or h < 1:
        raise InputFormatError(f"{p}: not a readable image ({kind} header says {w}x{h} px)")
    return kind, int(w), int(h)


def check_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` (px) of the image at ``path`` from its header (:func:`image_size`);
    :class:`InputTooLargeError` when ``width × height`` exceeds :func:`max_image_pixels`."""
    kind, w, h = image_size(path)
    limit = max_image_pixels()
    if w * h > limit:
        raise InputTooLargeError(
            f"{Path(path)}: {kind} image of {w}x{h} px (W x H) = {w * h:,} pixels, more than the "
            f"limit {_limit_text(limit, MAX_IMAGE_PIXELS, ENV_MAX_IMAGE_PIXELS)}"
        )
    return w, h
