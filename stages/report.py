"""Stage ``report``: difference images against the BSSRDF (and low vs high geometry), metrics,
and the multi-page PDF (:mod:`dermis.reports.diff`, :mod:`dermis.reports.pdf_report`).

The differences themselves are the ``differences`` nodes' (one per lighting condition,
:mod:`dermis.reports.light_differences`); this node merges their metrics, draws the grids
from their thumbnails and writes the PDF, so a changed light recomputes one light's
comparisons, not all of them."""
from __future__ import annotations

from pathlib import Path

from dermis.pipeline.config import CameraConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.reports import diff, pdf_report
from dermis.reports.comparison_images import load_thumbnails
from dermis.reports.ground_truth import ground_truth_section
from dermis.reports.light_differences import merge_light_differences
from dermis.reports.profile_pages import profile_pages

NAME = "report"
VERSION = 3
KERNELS = ()
REFERENCE_MODEL = "bssrdf"
GROUND_TRUTH_MESH = "mesh_high"   # the references are of the high mesh; regions are on it


def node(scene, render_ids: list[str], irradiance_ids: list[str],
         difference_ids: list[str] = (), images_id: str | None = None,
         reference_ids: list[str] = (), reference_skipped: str | None = None) -> Node:
    """The report of the renders; with ``reference_ids`` (Mitsuba ground truth) also the
    distance-to-ground-truth section, which needs the high mesh (regions) and the camera.
    ``reference_skipped`` is the reason the scene asked for references and got none."""
    params = {"renders": sorted(render_ids), "irradiance": sorted(irradiance_ids),
              "differences": sorted(difference_ids), "images": images_id,
              "references": sorted(reference_ids), "reference_skipped": reference_skipped,
              "scene_name": scene.scene.name, "credits": list(scene.credits())}
    deps = (tuple(render_ids) + tuple(irradiance_ids) + tuple(sorted(difference_ids))
            + ((images_id,) if images_id else ()) + tuple(sorted(reference_ids)))
    if reference_ids:
        from dataclasses import asdict
        params["camera"] = asdict(scene.camera)
        deps += (GROUND_TRUTH_MESH,)
    # the layer profiles every BSSRDF model reads: the profile page (reports/profile_pages.py)
    from dermis.pipeline.config import BSSRDF_MODELS, profile_model, profiles_node_id
    params["profiles"] = sorted({profiles_node_id(scene, profile_model(scene, m))
                                 for m in scene.render.models if m in BSSRDF_MODELS})
    deps += tuple(params["profiles"])
    return Node(NAME, NAME, __name__, params, deps, label="grids + PDF")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    images = {nid: inputs[nid] for nid in params["renders"]}
    tiles: dict = {}   # difference images, computed once for the PNGs and the PDF
    if params.get("differences"):
        files, metrics = merge_light_differences([inputs[nid] for nid in params["differences"]],
                                                 ctx.out_dir, tiles)
    else:   # no differences nodes: compute them here
        files, metrics = diff.write_differences(images, ctx.out_dir,
                                                reference_model=REFERENCE_MODEL, tiles_out=tiles)
    extra = {}
    for nid in params["irradiance"]:  # irradiance-<mesh node>-<lighting label>
        _, mesh_node, label = nid.split("-", 2)
        extra[(label, mesh_node)] = float(inputs[nid].info.get("seconds", 0.0))
    thumbs = None
    if params.get("images"):   # the images stage's tone-mapped thumbnails for the image pages
        thumbs, _ = load_thumbnails(inputs[params["images"]])
    refs = {inputs[nid].info["light"]: inputs[nid] for nid in params.get("references", ())}
    gt_pages, gt_info = ground_truth_section(
        images, refs, ctx.out_dir, files, mesh=inputs[GROUND_TRUTH_MESH] if refs else None,
        camera=CameraConfig(**params["camera"]) if refs else None, extra_seconds=extra,
        skip_reason=params.get("reference_skipped"))
    profiles = {nid: inputs[nid] for nid in params.get("profiles", ())}
    added = {"profiles": 0}

    def extra_pages(pdf):   # the profile page, then the ground-truth section
        added["profiles"] = profile_pages(pdf, profiles)
        gt_pages(pdf)
    pdf = pdf_report.write_report(images, metrics, ctx.out_dir / "report.pdf",
                                  scene_name=params["scene_name"], device=ctx.cl.description,
                                  timings_extra=extra, credits=params["credits"], tiles=tiles,
                                  image_tiles=thumbs, extra_pages=extra_pages)
    names = [Path(f).name for f in files] + [pdf.name]
    pages = (pdf_report.report_page_count(images, metrics) + added["profiles"]
             + gt_info["pages"])
    return StageResult(files=names, info={"pages": pages, "ground_truth": gt_info})
