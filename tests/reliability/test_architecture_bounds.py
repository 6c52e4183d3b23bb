"""Architecture values read from model meta are bounded before any layer is built.

Before: a resealed fusion model folder whose ``backbone.base_width`` is 4096 printed a 41-line
allocator traceback (or was OOM-killed): ``DeepLabV3Plus`` built a stage-4 conv of 32768 x 32768
x 3 x 3 weights. The loads run in a subprocess under a 3 GB address-space limit, so an unbounded
allocation fails there instead of taking the machine.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _cli_models import tiny_spec

from traffictwin.fusion.deeplab import DeepLabSpec
from traffictwin.fusion.learned_registration import RegistrationNetSpec
from traffictwin.fusion.resnet import ResNetSpec
from traffictwin.io.limits import MAX_MODEL_PARAMETERS
from traffictwin.risk.dave2 import Dave2Config

ROOT = Path(__file__).resolve().parents[2]

_LOAD = textwrap.dedent(
    """
    import json, resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
    kind, folder = sys.argv[1], sys.argv[2]
    if kind == "fusion":
        from traffictwin.fusion.model_io import FusionModelError as E, load_fusion_model as load
    else:
        from traffictwin.risk.model_io import RiskModelError as E, load_risk_model as load
    try:
        load(folder)
    except E as exc:
        print(json.dumps({"refused": str(exc)}))
    """
)


def _load_limited(kind: str, folder: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", _LOAD, kind, str(folder)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert proc.returncode == 0 and proc.stdout, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def _resealed_fusion(folder: Path, arch: dict) -> Path:
    from traffictwin.model_format import MODEL_FORMAT, save_model_files

    info = {
        "format": MODEL_FORMAT,
        "problem": "fusion",
        "cfg": "D",
        "architecture": arch,
        "grid": {"rows": 32, "cols": 32, "cell": 0.5},
        "data_manifest_hash": "test",
    }
    folder.mkdir(parents=True)
    save_model_files(
        folder / "model.ckpt",
        {"state_dict": {}, "traffictwin": info},
        folder / "model_meta.json",
        info,
    )
    return folder


def test_a_resealed_fusion_model_with_a_huge_width_is_one_line(tmp_path) -> None:
    arch = tiny_spec().as_dict()
    arch["backbone"]["base_width"] = 4096
    got = _load_limited("fusion", _resealed_fusion(tmp_path / "m", arch))["refused"]
    assert "\n" not in got and "invalid architecture block" in got, got
    assert "resnet.base_width is 4096, more than its bound 256" in got, got


def test_a_resealed_risk_model_with_a_huge_input_is_one_line(tmp_path) -> None:
    from _cli_models import save_risk

    folder = save_risk(tmp_path / "risk")
    ck = folder / "model.ckpt"
    import torch

    from traffictwin.model_format import save_model_files

    blob = torch.load(ck, weights_only=True)
    meta = json.loads((folder / "model_meta.json").read_text())
    for d in (blob["traffictwin"]["architecture"], meta.get("config", {})):
        d["height"], d["width"] = 2000, 4000  # within the side bound, ~25 G weights in FC 1
    meta.pop("ckpt_sha256", None)
    save_model_files(ck, blob, folder / "model_meta.json", meta)
    got = _load_limited("risk", folder)["refused"]
    assert "\n" not in got and "invalid model config" in got, got
    assert f"more than the bound {MAX_MODEL_PARAMETERS:,}" in got, got


@pytest.mark.parametrize(
    ("build", "named"),
    [
        (lambda: ResNetSpec(base_width=4096), "resnet.base_width is 4096, more than its bound 256"),
        (lambda: ResNetSpec(layers=(2, 2, 1000, 2)), "resnet.layers[2] is 1000"),
        (lambda: DeepLabSpec(aspp_channels=100_000), "deeplab.aspp_channels is 100000"),
        (lambda: DeepLabSpec(aspp_rates=(6, 12, 100_000)), "deeplab.aspp_rates is 100000"),
        (
            lambda: DeepLabSpec(
                backbone=ResNetSpec(block="bottleneck", layers=(64, 64, 64, 64), base_width=256)
            ),
            "weights, more than the bound",
        ),
        (lambda: Dave2Config(width=100_000), "Dave2Config.width is 100000"),
        (lambda: Dave2Config(fc=(10**7, 10)), "Dave2Config.fc[0] is 10000000"),
        (lambda: Dave2Config(conv=((24, 5, 2), (10**6, 5, 2))), "conv[1] channels is 1000000"),
        (lambda: RegistrationNetSpec(coarse_width=10**6), "coarse_width is 1000000"),
        (lambda: RegistrationNetSpec(rot_step_deg=1e-6), "(candidate angles)"),
    ],
)
def test_architecture_values_name_field_value_and_bound(build, named) -> None:
    with pytest.raises(ValueError) as info:
        build()
    assert named in str(info.value), info.value


def test_the_paper_architectures_are_within_the_bounds() -> None:
    resnet50 = DeepLabSpec(
        backbone=ResNetSpec(block="bottleneck", layers=(3, 4, 6, 3), base_width=64),
        aspp_channels=256,
        decoder_channels=256,
    )
    assert 35e6 < resnet50.parameter_estimate() < 45e6  # the paper's ~40 M
    assert Dave2Config(height=160, width=320).parameter_estimate() < MAX_MODEL_PARAMETERS
    RegistrationNetSpec()
