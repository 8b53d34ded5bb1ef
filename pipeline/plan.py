"""From a scene to the stage graph: which nodes the requested outputs need, and how each runs.

The graph is built from the request, so a stage no output needs is never part
of it: the low mesh and its bakes exist only when a ``low*`` geometry is asked
for, layer profiles only for the BSSRDF model, and so on.  Each node's
``params`` is exactly the slice of the scene its stage reads.

Adapters here do the file IO (reading the scan, writing previews into the node's
output directory) so that the stage functions themselves stay pure.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from .config import Scene, _resolve
from .graph import Node, StageResult
from .store import file_digest

__all__ = ["build_graph", "STAGE_NAMES"]

# Every stage name, in pipeline order (for --until / --force / clean validation).
STAGE_NAMES = ("mesh_source", "mesh_high", "mesh_low", "bake", "mesh_previews", "profiles",
               "samples", "irradiance", "render", "images", "report")

GEOMETRY_MESH = {"high": "mesh_high", "low": "mesh_low", "low_bump": "mesh_low",
                 "low_bump_blur": "mesh_low"}
GEOMETRY_BUMP = {"high": None, "low": None, "low_bump": "sharp", "low_bump_blur": "blur"}


# --------------------------------------------------------------------------- adapters
def _mesh_source(scene: Scene) -> Node:
    m = scene.mesh
    if m.source == "procedural":
        params = {"triangles": m.high_triangles, "detail": m.procedural_detail,
                  "texture_size": m.procedural_texture_size, "seed": m.seed}

        def fn(inputs, ctx):
            from dermis.stages import procedural_head
            mesh = procedural_head.run(**params)
            return StageResult(mesh, info={"triangles": mesh.n_triangles})

        return Node("mesh_source", "mesh_source", "dermis.stages.procedural_head", params, (), fn,
                    "procedural head")

    path = scene.mesh_path()
    texture = _resolved(scene, m.texture)
    params = {"file": str(path), "file_sha256": file_digest(path), "units": m.units,
              "texture": str(texture) if texture else "",
              "texture_sha256": file_digest(texture) if texture else ""}

    def fn(inputs, ctx):
        from dermis.stages import mesh_prep
        mesh = mesh_prep.load_scan(path, units=m.units, texture=texture)
        mesh, repairs = mesh_prep.validate(mesh, source=str(path))
        return StageResult(mesh, info={"repairs": repairs, "triangles": mesh.n_triangles})

    return Node("mesh_source", "mesh_source", "dermis.stages.mesh_prep", params, (), fn, "load scan")


def _resolved(scene: Scene, value: str) -> Path | None:
    """A scene path value resolved against the scene file's folder (None if empty)."""
    return _resolve(value, scene.path) if value else None


def _mesh_high(scene: Scene) -> Node:
    m = scene.mesh
    disp = _resolved(scene, m.displacement)
    params = {"target_triangles": m.high_triangles,
              "displacement": str(disp) if disp else "",
              "displacement_sha256": file_digest(disp) if disp else "",
              "displacement_scale_mm": m.displacement_scale_mm,
              "displacement_mid": m.displacement_mid}

    def fn(inputs, ctx):
        from dermis.stages import mesh_prep
        from .imageio import read_image
        image = read_image(disp, channels=1, what="mesh.displacement")[..., 0] if disp else None
        high = mesh_prep.make_high(inputs["mesh_source"], target_triangles=m.high_triangles,
                                   displacement=image,
                                   displacement_scale_mm=m.displacement_scale_mm,
                                   displacement_mid=m.displacement_mid)
        high.normals = mesh_prep.vertex_normals(high.vertices, high.faces)
        return StageResult(high, info={"triangles": high.n_triangles})

    return Node("mesh_high", "mesh_high", "dermis.stages.mesh_prep", params, ("mesh_source",), fn,
                "high mesh + normals")


