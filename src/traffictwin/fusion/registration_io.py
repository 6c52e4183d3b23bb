"""Reading a trained learned registration back (:func:`load_registration_model`): torch only, no
Lightning, so that the stages that evaluate it (and the CLI) do not import the trainer.
:mod:`traffictwin.fusion.registration_training` writes what this reads."""

from __future__ import annotations

from pathlib import Path

from traffictwin.fusion.learned_registration import LearnedRegistration, RegistrationNetSpec
from traffictwin.fusion.model_io import SEALED_META, FusionModelError
from traffictwin.grid import GridSpec
from traffictwin.model_format import (
    check_model_pair,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
)

#: the ``problem`` of a learned registration's checkpoint
PROBLEM = "registration"


def load_registration_model(
    path: str | Path, *, expected_grid: GridSpec | None = None, expected_cfg: str | None = None
) -> LearnedRegistration:
    """A trained :class:`LearnedRegistration` (eval mode) from ``model.ckpt`` (file or folder);
    ``model.meta`` holds its meta. Errors name the file and the mismatch."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.ckpt"
    if not path.exists():
        raise FusionModelError(
            f"{path}: learned registration checkpoint not found (run `dvc repro train_registration` first)"
        )
    ck = read_model_checkpoint(path, PROBLEM, FusionModelError)
    info = ck["traffictwin"]
    meta = read_model_meta(path.parent / "model_meta.json", FusionModelError)
    check_model_pair(path, meta, FusionModelError, info, (*SEALED_META, "method", "min_gain"))
    g = GridSpec(**info["grid"])
    if expected_grid is not None and (g.rows, g.cols, g.cell) != (
        expected_grid.rows,
        expected_grid.cols,
        expected_grid.cell,
    ):
        raise FusionModelError(
            f"{path}: trained on grid {info['grid']}, expected {expected_grid.rows}x{expected_grid.cols} cells of {expected_grid.cell} m"
        )
    if expected_cfg is not None and info.get("cfg") != expected_cfg:
        raise FusionModelError(
            f"{path}: trained for configuration '{info.get('cfg')}', expected '{expected_cfg}'"
        )
    try:
        net = LearnedRegistration(
            RegistrationNetSpec.from_dict(info["architecture"]), g, float(info.get("min_gain", 0.0))
        )
        net.load_state_dict(net_state_dict(ck), strict=True)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise FusionModelError(
            f"{path}: weights do not fit the learned registration architecture ({str(exc)[:300]})"
        ) from None
    net.meta = dict(info)  # type: ignore[attr-defined]
    return net.eval()
