"""One bounce of indirect light (lighting/indirect.py, rendering/indirect_shading.py, stage
``indirect``) against independent evidence.

* A floor beside a uniformly lit wall: E_ind at a floor point is a E_wall F, F the closed-form
  (Lambert/Hottel contour) form factor from a differential area to the wall's rectangle.
  Tolerance: 5 standard errors of independent samples, a E_wall sqrt(F (1 - F) / S) (a hit
  is a Bernoulli trial of probability F; the stratified estimate's variance is at most
  that), a false-failure rate below 1e-6 per point.
* A lit surface seen from behind re-emits nothing; a sphere (convex) sees nothing of itself:
  E_ind = 0 exactly.
* A Lambertian BRDF's response is albedo E_ind / pi at every hit, exactly (its f is
  constant, so the cosine-weighted directions carry no variance): float32 tolerance.
* Lafortune's response is rho_dh(wo) E_ind / pi, rho_dh = L(mu_o) + a (1 - L(mu_o)) (the
  coupled matte term, models/lafortune.py): 5 standard errors of the pixel mean, from the
  pixels' own spread.
* ``[render] indirect = false`` plans exactly the nodes of a scene without the key; with
  true, every image of a mesh and light reads one indirect node, radiance stays finite and
  non-negative, the BSSRDF's points gain E_ind times the diffuse entry transmittance, and
  its exitance grows by the gather of that light alone, keeping the point light's shadow
  edges (which reading it as the light's own irradiance would lose).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from dermis.lighting.indirect import at_points, bounce_irradiance, one_bounce
from dermis.lighting.visibility import Visibility, interpolate
from dermis.models import asperity, hk93, lafortune, lambert
from dermis.models.lafortune import LafortuneParams, lafortune_lobe_albedo
from dermis.models.lambert import LambertParams
from dermis.optics.transmittance import Transmittance
from dermis.pipeline.artifacts import Mesh
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.rendering.color import srgb_to_linear
from dermis.rendering.options import RenderOptions
from dermis.rendering.shade import render

sys.path.insert(0, str(Path(__file__).parent))
from render_fixtures import icosphere, merge, plane  # noqa: E402
from scene_toml import scene_file  # noqa: E402

N_SIGMA = 5.0
F32_RTOL = 1e-5
WALL = 200.0                        # wall: x in [-100, 100], z in [0, 200], facing +y
WALL_SRGB = (200, 120, 60)          # its texture, uniform


def _form_factor(p, n, polygon) -> float:
    """Differential area at ``p`` (normal ``n``) to a planar polygon: Lambert's contour
    formula F = |sum_i theta_i n . (R_i x R_i+1) / |R_i x R_i+1|| / (2 pi) (Howell's
    catalogue of configuration factors; R_i from p to the corners, theta_i their angle)."""
    total = 0.0
    for i in range(len(polygon)):
        a, b = polygon[i] - p, polygon[(i + 1) % len(polygon)] - p
        c = np.cross(a, b)
        theta = math.acos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))
        total += theta * (n @ c) / np.linalg.norm(c)
    return abs(total) / (2.0 * math.pi)


def _wall_and_floor(n: int = 20):
    """A floor (z = 0, y in [1, 201], facing +z) and a textured wall (y = 0, facing +y), as
    separate vertex sets.  The 1 mm gap keeps the wall's bottom vertices' shadow rays off the
    floor's plane (they would start on it and be blocked at t = 0)."""
    floor = plane(WALL, n, centre=(0.0, WALL / 2 + 1.0))
    w = plane(WALL, n)
    wv = np.asarray(w.vertices)
    wall_v = np.stack([wv[:, 0], np.zeros(len(wv)), WALL / 2 - wv[:, 1]], axis=1)  # rotated
    m = merge(floor, Mesh(vertices=wall_v, faces=w.faces,
                          normals=np.tile(np.float32([0, 1, 0]), (len(wv), 1))))
    uv = np.full((len(m.vertices), 2), 0.5, np.float32)
    tex = np.broadcast_to(np.uint8(WALL_SRGB), (4, 4, 3)).copy()
    mesh = Mesh(vertices=m.vertices, faces=m.faces, normals=m.normals, uv=uv,
                uv_faces=m.faces.copy(), texture_srgb=tex)
    return mesh, len(floor.vertices)


