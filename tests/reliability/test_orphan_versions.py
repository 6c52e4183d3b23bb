"""A retraining interrupted during promotion restores its files but left a
registered version with no alias and no gate tags, whose files belong to rolled-back data. The
restore now retires every version registered after the snapshot of the registry."""

from __future__ import annotations

import logging

import pytest
from _registry_models import log_linear

from pipelines import _checkout as ck
from traffictwin.mlops import registry as reg

NAME = "traffictwin-orphans"

pytestmark = pytest.mark.integration


def test_versions_after_the_snapshot_are_deleted_or_tagged(cl):
    reg.ensure_version(cl, NAME, log_linear(1.0))
    cl.set_registered_model_alias(NAME, "champion", "1")
    before = reg.latest_versions(cl, [NAME, "traffictwin-never-registered"])
    assert before == {NAME: 1, "traffictwin-never-registered": 0}
    reg.ensure_version(cl, NAME, log_linear(2.0))  # v2: registered, then the run was interrupted
    reg.ensure_version(cl, NAME, log_linear(3.0))  # v3: an alias already points at it
    cl.set_registered_model_alias(NAME, "challenger", "3")
    reg.ensure_version(cl, "traffictwin-never-registered", log_linear(4.0))
    done = ck.retire_orphans(cl, before, logging.getLogger("test"))
    assert f"{NAME} v2 deleted" in done
    assert any(d.startswith(f"{NAME} v3 tagged orphan") for d in done), done
    left = {int(mv.version) for mv in cl.search_model_versions(f"name='{NAME}'")}
    assert left == {1, 3}
    assert reg.ORPHAN_TAG in cl.get_model_version(NAME, "3").tags
    assert reg.ORPHAN_TAG not in cl.get_model_version(NAME, "1").tags
    assert str(cl.get_model_version_by_alias(NAME, "champion").version) == "1"  # the champion kept
    # a model the interrupted run registered first is removed entirely
    assert "traffictwin-never-registered" not in reg.registered_names(cl)
    assert ck.retire_orphans(cl, reg.latest_versions(cl, [NAME]), logging.getLogger("t")) == []
