"""The reference's controlled variants and the causes table.

Mitsuba tests ask for the ``mi`` fixture, which skips with one message without the
``reference`` extra (as tests/test_reference.py).  Sizes are small (the file stays around a
minute on 2 cores); the default scene's numbers are bench/bench_causes.py's.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.artifacts import Mesh, RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig, load_scene
from dermis.geometry.regions import REGION_LABELS, REGIONS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_fixtures import icosphere, merge  # noqa: E402
from scene_toml import scene_file  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "scenes" / "quick.toml"
POINT = LightConfig(name="point", type="point", position=(350.0, 450.0, 600.0),
                    intensity=(4e5, 4e5, 4e5))
AREA = LightConfig(name="area", type="disc", position=(350.0, 450.0, 600.0),
                   direction=(-0.35, -0.45, -0.6), radius=70.0, intensity=(4e5, 4e5, 4e5))


@pytest.fixture(scope="module")
def quick_mesh(tmp_path_factory):
    from dermis.pipeline import artifacts
    from dermis.pipeline.api import run
    summary = run(load_scene(QUICK), cache=tmp_path_factory.mktemp("cache"), until="mesh_high",
                  export=False)
    return artifacts.load(next(n for n in summary.nodes if n.id == "mesh_high").path)


def _camera(width, fov=17.0, position=(0.0, -15.0, 1000.0), look_at=(0.0, -15.0, 0.0)):
    return CameraConfig(position=position, look_at=look_at, up=(0.0, 1.0, 0.0), fov_deg=fov,
                        width=width, height=width)


def _floor(y: float, size: float) -> Mesh:
    """A square at height y facing +y (a floor under a shape)."""
    s = size / 2.0
    v = np.array([[-s, y, -s], [s, y, -s], [s, y, s], [-s, y, s]], np.float64)
    f = np.array([[0, 3, 2], [0, 2, 1]], np.int32)      # counter-clockwise seen from +y
    return Mesh(vertices=v, faces=f, normals=np.tile(np.float32([0, 1, 0]), (4, 1)))


def _box(half: float, depth: float, grey: int) -> Mesh:
    """A closed box (top face z = 0) of separate faces (flat normals), UVs, uniform texture."""
    x0, x1, y0, y1, z0, z1 = -half, half, -half, half, -depth, 0.0
    quads = [[(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
             [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)],
             [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
             [(x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)],
             [(x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)],
             [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)]]
    centre = np.array([0.0, 0.0, -depth / 2])
    verts, faces, normals = [], [], []
    for q in quads:
        q = np.array(q, np.float64)
        n = np.cross(q[1] - q[0], q[2] - q[0])
        if n @ (q.mean(axis=0) - centre) < 0:      # counter-clockwise seen from outside
            q, n = q[::-1], -n
        k = len(verts) * 4
        verts.append(q)
        normals.append(np.tile(n / np.linalg.norm(n), (4, 1)))
        faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    uv = np.tile(np.float32([[0, 0], [1, 0], [1, 1], [0, 1]]), (6, 1))
    f = np.array(faces, np.int32)
    return Mesh(vertices=np.concatenate(verts), faces=f,
                normals=np.concatenate(normals).astype(np.float32), uv=uv, uv_faces=f.copy(),
                texture_srgb=np.full((8, 8, 3), grey, np.uint8))


# ------------------------------------------------------------------------ interreflection
def test01_interreflection_gain_nonnegative_on_the_head_zero_on_a_sphere(mi, quick_mesh):
    """The diffuse head gains light from interreflection in every region (>= 0 within 3
    standard errors, > 0 resolved over the face); a convex sphere gains none (0 within 3
    standard errors) while the same sphere over a lit floor gains, resolved: the check sees
    interreflection where there is some."""
    from dermis.groundtruth.variants import VariantOptions, interreflection_variant
    opts = VariantOptions(width=40, height=40, diffuse_spp=16)
    head = interreflection_variant(mi, quick_mesh, _camera(40), [AREA], opts)["regions"]
    for name, r in head.items():
        if r.get("se_lum") is not None:
            assert r["effect_lum"] >= -3 * r["se_lum"], (name, r)
    assert head["face"]["effect_lum"] > 3 * head["face"]["se_lum"] > 0, head["face"]

    sphere = icosphere(radius=100.0, subdivisions=4)
    cam = _camera(32, fov=14.0, position=(0.0, 0.0, 1000.0), look_at=(0.0, 0.0, 0.0))
    alone = interreflection_variant(mi, sphere, cam, [POINT], opts)
    assert set(alone["regions"]) == set(REGIONS) | {"face"}
    measured = 0
    for name, r in alone["regions"].items():
        if r.get("se_lum") is None:
            continue
        measured += 1
        assert abs(r["effect_lum"]) <= 3 * r["se_lum"] + 1e-5, (name, r)
    assert measured >= 3
    # the indirect light of a convex shape is nothing at all, pixel by pixel
    assert np.abs(alone["all"].mean - alone["direct"].mean).max() <= 1e-6 * alone[
        "direct"].mean.max()

    on_floor = interreflection_variant(mi, merge(sphere, _floor(-101.0, 800.0)), cam,
                                       [POINT], opts)["regions"]["face"]
    assert on_floor["effect_lum"] > max(3 * on_floor["se_lum"], 0.01), on_floor


# ------------------------------------------------------------------------ flat slab
def test02_smooth_slab_agrees_with_monte_carlo_and_the_rough_one_is_darker(mi):
    """A 1 mm Skin1 slab (groundtruth/slab.py, by reciprocity: a radiance meter under a
    uniform sky): with the smooth boundary of the boundary variant it reads dermis's Monte
    Carlo (smooth Fresnel, no rough-boundary loss) within 4 standard errors, and its specular
    reflection is Fresnel's ((eta - 1) / (eta + 1))^2; the rough slab is darker than the
    smooth one by more than its noise (the GGX boundary's energy loss, docs/ground-truth.md
    trap 9)."""
    from dermis.groundtruth.slab import slab_reflectance
    from dermis.optics import monte_carlo_slab as mc_slab
    from dermis.optics.layers import Layer, LayerStack
    stack = LayerStack((Layer(1.0, 1.3, (0.032, 0.17, 0.48), (0.74, 0.88, 1.01)),))
    recip = slab_reflectance(mi, stack, roughness=0.3, samples=1 << 16, batches=16, seed=1)
    smooth = slab_reflectance(mi, stack, roughness=0.0, samples=1 << 16, batches=16, seed=1)
    mc = mc_slab.simulate(stack, photons=200_000, r_max_mm=50.0, bins=4, seed=3)
    se_mc = np.hypot(smooth.Rd_stderr, mc.Rd_err)
    assert np.all(np.abs(smooth.Rd_entered - mc.Rd) < 4 * se_mc), (smooth.Rd_entered, mc.Rd,
                                                                   se_mc)
    f0 = ((1.3 - 1.0) / (1.3 + 1.0)) ** 2
    n = 1 << 16  # the black-interior render's samples: reflect with probability F0
    assert np.all(np.abs(smooth.specular - f0) < 4 * math.sqrt(f0 * (1 - f0) / n))
    # the GGX loss is 22 / 11 / 3 % of this slab (R/G/B, docs/ground-truth.md trap 9): red
    # and green resolved at 2^16 paths, blue (~1.6 standard errors a percent) not darker
    # beyond noise
    se_pair = np.hypot(smooth.Rd_stderr, recip.Rd_stderr)
    loss = smooth.Rd_entered - recip.Rd_entered
    assert np.all(loss[:2] > 4 * se_pair[:2]) and loss[2] > -4 * se_pair[2], (loss, se_pair)


@pytest.mark.slow
def test03_boundary_variant_of_a_flat_slab_reads_the_slab_numbers(mi, tmp_path):
    """The boundary variant on a flat, uniformly textured slab seen straight down under a
    uniform sky: each boundary reads albedo + its own specular reflection (the rough one
    slab.py's, the smooth one Fresnel's), so the effect is (a + F0) / (a + spec) - 1, within
    4 standard errors (the half-buffers and both slabs' calibration)."""
    from dermis.groundtruth.slab import slab_reflectance
    from dermis.groundtruth.variants import VariantOptions, boundary_variant
    from dermis.optics.layers import Layer, LayerStack
    from dermis.pipeline.imageio import write_exr
    from dermis.rendering.color import srgb_to_linear
    sky = tmp_path / "sky.exr"
    write_exr(sky, np.ones((8, 16, 3), np.float32))
    light = LightConfig(name="sky", type="environment", map=str(sky))
    stack = LayerStack((Layer(math.inf, 1.3, (0.032, 0.17, 0.48), (0.74, 0.88, 1.01)),))
    grey = 140
    a = float(srgb_to_linear(np.float32(grey / 255.0)))
    mesh = _box(40.0, 40.0, grey)
    cam = _camera(8, fov=2.0, position=(0.0, 0.0, 1000.0), look_at=(0.0, 0.0, 0.0))
    opts = VariantOptions(width=8, height=8, rough_spp=128, smooth_spp=128,
                          slab_samples=1 << 16)
    res = boundary_variant(mi, mesh, stack, cam, [light], opts)
    assert res["normalised"] and res["hit"].all()
    spec = {"rough": slab_reflectance(mi, stack, roughness=0.3, samples=1 << 12).specular,
            "smooth": np.full(3, ((1.3 - 1.0) / (1.3 + 1.0)) ** 2)}
    for name in ("rough", "smooth"):
        h = res[name]
        got = h.mean[res["hit"]].mean(axis=0)
        se = np.sqrt((h.half_diff[res["hit"]] ** 2).sum(axis=0)) / res["hit"].sum()
        s = res["slabs"][name]
        cal = a * np.asarray(s.Rd_stderr) / np.asarray(s.Rd)
        want = a + spec[name]
        assert np.all(np.abs(got - want) < 4 * np.hypot(se, cal)), (name, got, want, se, cal)
    face = res["regions"]["face"]
    want = (a + spec["smooth"]) / (a + spec["rough"]) - 1
    assert np.all(np.abs(np.array(face["effect_rgb"]) - want)
                  < 4 * np.array(face["se_rgb"])), (face, want)


def test04_a_smooth_boundary_refuses_point_and_directional_lights(mi, quick_mesh):
    from dermis.groundtruth.variants import VariantOptions, boundary_variant
    from dermis.pipeline.errors import ConfigError
    from dermis.optics.layers import PRESETS
    with pytest.raises(ConfigError, match="never reaches"):
        boundary_variant(mi, quick_mesh, PRESETS["two_layer"], _camera(8), [POINT],
                         VariantOptions(width=8, height=8))


# ------------------------------------------------------------------------ the causes table
def _metrics(d: dict, light="area") -> dict:
    """A ground_truth_metrics-shaped dict: model -> (rel_lum, rel_rgb) for every region."""
    models = {}
    for model, (lum, rgb) in d.items():
        models[f"{model}-{light}"] = {
            "model": model, "light": light, "bias_rgb": list(rgb),
            "regions": {r: {"rel_lum": lum, "rel_rgb": list(rgb), "sigma_lum": 0.02,
                            "sigma_rgb": [0.02] * 3} for r in REGIONS}}
    ref = {r: {"pixels": 10, "mean_rgb": [0.3, 0.2, 0.1]} for r in REGIONS}
    return {"models": models, "references": {light: {"regions": ref}}}


def _variants(g: float, b: float | None) -> dict:
    rec = lambda e: {r: {"effect_lum": e, "se_lum": 0.01, "effect_rgb": [e] * 3,  # noqa: E731
                         "se_rgb": [0.01] * 3} for r in REGIONS + ("face",)}
    causes = {"interreflection": rec(g)}
    if b is not None:
        causes["boundary"] = rec(b)
    return {"area": {"causes": causes}}


def test05_the_causes_table_parts_sum_to_the_distance():
    """Every row's parts plus its remainder equal its distance, per channel and in
    luminance; a cause that explains a distance exactly leaves no remainder; the profile and
    geometry parts come from the bssrdf_mc rows and the low+bump images."""
    from dermis.reports.causes import causes_table
    d, dmc, g, b, c = -0.10, -0.06, 0.04, -0.02, -0.03
    metrics = _metrics({"bssrdf": (d, (d, d - 0.01, d + 0.02)), "bssrdf_mc": (dmc, (dmc,) * 3),
                        "lafortune": (d, (d,) * 3)})
    labels = np.zeros((4, 4), np.int8)
    labels[:2] = REGION_LABELS["cheek"]
    labels[2:] = REGION_LABELS["nose"]
    images = {}
    for model in ("bssrdf", "lafortune"):
        for geom, v in (("high", 1.0), ("low_bump", 0.95)):
            images[f"{model}-{geom}"] = RenderedImage(
                np.full((8, 8, 3), v, np.float32), np.ones((8, 8), bool), {},
                {"model": model, "light": "area", "geometry": geom})
    table = causes_table(metrics, _variants(g, b), convention=c, images=images, labels=labels)
    rows = table["rows"]
    assert {r["geometry"] for r in rows} == {"high", "low_bump"}
    for r in rows:
        for ch in range(4):
            parts = [p["value"][ch] for p in r["parts"].values() if p and
                     p["value"][ch] is not None]
            assert abs(sum(parts) + r["remainder"]["value"][ch] - r["distance"][ch]) < 1e-12
    row = next(r for r in rows if r["model"] == "bssrdf" and r["region"] == "nose"
               and r["geometry"] == "high")
    # profile first: the distance with the Monte Carlo profile is dmc
    assert abs(row["parts"]["profile"]["value"][0] - (d - dmc)) < 1e-12
    # the interreflection part: the truth without it is T / (1 + g)
    d1 = (1 + dmc) / (1 + c) - 1
    assert abs(row["parts"]["interreflection"]["value"][0] - (d1 - ((1 + d1) * (1 + g) - 1))
               ) < 1e-12
    assert row["parts"]["geometry"]["value"][0] == 0.0       # the reference's own mesh
    low = next(r for r in rows if r["model"] == "lafortune" and r["region"] == "cheek"
               and r["geometry"] == "low_bump")
    assert abs(low["distance"][0] - ((1 + d) * 0.95 - 1)) < 1e-6
    assert abs(low["parts"]["geometry"]["value"][0] - (low["distance"][0] - d)) < 1e-6
    # a distance that is exactly the interreflection the models lack leaves nothing
    exact = 1 / (1 + g) - 1
    t2 = causes_table(_metrics({"lafortune": (exact, (exact,) * 3)}), _variants(g, None))
    for r in t2["rows"]:
        assert abs(r["remainder"]["value"][0]) < 1e-12 and r["parts"]["boundary"] is None
        # the remainder's error: the distance's sigma (none given for the whole face) and
        # the interreflection's in quadrature
        se_i = r["parts"]["interreflection"]["se"][0]
        sigma = 0.0 if r["region"] == "face" else 0.02
        assert abs(r["remainder"]["se"][0] - math.hypot(sigma, se_i)) < 1e-12


def test06_the_causes_page_draws(tmp_path):
    from matplotlib.backends.backend_pdf import PdfPages
    from dermis.reports.causes import causes_pages, causes_table
    table = causes_table(_metrics({"lafortune": (-0.08, (-0.08, -0.09, -0.04))}),
                         _variants(0.02, 0.01), convention=-0.03)
    with PdfPages(tmp_path / "c.pdf") as pdf:
        assert causes_pages(pdf, table) == 1
    assert (tmp_path / "c.pdf").stat().st_size > 0


# ------------------------------------------------------------------------ the stage
@pytest.mark.slow
def test07_stage_plan_settings_and_cache(mi, tmp_path):
    """One causes node per referenced lighting condition when the reference is on (none
    when it or [causes] is off), the boundary variant only under disc lights, a point light
    refused as a boundary light; the stage's artifact holds every region's effects; a
    second run renders nothing (cached)."""
    from dermis.pipeline.api import run
    from dermis.pipeline.errors import ConfigError
    from dermis.pipeline.plan import build_graph
    from dermis.stages import causes
    over = {"render": {"lights": ["point", "area"]},
            "reference": {"enabled": True, "width": 16, "height": 16, "min_spp": 2,
                          "max_spp": 2, "budget_s": 0, "slab_samples": 2048},
            "causes": {"diffuse_spp": 4, "rough_spp": 2, "smooth_spp": 2,
                       "slab_samples": 2048}}
    scene = load_scene(scene_file(tmp_path, over))
    nodes, _ = build_graph(scene)
    assert {n for n in nodes if n.startswith("causes")} == {"causes-point", "causes-area"}
    assert nodes["causes-area"].params["boundary"] and not nodes["causes-point"].params[
        "boundary"]
    assert "optics" not in nodes["causes-point"].params   # the diffuse head reads no optics
    for table in ("reference", "causes"):
        off = {**over, table: {**over[table], "enabled": False}}
        s = load_scene(scene_file(tmp_path, off))
        assert not [n for n in build_graph(s)[0] if n.startswith("causes")], table
    bad = load_scene(scene_file(tmp_path, {**over, "causes": {"boundary_lights": ["point"]}}))
    with pytest.raises(ConfigError, match="never reaches"):
        build_graph(bad)

    cache = tmp_path / "cache"
    first = run(scene, cache=cache, until="causes", export=False)
    ran = {n.id: n.status for n in first.nodes}
    assert ran["causes-area"] == "ran" and ran["causes-point"] == "ran"
    from dermis.pipeline import artifacts
    art = artifacts.load(next(n for n in first.nodes if n.id == "causes-area").path)
    assert set(art.info["causes"]) == {"interreflection", "boundary"}
    assert set(art.info["causes"]["interreflection"]) == set(REGIONS) | {"face"}
    assert np.all(art.linear >= 0)                     # interreflected light, never negative
    second = run(scene, cache=cache, until="causes", export=False)
    assert {n.id: n.status for n in second.nodes if n.id.startswith("causes")} == {
        "causes-area": "cached", "causes-point": "cached"}
    assert causes.NAME == "causes"