def _mesh_low(scene: Scene) -> Node:
    params = {"target_triangles": scene.mesh.low_triangles}

    def fn(inputs, ctx):
        from dermis.stages import mesh_prep
        high = inputs["mesh_high"]
        low = mesh_prep.simplify(high, target_triangles=scene.mesh.low_triangles)
        low.normals = mesh_prep.vertex_normals(low.vertices, low.faces)
        low, report = mesh_prep.transfer_uv(high, low)
        return StageResult(low, info={"uv_transfer": report, "triangles": low.n_triangles})

    return Node("mesh_low", "mesh_low", "dermis.stages.mesh_prep", params, ("mesh_high",), fn,
                "simplify + UV transfer")


def _bake(scene: Scene) -> Node:
    b = scene.bake
    params = asdict(b)

    def fn(inputs, ctx):
        from dermis.stages import bake
        maps = bake.run(inputs["mesh_low"], inputs["mesh_high"], resolution=b.resolution,
                        max_distance_mm=b.max_distance or None, blur_sigma_px=b.blur_sigma_px,
                        dilate_px=b.dilate_px, reference=b.reference, progress=ctx.progress)
        return StageResult(maps, info=maps.info)

    return Node("bake", "bake", "dermis.stages.bake", params, ("mesh_low", "mesh_high"), fn,
                "bake albedo + bump")


def _mesh_previews(scene: Scene, low: bool) -> Node:
    params = {"size": 800, "low": low}
    deps = ("mesh_high", "mesh_low", "bake") if low else ("mesh_high",)

    def fn(inputs, ctx):
        from dermis.reports import mesh_previews
        files = []
        if low:
            files += mesh_previews.save_map_previews(inputs["bake"], ctx.out_dir)
            out = ctx.out_dir / "shaded_high_vs_low.png"
            mesh_previews.save_shaded_comparison(inputs["mesh_high"], inputs["mesh_low"],
                                                 inputs["bake"], out, size=800)
            files.append(out)
        else:
            out = ctx.out_dir / "shaded_high.png"
            mesh_previews.save_shaded_comparison(inputs["mesh_high"], None, None, out, size=800)
            files.append(out)
        return StageResult(files=[Path(f).name for f in files])

    return Node("mesh_previews", "mesh_previews", "dermis.reports.mesh_previews", params, deps, fn,
                "PNG previews")


def _profiles(scene: Scene) -> Node:
    params = {"stack": scene.optics.to_dict()}

    def fn(inputs, ctx):
        from dermis.stages import profiles
        prof = profiles.run(scene.optics)
        return StageResult(prof, info={"Rd": list(map(float, prof.Rd)),
                                       "Tt": list(map(float, prof.Tt))})

    return Node("profiles", "profiles", "dermis.stages.profiles", params, (), fn, "layer profiles")


def _visibility(ctx, mesh_node: str, mesh):
    """One Embree scene per mesh per run, shared by every image of that mesh."""
    from dermis.physics.visibility import Visibility
    key = ("visibility", mesh_node)
    if key not in ctx.memo:
        ctx.memo[key] = Visibility(mesh.vertices, mesh.faces)
    return ctx.memo[key]


def _model_params(scene: Scene, model: str):
    """The parameter objects of a BRDF model, all derived from the scene's one layer stack."""
    from dermis.stages.brdf_models import AsperityParams, HK93Params, LafortuneParams
    hk = lambda: HK93Params(layers=scene.optics)  # noqa: E731 - HK93 shares the BSSRDF's layers
    if model == "lafortune":
        return LafortuneParams(), None
    if model == "hk93":
        return hk(), None
    base = scene.render.asperity_base
    base_params = {"lafortune": LafortuneParams, "hk93": hk}.get(base, lambda: None)()
    return AsperityParams(base=base), base_params


