"""Stage ``differences``: the difference images and metrics of one lighting condition.

Every model against the BSSRDF and every low geometry against the high mesh, under one
light (:func:`dermis.reports.diff.write_differences`): ``diff-*.png`` and ``geomdiff-*.png``
(exported into the report folder), the light's ``metrics.json`` and thumbnails of its
difference images for the report's grids and PDF.  One node per lighting condition, so a
changed light redraws only its own comparisons; the ``report`` node merges them.
"""
from __future__ import annotations

import json
from pathlib import Path

from dermis.pipeline.graph import Node, StageResult

NAME = "differences"
VERSION = 1
KERNELS = ()
OUTPUT_FOLDER = "report"      # the difference PNGs go beside the report
REFERENCE_MODEL = "bssrdf"
METRICS = "metrics.json"


def node(scene, label: str, render_ids: list[str]) -> Node:
    ids = sorted(render_ids)
    return Node(f"differences-{label}", NAME, __name__, {"label": label, "renders": ids},
                tuple(ids), label=f"differences / {label}")


def thumbnail_name(kind: str, key: tuple) -> str:
    return f"thumb-{kind}-{'-'.join(key)}.png"


def run(params: dict, inputs: dict, ctx) -> StageResult:
    from dermis.reports import diff
    from dermis.reports.sheets import save_png, thumbnail

    images = {nid: inputs[nid] for nid in params["renders"]}
    tiles: dict = {}
    files, metrics = diff.write_differences(images, ctx.out_dir, reference_model=REFERENCE_MODEL,
                                            tiles_out=tiles, grids=False)
    index = {}
    for kind, got in tiles.items():
        for key, tile in got.items():
            name = thumbnail_name(kind, key)
            save_png(ctx.out_dir / name, thumbnail(tile))
            index.setdefault(kind, []).append(list(key))
    (ctx.out_dir / "thumbnails.json").write_text(json.dumps(index, sort_keys=True))
    return StageResult(files=[Path(f).name for f in files if Path(f).name != METRICS])


def load(folder: Path) -> tuple[dict, dict]:
    """(metrics, thumbnails {"model": {(m, l, g): uint8 image}, "geometry": {...}}) of one
    differences node's folder."""
    import numpy as np
    from PIL import Image

    folder = Path(folder)
    metrics = json.loads((folder / METRICS).read_text())
    tiles: dict = {}
    for kind, keys in json.loads((folder / "thumbnails.json").read_text()).items():
        for key in keys:
            with Image.open(folder / thumbnail_name(kind, tuple(key))) as im:
                tiles.setdefault(kind, {})[tuple(key)] = np.asarray(im.convert("RGB"))
    return metrics, tiles