def test01_floor_beside_lit_wall_matches_form_factor():
    mesh, n_floor = _wall_and_floor()
    vis = Visibility(mesh.vertices, mesh.faces)
    light = LightConfig(name="d", type="directional", direction=(0.0, 1.0, 1.0),
                        intensity=(1.0, 1.0, 1.0))
    samples = 16384
    e_ind, e_dir = one_bounce(mesh, [light], vis, samples=samples, direct_samples=1, seed=3)
    e_wall = e_dir[n_floor:]
    np.testing.assert_allclose(e_wall, math.sqrt(0.5), rtol=F32_RTOL)   # uniformly lit
    albedo = srgb_to_linear(np.asarray(WALL_SRGB, np.float64) / 255.0)
    corners = np.array([[-100, 0, 0], [100, 0, 0], [100, 0, 200], [-100, 0, 200]], float)
    v = np.asarray(mesh.vertices)
    for y0 in (11.0, 21.0, 51.0, 101.0, 191.0):
        i = np.flatnonzero((np.abs(v[:n_floor, 0]) < 1e-9) & (np.abs(v[:n_floor, 1] - y0) < 1e-9))
        assert len(i) == 1
        F = _form_factor(v[i[0]], np.array([0.0, 0.0, 1.0]), corners)
        expect = albedo * math.sqrt(0.5) * F
        tol = N_SIGMA * albedo * math.sqrt(0.5) * math.sqrt(F * (1 - F) / samples)
        np.testing.assert_array_less(np.abs(e_ind[i[0]] - expect), tol)
    above = v[n_floor:, 2] > 0                    # the wall above the floor's plane sees it
    assert np.all(e_ind[n_floor:][above] > 0)


def test02_a_wall_lit_on_its_far_side_sends_nothing():
    """The wall turned round (facing -y, lit from -y): the floor sees only its unlit back,
    which re-emits nothing (a ray into a mesh through an opening)."""
    mesh, n_floor = _wall_and_floor(8)
    normals = np.array(mesh.normals)
    normals[n_floor:] *= -1.0
    faces = np.array(mesh.faces)
    wall = np.arange(len(faces)) >= len(faces) // 2
    faces[wall] = faces[wall][:, ::-1]
    turned = Mesh(vertices=mesh.vertices, faces=faces, normals=normals, uv=mesh.uv,
                  uv_faces=faces.copy(), texture_srgb=mesh.texture_srgb)
    vis = Visibility(turned.vertices, turned.faces)
    light = LightConfig(name="d", type="directional", direction=(0.0, -1.0, 1.0),
                        intensity=(1.0, 1.0, 1.0))
    e_ind, e_dir = one_bounce(turned, [light], vis, samples=256, direct_samples=1)
    np.testing.assert_allclose(e_dir[n_floor:], math.sqrt(0.5), rtol=F32_RTOL)   # lit
    assert np.all(e_ind[:n_floor] == 0.0)


def test03_convex_sphere_sees_nothing():
    mesh = icosphere(50.0, 4)
    vis = Visibility(mesh.vertices, mesh.faces)
    light = LightConfig(name="p", type="point", position=(200.0, 100.0, 300.0),
                        intensity=(1e5, 1e5, 1e5))
    e_ind, e_dir = one_bounce(mesh, [light], vis, samples=256, direct_samples=1)
    assert (e_dir[:, 0] > 0).mean() > 0.3          # lit, so a self-hit would show
    assert np.all(e_ind == 0.0)


def test04_interpolation_and_closest_points_reproduce_a_linear_field(rng):
    mesh = plane(100.0, 7)
    vis = Visibility(mesh.vertices, mesh.faces)
    v = np.asarray(mesh.vertices)
    field = np.stack([v[:, 0], 2 * v[:, 1] + 5, np.ones(len(v))], axis=1)
    q = np.concatenate([rng.uniform(-50, 50, (500, 2)), np.zeros((500, 1))], axis=1)
    got = at_points(field, mesh, q, vis)
    np.testing.assert_allclose(got, np.stack([q[:, 0], 2 * q[:, 1] + 5, np.ones(500)], 1),
                               atol=1e-3)
    near = vis.closest(q)
    np.testing.assert_allclose(interpolate(v, mesh.faces, near.tri, near.bary), q, atol=1e-3)


def _flat_scene(e_value):
    """A 100 mm plane seen head-on from afar (view cosine > 0.999 everywhere), lit by a
    directional light, with a uniform E_ind per vertex."""
    mesh = plane(100.0, 8)
    cam = CameraConfig(position=(0.0, 0.0, 4000.0), look_at=(0.0, 0.0, 0.0), fov_deg=1.0,
                       width=48, height=48)
    light = LightConfig(name="d", type="directional", direction=(0.3, 0.2, 1.0),
                        intensity=(1.0, 1.0, 1.0))
    e_ind = np.tile(np.float32(e_value), (len(mesh.vertices), 1))
    return mesh, cam, light, e_ind


