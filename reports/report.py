"""Stage ``report``: difference images against the BSSRDF (and low vs high geometry), metrics,
and the multi-page PDF (:mod:`dermis.reports.diff`, :mod:`dermis.reports.pdf_report`)."""
from __future__ import annotations

from pathlib import Path

from dermis.pipeline.graph import Node, StageResult

NAME = "report"
VERSION = 2
KERNELS = ()
REFERENCE_MODEL = "bssrdf"


def node(scene, render_ids: list[str], irradiance_ids: list[str]) -> Node:
    params = {"renders": sorted(render_ids), "irradiance": sorted(irradiance_ids),
              "scene_name": scene.scene.name, "credits": list(scene.credits())}
    return Node(NAME, NAME, __name__, params, tuple(render_ids) + tuple(irradiance_ids),
                label="differences + PDF")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    from dermis.reports import diff, pdf_report
    images = {nid: inputs[nid] for nid in params["renders"]}
    tiles: dict = {}   # difference images, computed once for the PNGs and the PDF
    files, metrics = diff.write_differences(images, ctx.out_dir, reference_model=REFERENCE_MODEL,
                                            tiles_out=tiles)
    extra = {}
    for nid in params["irradiance"]:  # irradiance-<mesh node>-<lighting label>
        _, mesh_node, label = nid.split("-", 2)
        extra[(label, mesh_node)] = float(inputs[nid].info.get("seconds", 0.0))
    pdf = pdf_report.write_report(images, metrics, ctx.out_dir / "report.pdf",
                                  scene_name=params["scene_name"], device=ctx.cl.description,
                                  timings_extra=extra, credits=params["credits"], tiles=tiles)
    names = [Path(f).name for f in files] + [pdf.name]
    return StageResult(files=names, info={"pages": pdf_report.report_page_count(images, metrics)})