def _render(scene: Scene, model: str, label: str, lights: tuple, geometry: str) -> Node:
    mesh_node, bump = GEOMETRY_MESH[geometry], GEOMETRY_BUMP[geometry]
    deps = (mesh_node,) + (("bake",) if bump else ())
    uses_optics = model == "hk93" or (model == "asperity" and scene.render.asperity_base == "hk93")
    params = {"model": model, "lights": [asdict(l) for l in lights], "camera": asdict(scene.camera),
              "bump": bump, "seed": scene.mesh.seed,
              "asperity_base": scene.render.asperity_base if model == "asperity" else None,
              "optics": scene.optics.to_dict() if uses_optics else None}
    for light in lights:
        if light.type == "environment" and light.map != "procedural_sunset":
            params[f"map_sha256_{light.name}"] = file_digest(Path(light.map))
    node_id = f"render-{model}-{label}-{geometry}"

    def fn(inputs, ctx):
        from dermis.stages import render
        from .artifacts import RenderedImage
        from .imageio import write_exr
        mesh = inputs[mesh_node]
        p, base_params = _model_params(scene, model)
        result = render.render(mesh, list(lights), model, p, scene.camera, maps=inputs.get("bake"),
                               bump=bump, seed=scene.mesh.seed,
                               visibility=_visibility(ctx, mesh_node, mesh),
                               asperity_base=scene.render.asperity_base if model == "asperity"
                               else None, base_params=base_params, cl_env=ctx.cl,
                               progress=ctx.progress)
        name = f"{model}-{label}-{geometry}"
        write_exr(ctx.out_dir / f"{name}.exr", result.linear)
        image = RenderedImage(result.linear, result.mask, dict(result.timings),
                              {**result.info, "model": model, "light": label,
                               "geometry": geometry})
        return StageResult(image, files=[f"{name}.exr"],
                           info={"timings": result.timings,
                                 "kernel_seconds": result.timings.get("kernel_seconds", 0.0)})

    return Node(node_id, "render", "dermis.stages.render", params, deps, fn,
                f"{model} / {label} / {geometry}")


def _samples(scene: Scene, mesh_node: str) -> Node:
    """Uniform irradiance points on one mesh: cached per mesh, not per light."""
    from dermis.stages.samples import spacing_from_mfp
    spacing = spacing_from_mfp(scene.optics, scene.bssrdf.point_density)
    params = {"spacing_mm": spacing, "seed": scene.mesh.seed}

    def fn(inputs, ctx):
        from dermis.stages import samples
        from .artifacts import SurfacePoints
        mesh = inputs[mesh_node]
        pts = samples.run(mesh.vertices, mesh.faces, spacing_mm=spacing, seed=scene.mesh.seed,
                          vertex_normals=mesh.normals)
        return StageResult(SurfacePoints(pts.positions, pts.normals, pts.areas, pts.info),
                           info={"points": int(len(pts.positions)), "spacing_mm": spacing})

    return Node(f"samples-{mesh_node}", "samples", "dermis.stages.samples", params, (mesh_node,), fn,
                "irradiance points")


def _irradiance(scene: Scene, mesh_node: str, label: str, lights: tuple) -> Node:
    """Irradiance at the sample points from one lighting condition (thesis: 64 shadow samples)."""
    samples_id = f"samples-{mesh_node}"
    params = {"lights": [asdict(l) for l in lights], "samples": scene.bssrdf.irradiance_samples,
              "seed": scene.mesh.seed}
    for light in lights:
        if light.type == "environment" and light.map != "procedural_sunset":
            params[f"map_sha256_{light.name}"] = file_digest(Path(light.map))

    def fn(inputs, ctx):
        import time
        from .artifacts import PointIrradiance
        from dermis.physics.lights import irradiance
        pts, mesh = inputs[samples_id], inputs[mesh_node]
        t0 = time.perf_counter()
        vis = _visibility(ctx, mesh_node, mesh)
        E = irradiance(pts.positions, pts.normals, list(lights), vis.occluded,
                       samples=scene.bssrdf.irradiance_samples, seed=scene.mesh.seed)
        info = {"seconds": time.perf_counter() - t0, "points": int(len(E)),
                "samples": scene.bssrdf.irradiance_samples}
        return StageResult(PointIrradiance(E, info), info=info)

    return Node(f"irradiance-{mesh_node}-{label}", "irradiance", "dermis.physics.lights", params,
                (samples_id, mesh_node), fn, f"irradiance {label}")


