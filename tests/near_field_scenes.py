"""Synthetic scenes for the near field's sign tests and benchmark (not collected: no ``test_``
prefix): a sphere, smooth or with bumps, half in the shadow of a straight plate edge under a
point or directional light, so the shadow curve crosses a curved surface at every angle of
incidence down to grazing, and (with bumps) wiggles between the irradiance points.

Built with the same pieces as the knife edge (tests/test_knife_edge.py): the pipeline's own
points, irradiance with entry transmittance, layer profile and :func:`exitance.exitance`.
:func:`recording` captures the near-field terms exitance() computes, :func:`near_parts`
recomputes their pieces C(x), V(x), s(x) from the arguments (shared with
bench/bench_near_field_consistency.py).
"""
from __future__ import annotations

import contextlib

import numpy as np

from dermis.lighting.irradiance import irradiance
from dermis.lighting.visibility import Visibility
from dermis.optics.transmittance import Transmittance
from dermis.pipeline.config import BssrdfConfig, LightConfig
from dermis.subsurface import points as S
from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance
from render_fixtures import icosphere


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bumpy_sphere(radius: float, subdivisions: int, bump_mm: float, seed: int):
    """Icosphere with radial bumps: the sum of 12 random plane waves of wavelength 2-6 mm
    scaled so the displacement's largest magnitude is ``bump_mm`` (0: the plain sphere).
    Returns (vertices, faces, unit angle-weighted vertex normals)."""
    from dermis.geometry.normals import angle_weighted_normals
    m = icosphere(radius, subdivisions)
    v = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64)
    if bump_mm > 0:
        rng = np.random.default_rng(seed)
        k = _unit(rng.normal(size=(12, 3))) * (2 * np.pi / rng.uniform(2.0, 6.0, 12))[:, None]
        h = np.sin(v @ k.T + rng.uniform(0, 2 * np.pi, 12)).sum(axis=1)
        v = v + (bump_mm * h / np.abs(h).max())[:, None] * _unit(v)
    return v, f, _unit(angle_weighted_normals(v, f).astype(np.float64))


def surface_queries(v, f, vn, count: int, rng, keep=None):
    """``count`` uniform random surface points (area-weighted triangles, uniform barycentric)
    with their interpolated shading normals and geometric normals; ``keep(positions)`` (bool)
    restricts them to a region (drawn until ``count`` are kept)."""
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    cr = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    out = [[], [], []]
    have = 0
    while have < count:
        t = rng.choice(len(f), 4 * count, p=area / area.sum())
        a, b = rng.random((2, 4 * count))
        flip = a + b > 1
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        w = np.stack([1 - a - b, a, b], axis=1)
        p = (v[f[t]] * w[..., None]).sum(axis=1)
        sel = np.ones(len(p), bool) if keep is None else keep(p)
        ns = _unit((vn[f[t]] * w[..., None]).sum(axis=1))
        ng = _unit(cr[t])
        for lst, arr in zip(out, (p, ns, ng)):
            lst.append(arr[sel])
        have += int(sel.sum())
    return tuple(np.concatenate(lst)[:count] for lst in out)


def shadowed_sphere(prof, stack, *, light: str = "directional", elevation_deg: float = 40.0,
                    edge_mm: float = 0.0, bump_mm: float = 0.0, radius: float = 20.0,
                    subdivisions: int = 6, density: float | None = None, queries: int = 20000,
                    seed: int = 1) -> dict:
    """A sphere of ``radius`` mm at the origin, lit from azimuth +x at ``elevation_deg``
    (directional, or a point light 1 m away in that direction), and a plate at height
    1.5 ``radius`` between the sphere and the light whose straight edge (along y) throws a
    curved shadow across the sphere's lit side, through (``edge_mm``, 0, ``radius``) on the
    bare sphere.  Points at the scene's point density (``density``
    overrides it), their irradiance with entry transmittance, and ``queries`` random surface
    points on the sphere's upper half (the lit side, the shadow, the terminator)."""
    cfg = BssrdfConfig()
    rng = np.random.default_rng(seed)
    v, f, vn = bumpy_sphere(radius, subdivisions, bump_mm, seed)
    spacing = S.spacing_from_mfp(stack, cfg.point_density if density is None else density)
    pts = S.sample_points(v, f, spacing_mm=spacing, seed=seed, vertex_normals=vn)
    el = np.radians(elevation_deg)
    z, half = 1.5 * radius, 8.0 * radius
    x0 = edge_mm + 0.5 * radius / np.tan(el)     # shades x > x0 at height z
    plate = np.array([[x0, -half, z], [x0 + half, -half, z], [x0 + half, half, z],
                      [x0, half, z]])
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    vis = Visibility(np.vstack([v, plate]), np.vstack([f, tri + len(v)]))
    to_light = np.array([np.cos(el), 0.0, np.sin(el)])
    if light == "directional":
        lc = LightConfig(name="sun", type="directional", direction=tuple(to_light),
                         intensity=(1.5, 1.5, 1.5))
    else:
        lc = LightConfig(name="lamp", type="point", position=tuple(1000.0 * to_light),
                         intensity=(1.5e6, 1.5e6, 1.5e6))
    eta = stack.layers[0].eta / stack.eta_above
    transmit = Transmittance(eta, cfg.surface_reflection)
    E = irradiance(pts.positions, pts.normals, [lc], vis.occluded, transmittance=transmit)
    q, ns, ng = surface_queries(v, f, vn, queries, rng, keep=lambda p: p[:, 2] > 0)
    return {"pts": pts, "E": E, "q": q, "ns": ns, "ng": ng, "vis": vis, "light": lc,
            "transmit": transmit, "spacing": spacing, "mesh": (v, f)}


