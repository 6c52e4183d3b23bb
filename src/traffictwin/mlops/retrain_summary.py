"""The Markdown page of a scheduled retraining's summary (``reports/retrain_summary.md``).

The summary itself is a plain dict that ``pipelines/retrain.py`` fills on every exit path
(``status``, seeds, data versions before and after, the gate's decisions, champions, and on a
failure the error and whether the checkout was restored); this renders it for a person.
"""

from __future__ import annotations

from typing import Any


def _fig(v: float | None) -> str:
    return "–" if v is None else f"{v:.5g}"


def _decision_rows(decisions: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| model | challenger | champion before | metric | challenger | champion | decision |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for d in decisions:
        champ = f"v{d['champion_version']}" if d["champion_version"] else "–"
        lines.append(
            f"| {d['name']} | v{d['challenger_version']} | {champ} | {d['metric']} "
            f"| {_fig(d['challenger_value'])} | {_fig(d['champion_value'])} | {d['action']} |"
        )
    return lines


def summary_markdown(s: dict[str, Any]) -> str:
    """``s`` (a retraining summary) as a Markdown page."""
    commit = str(s.get("git_commit"))[:10]
    lines = [
        f"# Retraining {s['status']}: {s['started']}",
        "",
        f"- duration: {s.get('duration_s', 0):.0f} s; profile `{s.get('profile')}`; git `{commit}`",
    ]
    if s.get("recovered"):
        lines.append(f"- recovered first from a killed run: {s['recovered']}")
    if s.get("signal"):
        lines.append(f"- signal: {s['signal']}")
    lines += [f"- data seed `{k}`: {a} → {b}" for k, (a, b) in (s.get("seeds") or {}).items()]
    if s.get("overrides"):
        lines.append(f"- params.yaml = conf/ composed with `{' '.join(s['overrides'])}`")
    if s.get("error"):
        lines += [
            f"- **error** in step `{s.get('failed_step')}`: {s['error']}",
            f"- restored: {s.get('restored')} {s.get('restore_problems') or ''}; "
            f"champions: {s.get('champions_after')}",
        ]
    after, before = s.get("data_after") or {}, s.get("data_before") or {}
    changed = [p for p, h in after.items() if before.get(p) != h]
    if s["status"] == "succeeded":
        lines.append(
            f"- new data version: {len(changed)} of {len(after)} data outputs changed "
            f"({', '.join(changed) or 'none'})"
        )
    if s.get("decisions"):
        lines += ["", *_decision_rows(s["decisions"]), ""]
        lines.append(f"Champions after: {s.get('champions_after')}")
    return "\n".join(lines) + "\n"
