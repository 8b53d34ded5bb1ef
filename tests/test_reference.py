"""Mitsuba 3 ground truth: export round-trips, flat slab, region masks, the stage, distances.

Everything that needs Mitsuba asks for the ``mi`` fixture, which skips with one message when
the ``reference`` extra is not installed.  Sizes are tiny (the whole file stays well under
90 s on 2 cores); the real references are in bench/bench_reference.py.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.shared import RunCache
from dermis.pipeline.config import CameraConfig, LightConfig, load_scene
from dermis.geometry.regions import REGION_LABELS, face_regions

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "scenes" / "quick.toml"


@pytest.fixture(scope="module")
def quick_mesh(tmp_path_factory):
    """The quick scene's procedural high mesh (60k triangles), built once."""
    from dermis.pipeline import artifacts
    from dermis.pipeline.api import run
    scene = load_scene(QUICK)
    summary = run(scene, cache=tmp_path_factory.mktemp("cache"), until="mesh_high",
                  export=False)
    rep = next(n for n in summary.nodes if n.id == "mesh_high")
    return artifacts.load(rep.path)


def _camera(width, height, position=(0.0, -15.0, 1000.0)):
    return CameraConfig(position=position, look_at=(0.0, -15.0, 0.0), up=(0.0, 1.0, 0.0),
                        fov_deg=17.0, width=width, height=height)


# ------------------------------------------------------------------------ without Mitsuba
def test01_without_mitsuba_the_stage_is_skipped_with_one_message(monkeypatch, capsys):
    from dermis.pipeline.plan import build_graph
    from dermis.groundtruth import mitsuba
    from dermis.stages import reference
    monkeypatch.setattr(mitsuba, "mitsuba_missing_reason",
                        lambda: "Mitsuba 3 is not installed: pip install mitsuba")
    monkeypatch.setattr(reference, "_SKIP_NOTICES", set())
    scene = load_scene(QUICK, overrides={"reference": {"enabled": True}})
    for _ in range(2):  # planning twice (run + status) still says it once
        nodes, targets = build_graph(scene)
    assert not [n for n in nodes if n.startswith("reference")]
    assert "report" in nodes and "images" in nodes          # the rest of the report builds
    err = capsys.readouterr().err
    assert err.count("reference stage skipped") == 1 and "pip install mitsuba" in err


def test02_reference_on_by_default_and_config_errors():
    from dermis.pipeline.errors import ConfigError
    from dermis.pipeline.plan import build_graph
    from dermis.pipeline.config import ReferenceConfig
    from dermis.groundtruth import mitsuba
    assert ReferenceConfig().enabled                  # every default run measures the truth
    nodes, _ = build_graph(load_scene(QUICK))         # the quick scene turns it off
    assert not [n for n in nodes if n.startswith("reference")]
    if mitsuba.mitsuba_missing_reason() is None:
        nodes, _ = build_graph(load_scene(QUICK, overrides={"reference": {"enabled": True}}))
        groups = [label for label, _ in load_scene(QUICK).light_groups()]
        assert sorted(n for n in nodes if n.startswith("reference")) == sorted(
            f"reference-{g}" for g in groups)
    with pytest.raises(ConfigError, match="must divide the camera"):
        load_scene(QUICK, overrides={"reference": {"enabled": True, "width": 30, "height": 30}})
    with pytest.raises(ConfigError, match="give both"):
        load_scene(QUICK, overrides={"reference": {"enabled": True, "width": 40}})
    from dermis.pipeline.scene_rules import reference_size
    ref = load_scene(QUICK).reference
    assert [reference_size(_camera(w, h), ref) for w, h in ((800, 800), (160, 160),
            (32, 32), (1920, 1080), (101, 103))] == [(100, 100), (80, 80), (32, 32), (96, 54),
                                                      (101, 103)]
    with pytest.raises(ConfigError, match="reference.lights"):
        build_graph(load_scene(QUICK, overrides={"reference": {"enabled": True,
                                                               "lights": ["nope"]}}))
    with pytest.raises(ConfigError, match="reference.min_spp"):
        load_scene(QUICK, overrides={"reference": {"min_spp": 64, "max_spp": 32}})


