"""The stereo part of the report: SGM depth accuracy by range, the learned stereo network beside
SGM, the SGM variants, stereo-pair fault detection per rule, and the camera-resolution study
(tables: :mod:`traffictwin.stereo.report_tables`, :mod:`traffictwin.stereo.report_learned`).
Entry point: :func:`provider`.
"""

from __future__ import annotations

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import NEVER
from traffictwin.stereo.report_learned import (
    STEREO_FILE,
    VARIANTS_FILE,
    learned_tables,
    variant_tables,
)
from traffictwin.stereo.report_tables import (
    DISPARITY_FILE,
    ORB_FILE,
    RESOLUTION_FILE,
    disparity_tables,
    fault_tables,
    prose,
    resolution_tables,
)

TITLE = "Stereo — SGM and the learned stereo network's range accuracy, stereo-pair fault detection"
#: the figures the section shows, in order; their captions are macros of the same name
FIGURE_STEMS = ("stereo_learned_example", "stereo_resolution")
#: the stage that writes each metrics file the section reads
STAGES = {
    DISPARITY_FILE: "disparity",
    STEREO_FILE: "stereo_learned",
    VARIANTS_FILE: "sgm_variants",
    ORB_FILE: "orb_filter",
}


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The stereo section: disparity and range accuracy, the learned network, the SGM variants,
    fault detection, the resolution study; a pointer to the acceptance table where stereo.json
    has targets."""
    sec = page.Section(TITLE, paragraphs=[prose("intro")], figures=figures)
    if (targets := src.get(STEREO_FILE, "targets")) and isinstance(targets, dict):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
    builds = (disparity_tables, learned_tables, variant_tables, fault_tables)
    res = resolution_tables(src)
    sec.tables = [t for build in builds for t in build(src)] + res
    sec.paragraphs += [
        prose("missing", file=f, stage=stage) for f, stage in STAGES.items() if not src.has(f)
    ]
    if not res:
        sec.paragraphs.append(prose("resolution_missing", file=RESOLUTION_FILE))
    return sec


def provider() -> page.SectionProvider:
    """The stereo section's provider for the report (after the risk section)."""
    return page.SectionProvider(
        name="stereo",  # its page, reports/pages/stereo.md (no headline numbers)
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        figure_pattern=NEVER,
        shown_files=r"stereo_resolution\.json|stereo\.json|sgm_variants\.json",
    )
