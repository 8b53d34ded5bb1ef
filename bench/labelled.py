"""Benchmark results kept side by side: one JSON file, one entry per run label."""
from __future__ import annotations

import json
from pathlib import Path


def read_labelled(path) -> dict:
    """The file's entries by label ({} if it does not exist yet)."""
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else {}


def save_labelled(path, label: str, result: dict) -> None:
    """Store ``result`` under ``label`` in the JSON file at ``path``, keeping other labels."""
    path = Path(path)
    entries = read_labelled(path)
    entries[label] = result
    path.write_text(json.dumps(entries, indent=1))
