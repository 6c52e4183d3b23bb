"""The one checkpoint format of trained networks (fusion and risk), without Lightning.

:func:`model_checkpoint` builds it, :func:`save_model_checkpoint` writes it atomically,
:func:`read_model_checkpoint` reads it back with ``torch.load(weights_only=True)`` (tensors and
plain containers only: nothing unpickled runs code) and checks it, :func:`net_state_dict` gives
the network's weights. It lives here rather than in :mod:`traffictwin.trainer` so that loading a
model for inference (CLI, :mod:`traffictwin.api`) imports torch but not Lightning or MLflow;
:mod:`traffictwin.trainer` re-exports every name. torch itself loads in the functions that save
or read a checkpoint, so importing the module (the training settings do) costs nothing.
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from traffictwin.io.atomic import write_bytes_atomic
from traffictwin.io.outputs import check_regular_file

if TYPE_CHECKING:
    import torch

MODEL_FORMAT = "traffictwin-model/1"


class CheckpointError(RuntimeError):
    """A model checkpoint is missing, unreadable or not of :data:`MODEL_FORMAT`."""


def model_checkpoint(
    problem: str,
    architecture: Mapping[str, Any],
    state_dict: Mapping[str, torch.Tensor],
    meta: Mapping[str, Any] | None = None,
    *,
    prefix: str = "net.",
    **extra: Any,
) -> dict[str, Any]:
    """The checkpoint dict: ``state_dict`` (tensors on CPU, keys ``prefix`` + the network's own,
    as in the LightningModule that holds the network as ``net``) and a ``traffictwin`` block
    (``format``, ``problem``, ``architecture`` and the JSON-able ``meta``); ``extra`` top-level
    keys (e.g. ``epoch``, ``global_step``). Loadable with ``torch.load(weights_only=True)``."""
    info = json.loads(json.dumps(dict(meta or {}), default=str))
    info.update(
        format=MODEL_FORMAT,
        problem=problem,
        architecture=json.loads(json.dumps(dict(architecture), default=str)),
    )
    state = {
        (k if k.startswith(prefix) else prefix + k): v.detach().cpu().clone()
        for k, v in state_dict.items()
    }
    return {"state_dict": state, **extra, "traffictwin": info}


def save_model_checkpoint(path: str | Path, ckpt: Mapping[str, Any]) -> Path:
    """Write ``ckpt`` (see :func:`model_checkpoint`) to ``path`` atomically; returns ``path``.

    Serialised through a buffer, so the zip archive inside is always named ``archive`` (given a
    file name, torch.save names it after the temp file): the same checkpoint gives the same bytes.
    """
    import torch

    buf = io.BytesIO()
    torch.save(dict(ckpt), buf)
    write_bytes_atomic(path, buf.getvalue())
    return Path(path)


def read_model_checkpoint(
    path: str | Path,
    problem: str | None = None,
    error: type[Exception] = CheckpointError,
    map_location: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Read a checkpoint of :data:`MODEL_FORMAT` (``weights_only=True``); errors (``error``) name the file.

    ``problem``: the ``traffictwin.problem`` it must have (a checkpoint without that key is
    accepted as any problem).
    """
    import torch

    path = Path(path)
    _regular(path, "a torch checkpoint", error)
    try:
        ck = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 — any unpickling failure means the file is unusable
        raise error(
            f"{path}: not a readable torch checkpoint ({type(exc).__name__}: {exc})"
        ) from None
    info = ck.get("traffictwin") if isinstance(ck, dict) else None
    if not isinstance(info, dict) or info.get("format") != MODEL_FORMAT or "state_dict" not in ck:
        what = f"traffictwin {problem}" if problem else "traffictwin"
        raise error(f"{path}: not a {what} checkpoint (expected format '{MODEL_FORMAT}')")
    if problem is not None and info.get("problem", problem) != problem:
        raise error(f"{path}: a {info.get('problem')} model checkpoint, expected a {problem} model")
    return ck


def _regular(path: Path, what: str, error: type[Exception]) -> None:
    """``path`` is a regular file (stat before open: a FIFO never blocks), else ``error``."""
    try:
        check_regular_file(path, what)
    except OSError as exc:
        raise error(f"{path}: {exc.strerror or exc}") from None


def net_state_dict(ckpt: Mapping[str, Any], prefix: str = "net.") -> dict[str, torch.Tensor]:
    """The network's weights of a checkpoint (``prefix`` removed)."""
    return {k[len(prefix) :]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)}


# ---------------------------------------------------------------------------------------------
# a model folder: model.ckpt + model_meta.json written and read as one unit

