"""Stage ``report``: difference images against the BSSRDF (and low vs high geometry), metrics,
and the multi-page PDF (:mod:`dermis.reports.diff`, :mod:`dermis.reports.pdf_report`).

The differences themselves are the ``differences`` nodes' (one per lighting condition,
:mod:`dermis.reports.differences`); this node merges their metrics, draws the grids from
their thumbnails and writes the PDF, so a changed light recomputes one light's
comparisons, not all of them."""
from __future__ import annotations

import json
from pathlib import Path

from dermis.pipeline.graph import Node, StageResult

NAME = "report"
VERSION = 3
KERNELS = ()
REFERENCE_MODEL = "bssrdf"


def node(scene, render_ids: list[str], irradiance_ids: list[str],
         difference_ids: list[str] = (), images_id: str | None = None) -> Node:
    params = {"renders": sorted(render_ids), "irradiance": sorted(irradiance_ids),
              "differences": sorted(difference_ids), "images": images_id,
              "scene_name": scene.scene.name, "credits": list(scene.credits())}
    return Node(NAME, NAME, __name__, params,
                tuple(render_ids) + tuple(irradiance_ids) + tuple(sorted(difference_ids))
                + ((images_id,) if images_id else ()), label="grids + PDF")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    from dermis.reports import diff, pdf_report
    images = {nid: inputs[nid] for nid in params["renders"]}
    tiles: dict = {}   # difference images, computed once for the PNGs and the PDF
    if params.get("differences"):
        from dermis.reports import differences
        parts = [differences.load(inputs[nid]) for nid in params["differences"]]
        metrics = diff.merge_metrics([m for m, _ in parts])
        for _, got in parts:
            for kind, d in got.items():
                tiles.setdefault(kind, {}).update(d)
        files = diff.write_grids(metrics, tiles, ctx.out_dir)
        (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
        files.append(ctx.out_dir / "metrics.json")
    else:   # no differences nodes: compute them here
        files, metrics = diff.write_differences(images, ctx.out_dir,
                                                reference_model=REFERENCE_MODEL, tiles_out=tiles)
    extra = {}
    for nid in params["irradiance"]:  # irradiance-<mesh node>-<lighting label>
        _, mesh_node, label = nid.split("-", 2)
        extra[(label, mesh_node)] = float(inputs[nid].info.get("seconds", 0.0))
    thumbs = None
    if params.get("images"):   # the images stage's tone-mapped thumbnails for the image pages
        from dermis.reports.images import load_thumbnails
        thumbs, _ = load_thumbnails(inputs[params["images"]])
    pdf = pdf_report.write_report(images, metrics, ctx.out_dir / "report.pdf",
                                  scene_name=params["scene_name"], device=ctx.cl.description,
                                  timings_extra=extra, credits=params["credits"], tiles=tiles,
                                  image_tiles=thumbs)
    names = [Path(f).name for f in files] + [pdf.name]
    return StageResult(files=names, info={"pages": pdf_report.report_page_count(images, metrics)})