# ------------------------------------------------------------------------ regions
def test03_region_masks_disjoint_nonempty_and_the_same_for_two_cameras(quick_mesh):
    from dermis.reports.ground_truth import region_labels_for
    labels = face_regions(quick_mesh.vertices, quick_mesh.faces)
    assert set(np.unique(labels)) == {0, *REGION_LABELS.values()}     # every region exists
    cams = [_camera(96, 96), _camera(96, 96, position=(500.0, 150.0, 850.0))]
    per_cam = []
    for cam in cams:
        lab, tri = region_labels_for(quick_mesh, cam, width=96, height=96, with_faces=True)
        # disjoint: one label per pixel, and it is the label of the face the pixel sees
        assert np.array_equal(lab[tri >= 0], labels[tri[tri >= 0]])
        per_cam.append((lab, tri))
    for name, k in REGION_LABELS.items():
        seen = [set(tri[lab == k].tolist()) for lab, tri in per_cam]
        assert seen[0] and seen[1], name
        both = seen[0] & seen[1]
        assert both, f"{name}: the two cameras see no common face"
        # a face seen by both cameras carries the same region in both
        assert all(labels[f] == k for f in both)
        # and no face of region k is labelled otherwise by either camera
        for lab, tri in per_cam:
            assert not np.any((labels[np.maximum(tri, 0)] == k) & (tri >= 0) & (lab != k))


# ------------------------------------------------------------------------ export round trip
def test04_camera_rays_round_trip(mi, quick_mesh):
    """Mitsuba's pixel-centre rays hit the same faces as dermis's camera rays."""
    from dermis.reports.ground_truth import region_labels_for
    from dermis.groundtruth.passes import pixel_hits
    from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
    cam = _camera(64, 48)  # not square: fov across the shorter side
    head = head_scene(mi, quick_mesh, None, cam, [], width=64, height=48,
                      options=HeadSceneOptions(roughness=0.3, material="lambert"))
    try:
        hit, prim = pixel_hits(mi, head.scene, width=64, height=48)
    finally:
        release(head)
    _, tri = region_labels_for(quick_mesh, cam, width=64, height=48, with_faces=True)
    assert np.array_equal(hit, tri >= 0) or np.mean(hit != (tri >= 0)) < 0.005
    both = hit & (tri >= 0)
    assert np.mean(prim[both] == tri[both]) > 0.99


