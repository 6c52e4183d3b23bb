"""Prose templates: the sentences of a problem's findings, kept in Jinja templates that the
problem's package owns (``traffictwin/<problem>/templates/``), filled from a typed record the
problem computes from its metrics (numbers, verdicts, flags; no sentences).

The page kit knows no problem: it only loads a folder of templates with the settings findings
need. Markdown, not HTML (no escaping); a missing field is an error (``StrictUndefined``).
Long sentences are wrapped in the template source and joined again by the ``oneline`` filter
(a line break and the indentation around it become one space; before a line that starts with
``.``, ``,`` or ``;`` nothing), so a bullet is one line of Markdown however its template is laid out.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path
from typing import Any

__all__ = ["oneline", "template_environment", "render_prose", "template_macro"]


def oneline(text: str) -> str:
    """``text`` without its surrounding blank space, each line break (with the blank space around
    it) replaced by one space, or by nothing where the next line starts with ``.``, ``,`` or ``;``
    (a list's last item ends its line; the full stop after it follows on the next)."""
    text = re.sub(r"\s*\n\s*(?=[.,;])", "", str(text).strip())
    return re.sub(r"[ \t]*\n\s*", " ", text)


def template_environment(folder: str | Path, *, autoescape: bool = False) -> Any:
    """The project's Jinja2 settings over the templates of ``folder``: block tags take no line of
    their own, a trailing newline is kept, a missing field is an error; HTML escaping on request."""
    import jinja2

    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(folder)),
        autoescape=autoescape,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
        undefined=jinja2.StrictUndefined,
    )


@cache
def _environment(folder: str) -> Any:
    env = template_environment(folder)
    env.filters["oneline"] = oneline
    return env


def render_prose(folder: Path, name: str, **context: Any) -> str:
    """Template ``name`` of ``folder`` rendered with ``context``."""
    return str(_environment(str(folder)).get_template(name).render(**context))


def template_macro(folder: Path, name: str, macro: str) -> Any:
    """Macro ``macro`` of template ``name`` in ``folder``, callable from Python (returns text)."""
    return getattr(_environment(str(folder)).get_template(name).module, macro)
