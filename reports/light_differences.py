"""The difference images and metrics of one lighting condition, as a folder and read back.

Every model against the reference model and every low geometry against the high mesh, under
one light (:func:`dermis.reports.diff.write_differences`): ``diff-*.png`` and
``geomdiff-*.png``, the light's ``metrics.json`` and thumbnails of its difference images
(``thumbnails.json`` indexes them) for the report's grids and PDF.  The ``differences`` stage
writes one such folder per lighting condition; the ``report`` stage merges them
(:func:`merge_light_differences`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from dermis.reports import diff
from dermis.reports.sheets import save_png, thumbnail

__all__ = ["METRICS", "thumbnail_name", "write_light_differences", "load_light_differences",
           "merge_light_differences"]

METRICS = "metrics.json"


def thumbnail_name(kind: str, key: tuple) -> str:
    return f"thumb-{kind}-{'-'.join(key)}.png"


def write_light_differences(images: dict, out_dir: Path, *, reference_model: str) -> list[Path]:
    """Difference images, ``metrics.json`` and thumbnails of ``images`` (node id ->
    RenderedImage, one lighting condition) against ``reference_model``, into ``out_dir``.

    Returns the files written for export (every one but ``metrics.json`` and the thumbnails).
    """
    tiles: dict = {}
    files, metrics = diff.write_differences(images, out_dir, reference_model=reference_model,
                                            tiles_out=tiles, grids=False)
    index = {}
    for kind, got in tiles.items():
        for key, tile in got.items():
            name = thumbnail_name(kind, key)
            save_png(out_dir / name, thumbnail(tile))
            index.setdefault(kind, []).append(list(key))
    (out_dir / "thumbnails.json").write_text(json.dumps(index, sort_keys=True))
    return [Path(f) for f in files if Path(f).name != METRICS]


def load_light_differences(folder: Path) -> tuple[dict, dict]:
    """(metrics, thumbnails {"model": {(m, l, g): uint8 image}, "geometry": {...}}) of one
    differences node's folder."""
    folder = Path(folder)
    metrics = json.loads((folder / METRICS).read_text())
    tiles: dict = {}
    for kind, keys in json.loads((folder / "thumbnails.json").read_text()).items():
        for key in keys:
            with Image.open(folder / thumbnail_name(kind, tuple(key))) as im:
                tiles.setdefault(kind, {})[tuple(key)] = np.asarray(im.convert("RGB"))
    return metrics, tiles


def merge_light_differences(folders: list, out_dir: Path, tiles: dict) -> tuple[list, dict]:
    """The report's grids and merged ``metrics.json`` from the folders of every lighting
    condition; their thumbnails are added to ``tiles`` ({"model": {...}, "geometry": {...}}).

    Returns (the files written, the merged metrics).
    """
    parts = [load_light_differences(folder) for folder in folders]
    metrics = diff.merge_metrics([m for m, _ in parts])
    for _, got in parts:
        for kind, d in got.items():
            tiles.setdefault(kind, {}).update(d)
    files = diff.write_grids(metrics, tiles, out_dir)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    files.append(out_dir / "metrics.json")
    return files, metrics