def _two(mesh, light, model, params, cam, e_ind, cl_env, **opts):
    base = render(mesh, light, model, params, cam, RenderOptions(spp=4, **opts), cl_env=cl_env)
    more = render(mesh, light, model, params, cam, RenderOptions(spp=4, indirect=e_ind, **opts),
                  cl_env=cl_env)
    return base, more


def test05_lambert_response_is_albedo_e_over_pi(cl_env):
    mesh, cam, light, e_ind = _flat_scene((0.3, 0.2, 0.1))
    albedo = np.array([0.6, 0.5, 0.4])
    base, more = _two(mesh, light, lambert.MODEL, LambertParams(albedo), cam, e_ind, cl_env)
    full = more.coverage == 1.0
    assert full.sum() > 1000
    np.testing.assert_allclose((more.linear - base.linear)[full],
                               np.broadcast_to(albedo * e_ind[0] / math.pi, (full.sum(), 3)),
                               rtol=1e-4)
    # none: the image is byte-identical to the direct-only render
    none = render(mesh, light, lambert.MODEL, LambertParams(albedo), cam,
                  RenderOptions(spp=4, indirect=None), cl_env=cl_env)
    assert none.linear.tobytes() == base.linear.tobytes()


def test06_lafortune_response_is_its_directional_albedo(cl_env):
    """rho_dh = L(mu_o) + a (1 - L(mu_o)) (models/lafortune.py, the coupled matte term; L by
    its own quadrature): the table's Monte Carlo error is <= 4e-3 of L (~0.03) and the
    interpolation's <= 2.2e-4 of rho_dh (rendering/indirect_shading.py), so 1e-3 bounds it."""
    mesh, cam, light, e_ind = _flat_scene((1.0, 1.0, 1.0))
    p = LafortuneParams()
    base, more = _two(mesh, light, lafortune.MODEL, p, cam, e_ind, cl_env, textured=False)
    full = more.coverage == 1.0
    got = (more.linear - base.linear)[full].astype(np.float64)
    lobe = lafortune_lobe_albedo(np.array([1.0]), p)[0]
    expect = (lobe + p.rho_d * (1.0 - lobe)) / math.pi      # view cosine 0.9999+
    np.testing.assert_allclose(got, np.broadcast_to(expect, got.shape), rtol=1e-3)
    # the lobes: 1 - a of the light not taken by the matte term
    assert np.all(got.mean(axis=0) > p.rho_d / math.pi * 1.01)


@pytest.mark.parametrize("model,params", [(hk93.MODEL, None), (asperity.MODEL, None),
                                          (lafortune.MODEL, None)])
def test07_radiance_finite_and_not_negative(cl_env, model, params):
    mesh, n_floor = _wall_and_floor(8)
    vis = Visibility(mesh.vertices, mesh.faces)
    light = LightConfig(name="p", type="point", position=(60.0, 300.0, 250.0),
                        intensity=(1e5, 1e5, 1e5))
    e_ind, _ = one_bounce(mesh, [light], vis, samples=64, direct_samples=1)
    cam = CameraConfig(position=(0.0, 500.0, 300.0), look_at=(0.0, 60.0, 40.0), fov_deg=40.0,
                       width=40, height=40)
    base, more = _two(mesh, light, model, params, cam, e_ind, cl_env)
    assert more.info["nonfinite_pixels"] == 0
    assert np.all(np.isfinite(more.linear)) and np.all(more.linear >= 0)
    assert np.all(more.linear >= base.linear)      # it only adds non-negative terms
    assert (more.linear > base.linear).any()


def test08_bounce_checks_its_inputs():
    mesh = plane(10.0, 2)
    vis = Visibility(mesh.vertices, mesh.faces)
    from dermis.pipeline.errors import DermisError
    with pytest.raises(DermisError, match="one row per vertex"):
        bounce_irradiance(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), mesh,
                          np.zeros((3, 3)), vis, samples=4)
    with pytest.raises(DermisError, match="samples"):
        bounce_irradiance(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), mesh,
                          np.zeros((len(mesh.vertices), 3)), vis, samples=0)


# --------------------------------------------------------------------------- pipeline

def _graph(tmp_path, render_over):
    from dermis.pipeline.config import load_scene
    from dermis.pipeline.plan import build_graph
    over = {"render": {"models": ["lafortune", "bssrdf"], "lights": ["point"],
                       "geometries": ["high", "low_bump"], **render_over}}
    scene = load_scene(scene_file(tmp_path, over, name=f"s{len(render_over)}.toml"))
    return scene, build_graph(scene)[0]


