"""Stage ``report``: every model's distance to the path-traced reference, difference images
against the BSSRDF (and low vs high geometry), metrics, and the multi-page PDF
(:mod:`dermis.reports.ground_truth`, :mod:`dermis.reports.diff`,
:mod:`dermis.reports.pdf_report`).

The differences themselves are the ``differences`` nodes' (one per lighting condition,
:mod:`dermis.reports.light_differences`); this node merges their metrics, draws the grids
from their thumbnails and writes the PDF, so a changed light recomputes one light's
comparisons, not all of them.  With references the PDF leads with the distance to them
(title page and the pages after it) and ``metrics.json`` gains ``ground_truth`` (per
lighting condition) and ``thesis`` (docs/ground-truth.md "In metrics.json"); without,
``ground_truth`` is empty and ``ground_truth_skipped`` says why, as the title page does.
Beside the PDF, ``report.html``: every image of the run to compare pixel by pixel, with the
same numbers (:mod:`dermis.reports.interactive_page`, docs/report-page.md)."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from dermis.pipeline.config import CameraConfig, condition_of
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.registry import stage
from dermis.reports import diff, pdf_report
from dermis.reports.adaptive_pages import adaptive_pages
from dermis.reports.comparison_images import load_thumbnails
from dermis.reports.ground_truth import RegionLabeller, ground_truth_section
from dermis.reports.interactive_page import write_page
from dermis.reports.light_differences import merge_light_differences
from dermis.reports.profile_pages import profile_pages
from dermis.reports.requirement_pages import requirement_pages
from dermis.reports.requirements import auto_verdicts, requirements_of

NAME = "report"
VERSION = 6   # 6: the adaptive BSSRDF pages
KERNELS = ()
GROUND_TRUTH_MESH = "mesh_high"   # the references are of the high mesh; regions are on it


def node(scene, render_ids: list[str], irradiance: dict[str, tuple[str, str]],
         difference_ids: list[str] = (), images_id: str | None = None,
         reference_ids: list[str] = (), reference_skipped: str | None = None,
         profile_ids: list[str] = (), cause_ids: list[str] = ()) -> Node:
    """The report of the renders.  ``irradiance``: the BSSRDF's irradiance passes, id ->
    (lighting label, mesh node), whose seconds the timing table adds; ``profile_ids``: the
    layer profiles the BSSRDF models read (the profile page).  With ``reference_ids``
    (Mitsuba ground truth) also the distance-to-ground-truth section, which needs the high
    mesh (regions) and the camera; ``reference_skipped`` is the reason the scene asked for
    references and got none; ``cause_ids`` the reference's controlled variants (the causes
    table)."""
    params = {"renders": sorted(render_ids),
              "irradiance": {nid: list(irradiance[nid]) for nid in sorted(irradiance)},
              "differences": sorted(difference_ids), "images": images_id,
              "references": sorted(reference_ids), "reference_skipped": reference_skipped,
              "profiles": sorted(profile_ids), "causes": sorted(cause_ids),
              "scene_name": scene.scene.name, "credits": list(scene.credits())}
    deps = (tuple(render_ids) + tuple(params["irradiance"]) + tuple(params["differences"])
            + ((images_id,) if images_id else ()) + tuple(params["references"]))
    if reference_ids:
        params["camera"] = asdict(scene.camera)
    if any("high" in scene.geometries_of(label) for label, _ in scene.light_groups()):
        # what the scene requires: regions of every view's pixels, on the high mesh
        params["requires"] = {**asdict(scene.report), "cameras": {
            label: asdict(scene.camera_of(label)) for label, _ in scene.light_groups()},
            "chosen": dict(scene.chosen)}
    if reference_ids or "requires" in params:
        deps += (GROUND_TRUTH_MESH,)
    deps += tuple(params["profiles"]) + tuple(params["causes"])
    return Node(NAME, NAME, __name__, params, deps, label="grids + PDF")


def plan(scene, plan) -> None:
    """When the differences are drawn: the baseline and another model are rendered."""
    differences = stage("differences")
    if not differences.compared(scene):
        return
    images = plan.of_stage("images")
    plan.add(node(
        scene, [n.id for n in plan.provided("image")],
        {n.id: (n.params["label"], n.deps["mesh"]) for n in plan.of_stage("irradiance")},
        [n.id for n in plan.of_stage("differences")], images[0].id if images else None,
        [n.id for n in plan.of_stage("reference")], plan.skipped.get("reference"),
        [n.id for n in plan.of_stage("profiles")], [n.id for n in plan.of_stage("causes")]),
        target=True)


def run(params: dict, inputs: dict, ctx) -> StageResult:
    images = {nid: inputs[nid] for nid in params["renders"]}
    tiles: dict = {}   # difference images, computed once for the PNGs and the PDF
    if params.get("differences"):
        files, metrics = merge_light_differences([inputs[nid] for nid in params["differences"]],
                                                 ctx.out_dir, tiles)
    else:   # no differences nodes: compute them here
        files, metrics = diff.write_differences(images, ctx.out_dir,
                                                reference_model=stage("differences").BASELINE,
                                                tiles_out=tiles)
    extra = {}
    for nid, (label, mesh_node) in params["irradiance"].items():
        extra[(label, mesh_node)] = float(inputs[nid].info.get("seconds", 0.0))
    for im in images.values():   # a close-up's BSSRDF reads its condition's pass
        for mesh_node in {m for _, m in params["irradiance"].values()}:
            if (condition_of(im.info["light"]), mesh_node) in extra:
                extra[(im.info["light"], mesh_node)] = extra[(condition_of(im.info["light"]),
                                                              mesh_node)]
    thumbs = None
    if params.get("images"):   # the images stage's tone-mapped thumbnails for the image pages
        thumbs, _ = load_thumbnails(inputs[params["images"]])
    refs = {inputs[nid].info["light"]: inputs[nid] for nid in params.get("references", ())}
    # the high mesh's face regions under every camera, each cast once for all pages
    mesh = inputs.get(GROUND_TRUTH_MESH)
    regions = RegionLabeller(mesh) if mesh is not None else None
    opening, details, gt_info = ground_truth_section(
        images, refs, ctx.out_dir, files, mesh=regions if refs else None,
        camera=CameraConfig(**params["camera"]) if refs else None, extra_seconds=extra,
        skip_reason=params.get("reference_skipped"), differences=metrics,
        tiles=tiles.get("model"),
        variants={inputs[nid].info["light"]: inputs[nid] for nid in params.get("causes", ())})
    metrics["ground_truth"] = gt_info["metrics"]
    if refs:
        metrics["thesis"] = gt_info["thesis"]
        if gt_info.get("causes"):
            metrics["causes"] = gt_info["causes"]
    else:
        metrics["ground_truth_skipped"] = gt_info["title"]["note"]
    req = params.get("requires")
    if req:
        metrics["views"] = {view: {"requires": rec} for view, rec in requirements_of(
            images, regions, req, metrics.get("ground_truth"), extra).items()}
        for view, rec in auto_verdicts({v: r["requires"] for v, r in metrics["views"].items()},
                                       req["chosen"], req["accuracy"]).items():
            metrics["views"].setdefault(view, {})["auto"] = rec
    mpath = ctx.out_dir / "metrics.json"
    mpath.write_text(json.dumps(metrics, indent=1, sort_keys=True, default=float))
    if mpath.name not in {Path(f).name for f in files}:
        files.append(mpath)
    profiles = {nid: inputs[nid] for nid in params.get("profiles", ())}
    added = {"profiles": 0, "requires": 0, "adaptive": 0}

    def extra_pages(pdf):   # what the scene requires, the profile page, the truth's details
        if metrics.get("views"):
            added["requires"] = requirement_pages(pdf, metrics["views"],
                                                  accuracy=req["accuracy"],
                                                  threshold=req["effect_threshold"])
        added["profiles"] = profile_pages(pdf, profiles)
        added["adaptive"] = adaptive_pages(pdf, images)
        details(pdf)
    pdf = pdf_report.write_report(images, metrics, ctx.out_dir / "report.pdf",
                                  scene_name=params["scene_name"], device=ctx.cl.description,
                                  timings_extra=extra, credits=params["credits"], tiles=tiles,
                                  image_tiles=thumbs, extra_pages=extra_pages, opening_pages=opening,
                                  truth=gt_info["title"])
    cameras = (params.get("requires") or {}).get("cameras") or {
        light: params["camera"] for light in refs}   # lighting label -> its view's camera
    page = write_page(ctx.out_dir, images, refs, metrics, scene_name=params["scene_name"],
                      device=ctx.cl.description, timings_extra=extra,
                      mesh=regions,
                      cameras={k: CameraConfig(**v) for k, v in cameras.items()})
    names = [Path(f).name for f in files] + [pdf.name, page.name]
    pages = (pdf_report.report_page_count(images, metrics) + added["profiles"] + added["requires"]
             + added["adaptive"] + gt_info["pages"])
    summary = {k: gt_info[k] for k in ("references", "pages", "ranking", "thesis") if k in gt_info}
    return StageResult(files=names, info={"pages": pages, "ground_truth": summary})
