"""The rendered report as its files: the index (``reports/README.md``, ``reports/index.html``) and
the pages it lists (``reports/pages/<name>.md`` / ``.html``), in the index's order; and a checker
of every relative link, image source and style sheet of every page (target file present, anchor
present on the target page, each HTML page linking the report's one style sheet)."""

from __future__ import annotations

import re
from collections import Counter
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

from traffictwin.report import render as R

MD_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)\)")


def page_files(reports: Path, html: bool = False) -> list[Path]:
    """The index, then every page its list links (``pages/<name>.md`` or ``.html``), in order."""
    index = reports / (R.INDEX_HTML if html else R.README)
    text = index.read_text()
    ext = "html" if html else "md"
    pat = (
        rf'<li><a href="({R.PAGES}/[\w-]+\.{ext})">'
        if html
        else rf"^- \[[^\]]+\]\(({R.PAGES}/[\w-]+\.{ext})\)$"
    )
    names = re.findall(pat, text, flags=re.M)
    return [index, *(reports / n for n in dict.fromkeys(names))]


def all_md(reports: Path) -> str:
    """Every Markdown file of the report, the index first, joined in reading order."""
    return "\n".join(p.read_text() for p in page_files(reports))


def all_html(reports: Path) -> str:
    """Every HTML file of the report, the index first, joined in reading order."""
    return "\n".join(p.read_text() for p in page_files(reports, html=True))


def page_md(reports: Path, name: str) -> str:
    """``reports/pages/<name>.md``."""
    return (reports / R.PAGES / f"{name}.md").read_text()


def page_html(reports: Path, name: str) -> str:
    """``reports/pages/<name>.html``."""
    return (reports / R.PAGES / f"{name}.html").read_text()


class _Refs(HTMLParser):
    """``href`` / ``src`` values, ``id`` attributes, the ``<link rel="stylesheet">`` targets and
    the inline ``<style>`` elements of an HTML page."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.refs: list[str] = []
        self.ids: set[str] = set()
        self.sheets: list[str] = []
        self.inline_styles = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self.refs += [v for k, v in a.items() if k in ("href", "src") and v]
        if a.get("id"):
            self.ids.add(str(a["id"]))
        if tag == "link" and a.get("rel") == "stylesheet":
            self.sheets.append(a.get("href") or "")
        self.inline_styles += tag == "style"


def stylesheet_problems(page: Path, reports: Path) -> list[str]:
    """``"<page>: ... (why)"`` unless the HTML page links exactly one style sheet, the report's
    ``reports/style.css`` (by a path relative to the page), and inlines none."""
    p = _Refs()
    p.feed(page.read_text())
    name = page.relative_to(reports)
    want = (reports / R.STYLE).resolve()
    bad = []
    if p.inline_styles:
        bad.append(f"{name}: an inline <style> (the style sheet is {R.STYLE})")
    if len(p.sheets) != 1:
        bad.append(f"{name}: {len(p.sheets)} style sheet links (want one, to {R.STYLE})")
    bad += [
        f"{name}: {h} (style sheet is not reports/{R.STYLE})"
        for h in p.sheets
        if (page.parent / unquote(h)).resolve() != want
    ]
    return bad


def md_anchors(text: str) -> set[str]:
    """The anchors GitHub gives a Markdown page: one per heading (its slug; a repeated slug gets
    ``-1``, ``-2``, ...), plus any HTML ``id``."""
    out: set[str] = set()
    seen: Counter[str] = Counter()
    for head in re.findall(r"^#{1,6} (.+)$", text, flags=re.M):
        slug = R._slug(head)
        out.add(slug if not seen[slug] else f"{slug}-{seen[slug]}")
        seen[slug] += 1
    out.update(re.findall(r'id="([^"]+)"', text))
    return out


def _anchors(path: Path) -> set[str]:
    text = path.read_text()
    if path.suffix == ".html":
        p = _Refs()
        p.feed(text)
        return p.ids
    return md_anchors(text)


def refs(path: Path) -> list[str]:
    """Every link and image source of a Markdown or HTML page, as written."""
    text = path.read_text()
    if path.suffix == ".html":
        p = _Refs()
        p.feed(text)
        return p.refs
    return MD_LINK.findall(text)


def broken_links(reports: Path) -> list[str]:
    """``"<page>: <ref> (why)"`` for every relative link, image source or style sheet of every
    page of the report (Markdown and HTML) whose target file is missing, or whose ``#anchor`` is
    not on the target page, and for every HTML page that does not link the report's one style
    sheet (:func:`stylesheet_problems`); external links (``http(s):``, ``mailto:``) and
    ``data:`` images are skipped."""
    bad = []
    pages = [*page_files(reports), *page_files(reports, html=True)]
    for page in pages:
        if not page.is_file():  # a listed page that is missing: named by the index's link to it
            continue
        if page.suffix == ".html":
            bad += stylesheet_problems(page, reports)
        for ref in refs(page):
            if re.match(r"^(?:[a-z]+:)", ref):
                continue
            path, _, anchor = ref.partition("#")
            target = (page.parent / unquote(path)).resolve() if path else page
            if not target.is_file():
                bad.append(f"{page.relative_to(reports)}: {ref} (no file {target})")
            elif anchor and anchor not in _anchors(target):
                bad.append(f"{page.relative_to(reports)}: {ref} (no anchor #{anchor})")
    return bad