def _render_bssrdf(scene: Scene, label: str, lights: tuple, geometry: str) -> Node:
    """Jensen-Buhler pass 2 at every pixel: hierarchical gather, Fresnel exit, surface term."""
    mesh_node, bump = GEOMETRY_MESH[geometry], GEOMETRY_BUMP[geometry]
    samples_id, irr_id = f"samples-{mesh_node}", f"irradiance-{mesh_node}-{label}"
    deps = (mesh_node, samples_id, irr_id, "profiles") + (("bake",) if bump else ())
    b = scene.bssrdf
    params = {"camera": asdict(scene.camera), "bump": bump, "bssrdf": asdict(b),
              "lights": [asdict(l) for l in lights], "seed": scene.mesh.seed}
    node_id = f"render-bssrdf-{label}-{geometry}"

    def fn(inputs, ctx):
        import time
        import numpy as np
        from dermis.stages import gather, render
        from .artifacts import RenderedImage
        from .imageio import write_exr
        t_start = time.perf_counter()
        mesh, maps, profile = inputs[mesh_node], inputs.get("bake"), inputs["profiles"]
        vis = _visibility(ctx, mesh_node, mesh)
        px = render.pixel_surface(mesh, scene.camera, maps=maps, bump=bump, visibility=vis,
                                  cl_env=ctx.cl)
        t_vis = time.perf_counter() - t_start
        key = ("octree", irr_id)
        t0 = time.perf_counter()
        if key not in ctx.memo:  # one octree per (points, lighting), shared by geometries
            pts = inputs[samples_id]
            ctx.memo[key] = gather.build_octree(
                pts.positions, pts.areas, inputs[irr_id].irradiance, leaf_size=b.leaf_size,
                kernel_sigma_mm=pts.info.get("kernel_sigma_mm"))  # the areas' partition of unity
        t_tree = time.perf_counter() - t0
        front = px.front_idx
        surf = px.surf
        t0 = time.perf_counter()
        M, stats = gather.gather(ctx.memo[key], profile, surf["position"][front],
                                 epsilon=b.epsilon, normalisation=b.normalisation, env=ctx.cl,
                                 brute_force=b.brute_force, progress=ctx.progress)
        t_gather = time.perf_counter() - t0
        cos_o = np.einsum("ij,ij->i", surf["shading_normal"][front], surf["wo"][front])
        eta = scene.optics.layers[0].eta / scene.optics.eta_above
        albedo = None if b.albedo_mode == "none" else surf["albedo"][front]
        L = gather.exitance_to_radiance(M, cos_o, eta, albedo=albedo,
                                        albedo_mode="replace" if albedo is None else b.albedo_mode,
                                        rd=profile.Rd)
        image = np.zeros((px.height * px.width, 3), np.float32)
        image[px.hit_idx[front]] = L
        timings = {"visibility": t_vis, "octree": t_tree, "gather": t_gather,
                   "kernel_seconds": float(stats.get("kernel_seconds", 0.0)) + px.kernel_seconds}
        if b.surface_reflection == "lafortune_lobes":
            from dermis.stages.brdf_models import LafortuneParams
            spec = render.render(mesh, list(lights), "lafortune",
                                 LafortuneParams(rho_d=(0.0, 0.0, 0.0)), scene.camera,
                                 maps=maps, bump=bump, seed=scene.mesh.seed, visibility=vis,
                                 cl_env=ctx.cl, textured=False)
            image += spec.linear.reshape(-1, 3)
            timings["surface_reflection"] = spec.timings["total"]
            timings["kernel_seconds"] += spec.timings.get("kernel_seconds", 0.0)
        image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
        timings["total"] = time.perf_counter() - t_start
        linear = image.reshape(px.height, px.width, 3)
        mask = px.hits.hit.reshape(px.height, px.width)
        name = f"bssrdf-{label}-{geometry}"
        write_exr(ctx.out_dir / f"{name}.exr", linear)
        info = {"model": "bssrdf", "light": label, "geometry": geometry,
                "gather": {k: v for k, v in stats.items() if isinstance(v, (int, float, str))}}
        return StageResult(RenderedImage(linear, mask, timings, info), files=[f"{name}.exr"],
                           info={"timings": timings, "kernel_seconds": timings["kernel_seconds"]})

    return Node(node_id, "render", "dermis.stages.gather", params, deps, fn,
                f"bssrdf / {label} / {geometry}")