CKPT_SHA_KEY = "ckpt_sha256"


def save_model_files(
    ckpt_path: str | Path,
    ckpt: Mapping[str, Any],
    meta_path: str | Path | None = None,
    meta: Mapping[str, Any] | None = None,
) -> str:
    """Write a checkpoint and its metadata as one unit; returns the checkpoint's SHA-256.

    Order: the old ``meta_path`` is removed first, then ``ckpt`` is written atomically
    (:func:`save_model_checkpoint`), then ``meta`` + ``{"ckpt_sha256": <hex>}`` atomically last
    (indented, key-sorted JSON). A kill at any point leaves either the old pair, or a checkpoint
    without metadata, or the new pair — never a checkpoint beside another run's metadata;
    :func:`check_model_pair` refuses a pair whose hash does not match.
    """
    from traffictwin.io.atomic import write_json_atomic
    from traffictwin.io.shards import sha256_file

    if meta_path is not None:
        Path(meta_path).unlink(missing_ok=True)
    save_model_checkpoint(ckpt_path, ckpt)
    digest = sha256_file(ckpt_path)
    if meta_path is not None:
        write_json_atomic(meta_path, {**dict(meta or {}), CKPT_SHA_KEY: digest})
    return digest


def read_model_meta(
    meta_path: str | Path, error: type[Exception] = CheckpointError
) -> dict[str, Any]:
    """``model_meta.json`` as a dict; a missing, non-UTF-8, invalid or non-object file is an
    ``error`` that names it (the meta is half of the model's seal: a model without it is refused)."""
    meta_path = Path(meta_path)
    try:
        check_regular_file(meta_path, "the model's JSON metadata")  # a FIFO would block
        text = meta_path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise error(
            f"{meta_path}: missing; a model folder needs model.ckpt and its model_meta.json "
            "(written together by the training stage; re-run it)"
        ) from None
    except UnicodeDecodeError:
        raise error(f"{meta_path}: not UTF-8 text; expected the model's JSON metadata") from None
    except OSError as exc:
        raise error(f"{meta_path}: unreadable ({exc.strerror or exc})") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise error(
            f"{meta_path}: expected a JSON object of model metadata, got {type(meta).__name__}"
        )
    return meta


def _json_value(v: Any) -> Any:
    return json.loads(json.dumps(v, default=str))


def check_model_pair(
    ckpt_path: str | Path,
    meta: Mapping[str, Any] | None,
    error: type[Exception] = CheckpointError,
    info: Mapping[str, Any] | None = None,
    sealed: tuple[str, ...] = (),
) -> None:
    """The seal of a model folder: ``meta`` (``model_meta.json``) must record the SHA-256 of
    ``ckpt_path`` (a missing meta or key is a refusal, not a skip), and every ``sealed`` key the
    loader trusts must equal the checkpoint's own copy in ``info`` (its ``traffictwin`` block,
    covered by that hash): an edited or deleted ``domain`` in the JSON is refused. ``error``
    names the folder. MLflow artifacts carry the key too (:func:`traffictwin.trainer.log_model`)."""
    ckpt_path = Path(ckpt_path)
    meta_name = "model_meta.json"
    if meta is None:
        raise error(
            f"{ckpt_path.parent}: no {meta_name} beside {ckpt_path.name}; re-run the training stage"
        )
    if CKPT_SHA_KEY not in meta:
        raise error(
            f"{ckpt_path.parent / meta_name}: no '{CKPT_SHA_KEY}' (the checkpoint's seal); the "
            "file was replaced or edited — re-run the training stage that wrote the model"
        )
    from traffictwin.io.shards import sha256_file

    _regular(ckpt_path, "a torch checkpoint", error)
    want, got = str(meta[CKPT_SHA_KEY]), sha256_file(ckpt_path)
    if want != got:
        raise error(
            f"{ckpt_path.parent}: {ckpt_path.name} and its {meta_name} are not one pair "
            f"(SHA-256 of {ckpt_path.name} {got[:12]}…, {meta_name} records {want[:12]}…): "
            f"a training was interrupted or a file was replaced; re-run the training stage"
        )
    for key in sealed:
        if info is None or key not in info:
            continue
        if key not in meta or _json_value(meta[key]) != _json_value(info[key]):
            raise error(
                f"{ckpt_path.parent / meta_name}: '{key}' "
                f"{'is missing' if key not in meta else 'differs from the checkpoint'} "
                f"(checkpoint {_json_value(info[key])!r}); the metadata was edited — re-run the "
                "training stage that wrote the model"
            )
