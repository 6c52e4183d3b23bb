"""Prose templates: a problem's findings sentences in Jinja templates its package owns
(``traffictwin/<problem>/templates/``), filled from a typed record of numbers, verdicts and
flags. Markdown, not HTML (no escaping); a missing field is an error. Long sentences are wrapped
in the template source and joined again by the ``oneline`` filter.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any


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


def macro_prose(folder: Path, name: str) -> Callable[..., str]:
    """``prose(macro, **context)``: macro ``macro`` of template ``name`` in ``folder`` filled with
    ``context``, on one line (each section's prose helper)."""

    def prose(macro: str, **context: Any) -> str:
        return oneline(template_macro(folder, name, macro)(**context))

    return prose