def _images(scene: Scene, render_ids: list[str]) -> Node:
    """Tone-map every rendered image with ONE shared exposure; write PNGs and a contact sheet."""
    params = {"renders": sorted(render_ids)}

    def fn(inputs, ctx):
        from dermis.reports import comparison
        files = comparison.write_pngs({nid: inputs[nid] for nid in render_ids}, ctx.out_dir)
        return StageResult(files=[f.name for f in files])

    return Node("images", "images", "dermis.reports.comparison", params, tuple(render_ids), fn,
                "tone-mapped PNGs")


def _report(scene: Scene, render_ids: list[str], irradiance_ids: list[str]) -> Node:
    """Difference images against the BSSRDF, metrics, and the multi-page PDF report."""
    params = {"renders": sorted(render_ids), "irradiance": sorted(irradiance_ids),
              "scene_name": scene.scene.name}

    def fn(inputs, ctx):
        from dermis.reports import diff, pdf_report
        images = {nid: inputs[nid] for nid in render_ids}
        files, metrics = diff.write_differences(images, ctx.out_dir, reference_model="bssrdf")
        extra = {}
        for nid in irradiance_ids:  # irradiance-<mesh node>-<lighting label>
            _, mesh_node, label = nid.split("-", 2)
            extra[(label, mesh_node)] = float(inputs[nid].info.get("seconds", 0.0))
        pdf = pdf_report.write_report(images, metrics, ctx.out_dir / "report.pdf",
                                      scene_name=scene.scene.name, device=ctx.cl.description,
                                      timings_extra=extra)
        names = [Path(f).name for f in files] + [pdf.name]
        return StageResult(files=names, info={"pages": pdf_report.report_page_count(images,
                                                                                    metrics)})

    return Node("report", "report", "dermis.reports.pdf_report", params,
                tuple(render_ids) + tuple(irradiance_ids), fn, "differences + PDF")


# --------------------------------------------------------------------------- graph
def build_graph(scene: Scene) -> tuple[dict[str, Node], list[str]]:
    """Nodes needed by the scene's requested outputs, and the target node ids.

    Returns
    -------
    nodes : dict node id -> Node
    targets : the node ids whose artifacts are the run's outputs
    """
    geoms = set(scene.render.geometries)
    needs_low = bool(geoms & {"low", "low_bump", "low_bump_blur"})
    needs_bake = bool(geoms & {"low_bump", "low_bump_blur"})
    models = set(scene.render.models)
    needs_profiles = "bssrdf" in models or (
        "asperity" in models and scene.render.asperity_base == "bssrdf")

    nodes: dict[str, Node] = {}
    targets: list[str] = []

    def add(node: Node, target: bool = False):
        nodes[node.id] = node
        if target:
            targets.append(node.id)

    add(_mesh_source(scene))
    add(_mesh_high(scene), target=not needs_low)
    if needs_low:
        add(_mesh_low(scene), target=not needs_bake)
    if needs_bake:
        add(_bake(scene), target=True)
    if scene.output.previews:
        add(_mesh_previews(scene, needs_bake), target=True)
    if needs_profiles:
        add(_profiles(scene), target=True)
    render_ids = []
    for model in scene.render.models:
        for label, lights in scene.light_groups():
            for geometry in scene.render.geometries:
                if model == "bssrdf":
                    mesh_node = GEOMETRY_MESH[geometry]
                    add(_samples(scene, mesh_node))
                    add(_irradiance(scene, mesh_node, label, lights))
                    node = _render_bssrdf(scene, label, lights, geometry)
                else:
                    node = _render(scene, model, label, lights, geometry)
                add(node)
                render_ids.append(node.id)
    if render_ids:
        add(_images(scene, render_ids), target=True)
    if "bssrdf" in models and len(models) > 1:  # differences need the reference and another
        irradiance_ids = [n for n in nodes if n.startswith("irradiance-")]
        add(_report(scene, render_ids, irradiance_ids), target=True)
    return nodes, targets
