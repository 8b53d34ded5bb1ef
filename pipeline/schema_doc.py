"""The scene-format reference (README.md's table between its ``scene-format`` markers;
tests/test_config.py keeps them equal), generated from the schema's own field docs in
:mod:`dermis.pipeline.config`."""
from __future__ import annotations

from dataclasses import MISSING, fields

from .schema import SCHEMA_TABLES, choices_of
from .scene_rules import fmt

__all__ = ["schema_markdown"]


def _fmt_default(f) -> str:
    if f.default_factory is not MISSING or f.default is MISSING:
        return ""
    v = f.default
    if isinstance(v, tuple) and all(isinstance(x, str) for x in v):
        return "[" + ", ".join(v) + "]" if v else "[]"
    if isinstance(v, float) and v.is_integer() and abs(v) >= 1e4:
        return f"{int(v):,}"
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 1e4:
        return f"{v:,}"
    return fmt(v).replace("True", "true").replace("False", "false")


def _fmt_rule(meta) -> str:
    if choices_of(meta):
        return "one of " + ", ".join(str(c) for c in choices_of(meta))
    parts = []
    if meta.get("lo") is not None:
        parts.append((">" if meta.get("lo_open") else ">=") + f" {meta['lo']}")
    if meta.get("hi") is not None:
        parts.append(("<" if meta.get("hi_open") else "<=") + f" {meta['hi']}")
    return ", ".join(parts)


def schema_markdown() -> str:
    """The scene-format reference, generated from the schema's own field docs (README.md holds
    this text between its ``scene-format`` markers; tests/test_config.py keeps them equal)."""
    lines = ["| key | default | allowed | what |", "|---|---|---|---|"]
    for table, cls in SCHEMA_TABLES:
        for f in fields(cls):
            if f.metadata.get("internal"):
                continue
            unit = " (length)" if f.metadata.get("unit") == "length" else ""
            doc = f.metadata.get("doc", "").replace("|", "/")
            lines.append(f"| `[{table}] {f.name}` | {_fmt_default(f)} | {_fmt_rule(f.metadata)}"
                         f"{unit} | {doc} |")
    return "\n".join(lines)