def test09_off_plans_the_nodes_of_a_scene_without_it(tmp_path):
    _, without = _graph(tmp_path, {})
    _, off = _graph(tmp_path, {"indirect": False})
    assert list(without) == list(off)
    for nid, node in without.items():
        assert (node.params, node.deps) == (off[nid].params, off[nid].deps), nid
        assert "indirect" not in node.params and "indirect" not in node.deps
    _, on = _graph(tmp_path, {"indirect": True, "indirect_samples": 8})
    extra = sorted(set(on) - set(without))
    assert extra == ["indirect-mesh_high-point", "indirect-mesh_low-point"]
    for nid, node in on.items():
        if node.stage in ("render", "irradiance"):
            mesh = "mesh_low" if "low" in nid else "mesh_high"
            assert node.deps["indirect"] == f"indirect-{mesh}-point", nid
        if node.stage == "bssrdf":
            assert node.params["indirect"] is True
            assert "indirect" not in node.deps      # it reads the irradiance that holds it


def test10_pipeline_images_brighter_and_finite(tmp_path):
    from dermis.pipeline import api
    from dermis.pipeline.artifacts import load
    from dermis.pipeline.store import Store
    images = {}
    for on in (False, True):
        scene, _ = _graph(tmp_path, {"indirect": on, "indirect_samples": 16,
                                     "geometries": ["high"]})
        summary = api.run(scene, cache=tmp_path / "cache", export=False)
        store = Store(tmp_path / "cache")
        keys = {n.id: n.key for n in summary.nodes}
        art = lambda nid: load(store.artifact_dir(nid, keys[nid]))  # noqa: E731
        for model in ("lafortune", "bssrdf"):
            images[model, on] = art(f"render-{model}-point-high").linear
        images["points", on] = art("irradiance-mesh_high-point").irradiance
        if on:
            ind = art("indirect-mesh_high-point").irradiance
            assert np.all(np.isfinite(ind)) and np.all(ind >= 0) and ind.max() > 0
            mesh, pts = art("mesh_high"), art("samples-mesh_high")
            entry = Transmittance(scene.optics.layers[0].eta / scene.optics.eta_above,
                                  scene.bssrdf.surface_reflection)
            # the points gain E_ind times the entry transmittance of diffuse light
            added = at_points(ind, mesh, pts.positions, Visibility(mesh.vertices, mesh.faces))
            np.testing.assert_allclose(images["points", True] - images["points", False],
                                       added * entry.mean, rtol=1e-4,
                                       atol=1e-6 * float(images["points", False].max()))
    for model in ("lafortune", "bssrdf"):
        off, on = images[model, False], images[model, True]
        assert np.all(np.isfinite(on)) and np.all(on >= 0), model
        assert on.sum() > off.sum(), model
    assert np.all(images["lafortune", True] >= images["lafortune", False])


def test11_bssrdf_gathers_the_extra_light_whole_and_keeps_shadow_edges(cl_env):
    """A point light's shadow edge across a sphere, plus a uniform extra irradiance c at every
    point (what the indirect term adds): with ``indirect`` the exitance grows by exactly the
    gather of c alone (brute-force gathers: the same sums, float32 tolerance 1e-4) and the
    edges stay; read as the light's own irradiance (no flag) every point would count as lit,
    the edges vanish and the shadow's near field goes wrong."""
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance
    from near_field_scenes import shadowed_sphere
    prof = build_profiles(PRESETS["two_layer"])
    sc = shadowed_sphere(prof, PRESETS["two_layer"], light="point", queries=3000,
                         subdivisions=5, density=0.005)
    shading = ShadingPoints(sc["q"], sc["ns"], sc["ng"])

    def m(E, indirect, lights):
        o = ExitanceOptions(epsilon=None, brute_force=True, transmittance=sc["transmit"],
                            env=cl_env, indirect=indirect)
        return exitance(sc["pts"], E, prof, shading, lights=lights, visibility=sc["vis"],
                        options=o)
    c = np.float32(0.05) * sc["E"].max()
    off, st_off = m(sc["E"], False, [sc["light"]])
    on, st_on = m(sc["E"] + c, True, [sc["light"]])
    alone, _ = m(np.full_like(sc["E"], c), False, [])
    assert st_on["edge_crossings"] == st_off["edge_crossings"] and st_off["edge_crossings"][0] > 0
    np.testing.assert_allclose(on - off, alone, rtol=1e-4)
    wrong, st_wrong = m(sc["E"] + c, False, [sc["light"]])
    assert st_wrong["edge_crossings"] == [0]
    assert np.abs(wrong - off - alone).max() > 1.0 * np.abs(alone).max()