def scene_exitance(sc, prof, cl_env, *, shared=None):
    """exitance() at the scene's queries at the shipped settings (the shadow rays of the
    queries traced here, as the pipeline's shared visibility traces them)."""
    cfg = BssrdfConfig()
    options = ExitanceOptions(epsilon=cfg.epsilon, transmittance=sc["transmit"],
                              leaf_size=cfg.leaf_size, env=cl_env)
    return exitance(sc["pts"], sc["E"], prof, ShadingPoints(sc["q"], sc["ns"], sc["ng"]),
                    lights=[sc["light"]], visibility=sc["vis"], options=options, shared=shared)


def near_parts(call: dict, env) -> dict:
    """C(x), V(x), s(x) and the bracket Rd_near V - s of one sharp_near_field call, computed
    from its arguments the way subsurface/shadow_edges.py defines them."""
    from dermis.lighting.emitters import sample_lights
    from dermis.subsurface import shadow_edges as SE
    x = np.asarray(call["queries"], np.float32)
    ns = SE._unit(np.asarray(call["shading_normals"], np.float64))
    ng = np.asarray(call["geo_normals"], np.float32)
    light, ed, table = call["light"], call["edges"], call["table"]
    ls = sample_lights(light, x, ng)
    wi, wt, dist = ls.directions[:, 0], ls.weights[:, 0].astype(np.float64), ls.distance[:, 0]
    cos = np.einsum("ij,ij->i", wi, ns)
    live = (cos > 0) & (wt.sum(axis=1) > 0)
    c = np.zeros((len(x), 3))
    c[live] = wt[live] * cos[live, None]
    if call.get("transmittance") is not None:
        c[live] *= np.asarray(call["transmittance"](cos[live]))
    if call.get("visible") is not None:
        vis = np.asarray(call["visible"], bool).copy()
    else:
        vis = np.zeros(len(x), bool)
        vis[live] = ~call["visibility"].occluded(x[live], ng[live], wi[live], dist[live])
    s = SE.edge_sum_cl(x, ns, ed, table, env)
    s = s[0] if isinstance(s, tuple) else s      # checkouts whose edge sums also return a side
    bracket = table.rd_near[None, :] * vis[:, None] - s
    return {"c": c, "live": live, "visible": vis, "s": s, "bracket": bracket,
            "rd_near": np.asarray(table.rd_near, np.float64)}


@contextlib.contextmanager
def recording():
    """Wrap ``sharp_near_field`` where exitance() calls it, and the bssrdf stage's ``run``;
    yields (calls, images): the (arguments, returned near term) of every near-field call
    and each rendered image (node label -> linear image)."""
    import dermis.stages.bssrdf as B
    import dermis.subsurface.exitance as X
    calls, images = [], {}
    orig, orig_run = X.sharp_near_field, B.run
    names = ("queries", "shading_normals", "geo_normals", "light", "visibility", "edges",
             "table")

    def wrapped(*args, **kw):
        out = orig(*args, **kw)
        calls.append(({**dict(zip(names, args)), **kw}, out))
        return out

    def run(params, inputs, ctx):
        res = orig_run(params, inputs, ctx)
        images[f"{params.get('model', 'bssrdf')}-{params['label']}-{params['geometry']}"] = (
            np.asarray(res.artifact.linear, np.float64))
        return res
    X.sharp_near_field, B.run = wrapped, run
    try:
        yield calls, images
    finally:
        X.sharp_near_field, B.run = orig, orig_run