def test05_environment_orientation_and_rotation(mi):
    """Mitsuba's envmap radiance along a direction equals dermis's lookup (0 and 40 deg)."""
    import drjit as dr
    from dermis.lighting.environment import EnvironmentMap
    from dermis.groundtruth.scene_export import light_dicts
    rng = np.random.default_rng(3)
    # 4x4-pixel blocks of constant radiance: bilinear (Mitsuba) and nearest (dermis) lookups
    # differ only at block borders
    rad = np.kron(rng.random((8, 16, 3)) ** 2 * 10, np.ones((4, 4, 1))).astype(np.float32)
    for rot in (0.0, 40.0):
        env = EnvironmentMap(rad, rotation_deg=rot)
        light = LightConfig(name="sky", type="environment", map="procedural_sunset",
                            rotation_deg=rot)
        ms_map = light_dicts(mi, [light], target=(0, 0, 0))
        d = ms_map["light_sky"]
        d["bitmap"] = mi.Bitmap(rad)
        em = mi.load_dict(d)
        dirs = rng.normal(size=(2000, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
        si.wi = mi.Vector3f(*(-dirs.T.astype(np.float32)))
        got = np.asarray(em.eval(si)).T
        want = env.lookup(dirs)
        # Mitsuba interpolates bilinearly, dermis is piecewise constant: compare on the
        # rank order of brightness (the same pixels are bright) and the means
        corr = np.corrcoef(got[:, 0], want[:, 0])[0, 1]
        wrong = np.corrcoef(got[:, 0], EnvironmentMap(rad, rotation_deg=-rot - 90).lookup(
            dirs)[:, 0])[0, 1]
        assert corr > 0.9 and corr > wrong + 0.3, (rot, corr, wrong)


def test06_lambert_export_agrees_with_dermis_within_noise(mi, quick_mesh, cl_env):
    """A Lambertian head (the albedo texture) under each light type: dermis (block-averaged
    4x4 pixel centres) and Mitsuba (box filter, direct light only) agree on the mean over
    the face within 3 standard errors of the pair, and per 4x4 block within the noise."""
    from dermis.geometry.regions import block_mean
    from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
    from dermis.models import lambert
    from dermis.rendering.shade import render
    lights = [
        LightConfig(name="point", type="point", position=(350.0, 450.0, 600.0),
                    intensity=(4e5, 4e5, 4e5)),
        LightConfig(name="area", type="disc", position=(350.0, 450.0, 600.0),
                    direction=(-0.35, -0.45, -0.6), radius=70.0, intensity=(4e5, 4e5, 4e5),
                    samples=64),
        LightConfig(name="dir", type="directional", direction=(-0.6, 0.3, 0.75),
                    intensity=(0.6, 0.6, 0.6)),
        LightConfig(name="sunset", type="environment", map="procedural_sunset", samples=64),
    ]
    w = 24
    for light in lights:
        head = head_scene(mi, quick_mesh, None, _camera(w, w), [light], width=w, height=w,
                          options=HeadSceneOptions(roughness=0.3, material="lambert"))
        try:  # direct light only: dermis's renderer has no interreflection
            integ = mi.load_dict({"type": "path", "max_depth": 2, "hide_emitters": True})
            a = np.asarray(mi.render(head.scene, integrator=integ, spp=64, seed=1))[..., :3]
            b = np.asarray(mi.render(head.scene, integrator=integ, spp=64, seed=2))[..., :3]
        finally:
            release(head)
        res = render(quick_mesh, light, lambert.MODEL, lambert.LambertParams(),
                     _camera(4 * w, 4 * w), cl_env=cl_env)
        D, full = block_mean(res.linear, res.mask, 4)
        M = (a + b) / 2.0
        hd = (a - b) / 2.0
        lum = np.array([0.2126, 0.7152, 0.0722])
        m_mi, m_de = (M[full] @ lum).mean(), (D[full] @ lum).mean()
        se = math.sqrt(((hd[full] @ lum) ** 2).sum()) / full.sum()
        # dermis's own noise (16-64 light samples per pixel, 16 pixels per block) is small
        assert abs(m_mi - m_de) < 3 * se + 0.02 * m_de, (light.name, m_mi, m_de, se)
        err = np.sqrt(((M[full] - D[full]) ** 2).mean())
        noise = np.sqrt((hd[full] ** 2).mean())
        assert err < 2.0 * noise + 0.1 * np.sqrt((D[full] ** 2).mean()), (light.name, err, noise)


# ------------------------------------------------------------------------ flat slab
def test07_flat_slab_matches_monte_carlo_and_catches_the_units_trap(mi):
    """A 1 mm slab of Skin1 (finite, so its Rd depends on sigma x thickness: a mm/cm mix-up
    changes it 2-5x) behind a smooth boundary (roughness 0: the Monte Carlo's Fresnel
    boundary): Mitsuba's Rd per entered flux agrees with dermis's Monte Carlo and the
    multipole within 4 standard errors of the pair.  The reference's GGX boundary loses
    energy on top of this (22 / 11 / 3 % of this slab at alpha 0.3; docs/ground-truth.md
    trap 9)."""
    from dermis.optics.layers import Layer, LayerStack
    from dermis.groundtruth.slab import slab_reflectance
    from dermis.optics import monte_carlo_slab as mc_slab
    from dermis.optics.layer_profiles import build_profiles

    def stack(d):
        return LayerStack((Layer(d, 1.3, (0.032, 0.17, 0.48), (0.74, 0.88, 1.01)),))

    got = slab_reflectance(mi, stack(1.0), roughness=0.0, samples=1 << 15, batches=8)
    ref = mc_slab.simulate(stack(1.0), photons=60000, r_max_mm=50.0, bins=4)
    mc = ref.Rd
    multipole = build_profiles(stack(1.0)).Rd
    assert np.allclose(mc, multipole, rtol=0.05)
    tol = 4 * np.hypot(got.Rd_stderr / (1 - got.specular), ref.Rd_err)
    assert np.all(np.abs(got.Rd_entered - mc) < tol), (got.Rd_entered, mc, tol)
    for wrong in (0.1, 10.0):  # the slab read in cm, or its coefficients in 1/cm
        mc_wrong = mc_slab.simulate(stack(wrong), photons=20000, r_max_mm=50.0, bins=4).Rd
        assert np.any(np.abs(got.Rd_entered - mc_wrong) > tol), wrong  # the check catches it


# ------------------------------------------------------------------------ stage + distances
def test08_stage_runs_and_distances_are_honest(mi, quick_mesh, tmp_path):
    """The stage on the quick head (40x40, 16 spp, one light): its noise and region
    statistics exist; a fake model 10 % brighter than the reference is measured at ~10 %
    where the reference resolves it; the report pages build with and without references."""
    from types import SimpleNamespace
    from matplotlib.backends.backend_pdf import PdfPages
    from dermis.pipeline.artifacts import RenderedImage
    from dermis.reports.ground_truth import ground_truth_metrics, ground_truth_pages
    from dermis.stages import reference
    from dermis.pipeline.taskpool import SerialPool
    scene = load_scene(QUICK, overrides={"reference": {
        "enabled": True, "width": 40, "height": 40, "min_spp": 16, "max_spp": 16, "budget_s": 0,
        "slab_samples": 4096}})
    label, lights = scene.light_groups()[0]
    node = reference.node(scene, label, lights)
    ctx = SimpleNamespace(out_dir=tmp_path, progress=None, shared=RunCache(),
                          tasks=SerialPool())
    ref = reference.run(node.params, {"mesh": quick_mesh}, ctx).artifact
    info = ref.info
    assert info["noise"]["1"]["rel"] > info["noise"]["4"]["rel"] > 0       # averaging helps
    assert set(info["regions"]) == set(REGION_LABELS)
    assert all(math.isfinite(v) for v in info["noise_fit"].values())
    assert (tmp_path / f"reference-{label}.exr").is_file()
    # a fake model: the reference at camera resolution (nearest), 10 % brighter
    f = scene.camera.width // 40
    up = np.kron(ref.linear, np.ones((f, f, 1))).astype(np.float32) * 1.1
    mask = np.kron(ref.mask, np.ones((f, f))).astype(bool)
    fake = RenderedImage(up, mask, {"total": 1.0}, {"model": "lafortune", "light": label,
                                                   "geometry": "high"})
    gt = ground_truth_metrics({"fake": fake}, {label: ref}, mesh=quick_mesh,
                              camera=scene.camera)
    rec = gt["models"][f"lafortune-{label}"]
    s = rec["scales"]["1"]
    assert abs(s["rel_rmse"] - 0.1) < 1e-3                  # an exact copy, 10 % brighter
    for f, sc in rec["scales"].items():                       # claimed only where resolved
        assert sc["resolved"] == (0.1 > 2.0 * sc["ref_noise"]), f
        assert abs(sc["rel_rmse_true"] ** 2 - max(0.01 - sc["ref_noise"] ** 2, 0)) < 1e-3
    assert all(abs(g["rel_lum"] - 0.1) < 1e-6 for g in rec["regions"].values())
    assert s["speedup"] > 0 and math.isfinite(rec["flip"])
    with PdfPages(tmp_path / "gt.pdf") as pdf:
        n = ground_truth_pages(pdf, gt, {"fake": fake}, {label: ref})
        n0 = ground_truth_pages(pdf, None, {}, {}, skip_reason="no Mitsuba")
    assert n == 4 and n0 == 1 and (tmp_path / "gt.pdf").stat().st_size > 0


def test09_report_gains_the_ground_truth_section(mi, tmp_path, monkeypatch):
    """The whole pipeline with references on: the report node reads them, writes
    ground_truth.json (every high-mesh model of the light measured, the thesis's ranked) and its PDF
    has the section; without Mitsuba the same report still builds and says why."""
    import json
    import subprocess
    from dermis.stages import reference
    from dermis.pipeline.api import run
    from dermis.groundtruth import mitsuba
    over = {"camera": {"width": 80, "height": 80}, "mesh": {"high_triangles": 20_000},
            "render": {"models": ["lafortune", "bssrdf", "bssrdf_mc"], "lights": ["point"],
                       "geometries": ["high"]},
            "output": {"previews": False, "output_dir": str(tmp_path / "out")},
            "reference": {"enabled": True, "width": 40, "height": 40, "min_spp": 8,
                          "max_spp": 8, "budget_s": 0, "slab_samples": 4096}}
    cache = tmp_path / "cache"

    def report_of(summary):
        rep = next(n for n in summary.nodes if n.id == "report")
        return Path(rep.path)

    out = report_of(run(load_scene(QUICK, overrides=over), cache=cache, export=False))
    gt = json.loads((out / "ground_truth.json").read_text())
    assert set(gt["models"]) == {"lafortune-point", "bssrdf-point", "bssrdf_mc-point"}
    # the ranking is of the thesis's models: bssrdf_mc is measured, not ranked
    assert sorted(r["model"] for r in gt["ranking"]["point"]) == ["bssrdf", "lafortune"]
    assert (out / "gt-error-bssrdf-point.png").is_file()
    text = subprocess.run(["pdftotext", str(out / "report.pdf"), "-"], capture_output=True,
                          text=True, check=True).stdout
    assert "Distance to ground truth" in text and "Mitsuba" in text

    monkeypatch.setattr(mitsuba, "mitsuba_missing_reason",
                        lambda: "Mitsuba 3 is not installed: pip install mitsuba")
    monkeypatch.setattr(reference, "_SKIP_NOTICES", set())
    out = report_of(run(load_scene(QUICK, overrides=over), cache=cache, export=False))
    assert not (out / "ground_truth.json").exists()
    text = subprocess.run(["pdftotext", str(out / "report.pdf"), "-"], capture_output=True,
                          text=True, check=True).stdout
    assert "Reference stage skipped" in text and "pip install mitsuba" in text
