"""Stage `report` (last in the DAG): the index reports/README.md and reports/index.html, one page per
section under reports/pages/ (.md and .html), their style sheet reports/style.css,
reports/results_table.md.

Hands :func:`traffictwin.report.render.write_report` what the report shows about the run, read
from params.yaml -- the profile, the seed, the pose-noise configurations, the *scale* parameters
(every key some profile in conf/profile/ overrides, plus every seed) and the acceptance
thresholds -- and the section providers, one per problem in report order. The commit,
experiment and pipeline run differ between identical reruns: they go to the stage's run record.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from traffictwin.acceptance import for_problem
from traffictwin.config import flatten, typed
from traffictwin.fusion import report_section as fusion_report
from traffictwin.mlops.tracking import pipeline_run_id
from traffictwin.report.config import ReportParams
from traffictwin.report.model import ReportInputs, SectionProvider
from traffictwin.report.render import write_report
from traffictwin.risk import report_section as risk_report
from traffictwin.stereo import report_section as stereo_report
from traffictwin.twin import report_section as twin_report

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import CONF, REPORTS, ROOT
from ._provenance import git_commit


def profile_keys(conf_profile_dir: Path) -> set[str]:
    """Dotted keys that any profile (conf/profile/*.yaml, ``@package _global_``) sets, except ``defaults``."""
    keys: set[str] = set()
    for p in sorted(conf_profile_dir.glob("*.yaml")):
        data = yaml.safe_load(p.read_text()) or {}
        keys.update(flatten({k: v for k, v in data.items() if k != "defaults"}))
    return keys


def run_params(cfg: Any, keys: set[str]) -> dict[str, Any]:
    """Values of ``keys`` in params (a key that is a dict in params is expanded) plus every ``*seed*`` key."""
    return {
        k: v
        for k, v in flatten(cfg).items()
        if k != "profile.name"
        and (k in keys or any(k.startswith(p + ".") for p in keys) or "seed" in k.rsplit(".")[-1])
    }


def git_dirty(root: Path) -> bool:
    """True if src/, pipelines/, conf/ or dvc.yaml differ from HEAD (dvc.lock, params.yaml and reports/ are
    rewritten by the pipeline itself and do not count). False outside a git checkout."""
    import subprocess

    try:
        proc = subprocess.run(
            ["git", "diff", "--quiet", "HEAD", "--", "src", "pipelines", "conf", "dvc.yaml"],
            cwd=root,
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return proc.returncode == 1


def providers(configurations: Mapping[str, tuple[float, float]]) -> list[SectionProvider]:
    """The problems' sections, in report order; ``configurations``: ``{name: (r m, alpha deg)}``."""
    return [
        fusion_report.provider(configurations),
        risk_report.provider(),
        stereo_report.provider(),
        twin_report.provider(),
    ]


def main() -> None:
    setup_logging()
    with stage_timer("report") as record:
        cfg = params()
        p = typed({k: cfg.get(k) for k in ("seed", "profile", "configurations")}, ReportParams)
        inputs = ReportInputs(
            reports_dir=REPORTS,
            profile=p.profile.name,
            banner=p.profile.banner,
            seed=p.seed,
            git_commit=git_commit(ROOT),
            run_params=run_params(cfg, profile_keys(CONF / "profile")),
            acceptance={pr: for_problem(cfg, pr) for pr in ("fusion", "risk", "stereo", "twin")},
        )
        report = write_report(inputs, providers(p.pose_noise))
        record.update(  # what differs between identical reruns: the run record, not the report
            git_commit=inputs.git_commit,
            git_dirty=git_dirty(ROOT),
            dvc_exp_name=os.environ.get("DVC_EXP_NAME") or None,
            pipeline_run=pipeline_run_id(),
        )
    log = setup_logging()
    log.info(
        "report: %d sections, %d missing values -> reports/README.md, reports/index.html, reports/pages/",
        len(report.sections),
        len(report.missing),
    )


if __name__ == "__main__":
    run_stage(main, "report")
