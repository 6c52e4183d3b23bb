"""traffictwin.io.yamlio.safe_load: the documents and errors of ``yaml.safe_load``."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from traffictwin.io import yamlio

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["dvc.lock", "dvc.yaml", "params.yaml"])
def test_the_projects_files_read_as_safe_load_reads_them(name: str) -> None:
    text = (ROOT / name).read_text()
    assert yamlio.safe_load(text) == yaml.safe_load(text)


def test_yaml_1_1_scalars_and_safe_constructors() -> None:
    text = "a: yes\nb: 1e-07\nc: 1.0e-07\nd: 0o17\ne: ~\nf: 2026-11-30\ng: [1, '2']\n"
    assert yamlio.safe_load(text) == yaml.safe_load(text)
    assert yamlio.safe_load(b"x: 1\n") == {"x": 1}
    with pytest.raises(yaml.YAMLError):
        yamlio.safe_load("a: [1, 2\n")
    with pytest.raises(yaml.YAMLError):  # no arbitrary Python objects
        yamlio.safe_load("!!python/object/apply:os.system ['true']\n")
