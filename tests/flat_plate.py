"""A flat plate of skin under a directional light and under a uniform sky: every model's
exitance from its own code, the exact plane-parallel transport of the stack, and the path
tracer's textured plate as the reference stage exports it (tests/test_convention.py,
bench/bench_convention.py; the albedo convention of docs/ground-truth.md).

Exitance is per unit irradiance (directional: of the beam on the plate, E = cos theta; sky:
E = pi L) and integrated over the outgoing hemisphere.  "The albedo part" of a plate is its
exitance at texture albedo a minus its exitance at albedo 0, which is what the texture
controls; the rest (the surface's own reflection) is each model's surface term.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

from dermis.optics.layers import LayerStack
from dermis.pipeline import registry

# Outgoing directions of the BRDFs' exitance quadrature: Gauss-Legendre in cos theta_o x
# midpoints in phi, the grid of tests/test_energy.py (QUAD), which agrees with a 1500 x 1500
# midpoint grid to 3e-5 on the Lafortune lobes.
QUAD = (96, 192)
# Incident cosines of the uniform sky's average (Gauss-Legendre): 16 nodes agree with 32 to
# < 1e-5 on every model here.
SKY_NODES = 16


def sky_nodes() -> tuple[np.ndarray, np.ndarray]:
    """Incident cosines mu and weights w with sum w f(mu) = int f(mu) 2 mu dmu."""
    x, w = np.polynomial.legendre.leggauss(SKY_NODES)
    mu = 0.5 * (x + 1.0)
    return mu, w * mu


# --------------------------------------------------------------------------- the BRDF models
def _outgoing() -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(QUAD[0])
    mu, wmu = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(QUAD[1]) + 0.5) / QUAD[1] * 2.0 * np.pi
    m, p = (a.ravel() for a in np.meshgrid(mu, phi, indexing="ij"))
    s = np.sqrt(1.0 - m * m)
    wo = np.stack([s * np.cos(p), s * np.sin(p), m], axis=1).astype(np.float32)
    return wo, np.repeat(wmu, QUAD[1]) * (2.0 * np.pi / QUAD[1]) * m      # cos_o dw_o


def composed(name: str, stack: LayerStack, asperity_base: str = "lambert"):
    """(defines, base block, term block, albedo -> what cl/shade.cl reads) of model ``name``
    as the render stage composes it (``Model.scene_params``, the base under a term,
    ``Model.shade_albedo``)."""
    m = registry.model(name)
    scene = {"optics": stack.to_dict(), "asperity_base": asperity_base}
    params = m.scene_params(scene, None)
    if m.bases:
        base, term_params = m.base(asperity_base), params
        bparams = base.scene_params(scene, None)
    else:
        base, term_params, bparams = m, None, params
    defines = {"DERMIS_BASE": 0, "DERMIS_ASPERITY": 0, **dict(base.shade),
               **(dict(m.shade) if m.bases else {})}
    bblock = bparams.pack() if bparams is not None else np.zeros(4, np.float32)
    ablock = term_params.pack() if term_params is not None else np.zeros(8, np.float32)

    def albedo(a):
        a = np.asarray(a, np.float32)
        return base.shade_albedo(bparams, a, True) if base.shade_albedo else a
    return defines, bblock, ablock, albedo


def brdf_exitance(cl_env, name: str, stack: LayerStack, albedo, cos_in) -> np.ndarray:
    """(len(cos_in), 3) exitance per unit irradiance of BRDF model ``name`` (as rendered,
    :func:`composed`) under a directional light at each incident cosine, for texture albedo
    ``albedo`` (3,) linear: int f(wo, wi) cos_o dw_o through ``cl/shade.cl``."""
    import pyopencl as cl
    from dermis.pipeline.cl import to_device
    defines, bblock, ablock, shade_albedo = composed(name, stack)
    wo, cos_dw = _outgoing()
    ci = np.asarray(cos_in, np.float64)
    n, k = len(wo), len(ci)
    wi = np.stack([np.sqrt(1.0 - ci * ci), np.zeros_like(ci), ci], 1).astype(np.float32)
    total = n * k
    alb = np.tile(shade_albedo(np.asarray(albedo, np.float32)[None, :]), (total, 1))
    knl = cl.Kernel(cl_env.program("shade.cl", defines), "shade_samples")
    out = np.empty((total, 3), np.float32)
    d_out = cl.Buffer(cl_env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    args = [np.arange(total, dtype=np.int32), np.repeat(wi, n, axis=0),
            np.ones((total, 3), np.float32)]
    knl(cl_env.queue, (total,), None, *(to_device(cl_env, a) for a in args), np.int32(total),
        to_device(cl_env, np.tile(np.float32([0.0, 0.0, 1.0]), (total, 1))),
        to_device(cl_env, np.tile(wo, (k, 1))), to_device(cl_env, alb),
        to_device(cl_env, bblock), to_device(cl_env, ablock),
        to_device(cl_env, np.ones(1, np.uint8)), np.int32(0), d_out, d_out,
        np.int32(0))   # no flags: every lit; no control term
    cl.enqueue_copy(cl_env.queue, out, d_out)
    # out = f cos_i W (W = 1: unit beam); per unit irradiance E = cos_i
    return (out.reshape(k, n, 3).astype(np.float64) * cos_dw[None, :, None]).sum(1) / ci[:, None]


def brdf_plate(cl_env, name: str, stack: LayerStack, albedo) -> dict:
    """{"normal", "oblique" (60 deg), "sky"}: (3,) exitance per unit irradiance of BRDF
    model ``name`` at texture albedo ``albedo``."""
    mu, w = sky_nodes()
    got = brdf_exitance(cl_env, name, stack, albedo, np.concatenate([[1.0, 0.5], mu]))
    return {"normal": got[0], "oblique": got[1], "sky": (got[2:] * w[:, None]).sum(0)}


# --------------------------------------------------------------------------- the BSSRDF
def bssrdf_plate(cl_env, stack: LayerStack, albedos, *, n_query: int = 200) -> dict:
    """{"normal", "oblique", "sky"}: (len(albedos), 3) exitance per unit irradiance of the
    BSSRDF at each texture albedo through its own path: irradiance points on a plate wider
    than the profile's reach, their entering irradiance (the irradiance pass with the entry
    transmittance under the directional light; under the sky its expectation pi L T_mean,
    which the pass's 64 samples per point estimate without bias), the exitance gather
    (near field included) at queries beyond the reach from the border, the exit to radiance
    (``albedo_mode = "replace"``) integrated over the hemisphere, plus the surface term
    (Lafortune's lobes, rho_d = 0, through cl/shade.cl as the BSSRDF stage renders it).
    The profile is the layer file on hk93.RD_GRID's coarse radial grid: its totals are the
    profiles stage's exactly (models/hk93.py), and a uniform plate reads only its totals
    (the near field integrates it at each shading point)."""
    from dermis.lighting.irradiance import irradiance
    from dermis.models.hk93 import RD_GRID
    from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
    from dermis.optics.transmittance import Transmittance
    from dermis.pipeline.config import BssrdfConfig, LightConfig
    from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance
    from dermis.subsurface.radiance import exitance_to_radiance
    cfg = BssrdfConfig()
    prof = build_profiles(stack, options=MultipoleOptions(grid=RD_GRID))
    plate = flat_points(stack, prof, cfg)
    sp, vis, reach, half = plate.points, plate.visibility, plate.reach, plate.half
    eta = stack.layers[0].eta / stack.eta_above
    t = Transmittance(eta, cfg.surface_reflection)
    inner = half - reach - 1.0
    q = np.zeros((n_query, 3))
    q[:, :2] = np.random.default_rng(5).uniform(-inner, inner, (n_query, 2))
    nrm = np.tile([0.0, 0.0, 1.0], (n_query, 1))
    x, w = np.polynomial.legendre.leggauss(64)
    c_out, w_out = 0.5 * (x + 1.0), 0.5 * w
    lobes = brdf_plate(cl_env, "lafortune", stack, np.zeros(3))
    out = {}
    for kind, theta in (("normal", 0.0), ("oblique", 60.0), ("sky", None)):
        if theta is None:
            light = LightConfig(name="sky", type="environment", map="procedural_sunset",
                                samples=cfg.irradiance_samples)
            E = np.broadcast_to(math.pi * np.asarray(t.mean, np.float32),
                                (len(sp.positions), 3)).astype(np.float32)
            e_on = math.pi
        else:
            d = (math.sin(math.radians(theta)), 0.0, math.cos(math.radians(theta)))
            light = LightConfig(name="d", type="directional", direction=d,
                                intensity=(1.0, 1.0, 1.0))
            E = irradiance(sp.positions, sp.normals, [light], vis.occluded, transmittance=t)
            e_on = d[2]
        M, _ = exitance(sp, E, prof, ShadingPoints(q, nrm, nrm), lights=[light],
                        visibility=vis, options=ExitanceOptions(
                            epsilon=cfg.epsilon, transmittance=t, env=cl_env))
        rows = []
        for a in albedos:
            a = np.broadcast_to(np.asarray(a, np.float64), M.shape)
            L = np.stack([exitance_to_radiance(M, np.full(len(M), c), eta, albedo=a,
                                               albedo_mode="replace", rd=prof.Rd,
                                               transmittance=t) for c in c_out])
            sub = (L.astype(np.float64) * (2 * np.pi * c_out * w_out)[:, None, None]).sum(0)
            rows.append(sub.mean(axis=0) / e_on + lobes[kind])
        out[kind] = np.array(rows)
    return out


# --------------------------------------------------------------------------- exact transport
def exact_albedo_part(stack: LayerStack) -> dict:
    """{"normal", "sky"}: (3,) the albedo part per unit albedo of a plate of ``stack`` behind a
    smooth Fresnel boundary under the albedo convention (texture a = reflectance per
    entered flux at normal incidence), from the exact plane-parallel transport
    (adding-doubling, optics/adding_doubling.py): at normal incidence 1 - F(1); under the
    uniform sky the subsurface reflectance per unit irradiance over the normal-incidence
    reflectance per entered flux.  The sky's light enters along every refracted direction
    inside the critical cone, flux L eta^2 (1 - F) mu dw per internal solid angle.  The
    layers must share one index (no interface between them: the transport's own
    restriction, :func:`dermis.optics.adding_doubling.exact_totals`)."""
    from dermis.optics import adding_doubling as ad
    from dermis.optics.fresnel import fresnel_reflectance_inside
    if len({l.eta for l in stack.layers}) != 1:
        raise ValueError("exact_albedo_part: the layers must share one index")
    eta = stack.layers[0].eta / stack.eta_above
    normal, sky = [], []
    for c in range(3):
        S, n, cuts = ad._ad_layers(stack, c)
        mu, w = ad._ad_quadrature(n, cuts)
        f_top = fresnel_reflectance_inside(mu, eta)
        f_bot = fresnel_reflectance_inside(mu, stack.layers[-1].eta / stack.eta_below)
        beam = np.zeros(len(mu))
        beam[-1] = 1.0                                   # the node at mu = 1
        rd0, _ = ad._ad_bounded(S, f_top, f_bot, beam)   # per entered flux, normal incidence
        inside = mu > math.sqrt(max(0.0, 1.0 - 1.0 / eta ** 2))
        flux = np.where(inside, eta ** 2 * (1.0 - f_top) * mu * w * 2.0, 0.0)   # E = pi L = 1
        rsky, _ = ad._ad_bounded(S, f_top, f_bot, flux)
        t1 = 1.0 - float(fresnel_reflectance_inside(np.array([1.0]), eta)[0])
        normal.append(t1)
        sky.append(rsky / rd0)
    return {"normal": np.array(normal), "sky": np.array(sky)}


# --------------------------------------------------------------------------- the path tracer
PLATE_HALF_MM = 60.0
# Texture patches (sRGB bytes), top third to bottom third of the texture (v from 1 to 0:
# y > 20, |y| < 20, y < -20 mm on the plate), and where their centres lie: 20 mm from every
# border, > 14 diffusion lengths of the two-layer skin's reddest channel (1 / sigma_tr =
# 1.4 mm), so no path of one patch's light reaches another's meter in practice.
PATCHES = {"A": (200, 150, 130), "B": (120, 80, 70), "0": (0, 0, 0)}
CENTRES = {"A": (0.0, 40.0, 0.0), "B": (0.0, 0.0, 0.0), "0": (0.0, -40.0, 0.0)}
TEXTURE_PX = 60


def patch_albedo(name: str) -> np.ndarray:
    """(3,) linear albedo of a texture patch (the exporter's sRGB decoding)."""
    from dermis.rendering.color import srgb_to_linear
    return srgb_to_linear(np.asarray(PATCHES[name], np.float32) / 255.0).astype(np.float64)


def plate_mesh():
    """The textured plate: two triangles at z = 0 (normal +z), 120 mm wide, UVs over the
    whole texture, three horizontal patches (:data:`PATCHES`)."""
    from dermis.pipeline.artifacts import Mesh
    h = PLATE_HALF_MM
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    uv = ((v[:, :2] + h) / (2 * h)).astype(np.float32)
    tex = np.zeros((TEXTURE_PX, TEXTURE_PX, 3), np.uint8)   # row 0: the top, v = 1, +y
    third = TEXTURE_PX // 3
    for k, name in enumerate(("A", "B", "0")):
        tex[k * third:(k + 1) * third] = PATCHES[name]
    return Mesh(v, f, None, uv, f.copy(), tex)


def with_meters(mi, scene_dict: dict) -> dict:
    """A head scene dictionary with its lights and camera replaced by the unit sky, a
    radiance meter looking straight down at each patch centre (``rad_<patch>``: by
    reciprocity the exitance under a normally incident directional light) and an irradiance
    meter just above it (``irr_<patch>``: the exitance under the sky, times pi)."""
    from dermis.groundtruth.slab import irradiance_meter, radiance_meter, uniform_sky
    d = {k: v for k, v in scene_dict.items() if not k.startswith("light_") and k != "sensor"}
    d["sky"] = uniform_sky()
    for p, c in CENTRES.items():
        d[f"rad_{p}"] = radiance_meter(c, 0.0)
        d[f"meter_{p}"] = irradiance_meter(mi, f"irr_{p}", c)
    return d


def keep_files(scene_dict: dict, folder: Path) -> dict:
    """The dictionary with every PLY it names copied into ``folder`` (the exporter deletes
    its own temporary folder when loading fails or the scene is released)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for k, v in scene_dict.items():
        if isinstance(v, dict) and v.get("type") == "ply":
            src = Path(v["filename"])
            dst = folder / f"{k}-{src.name}"
            shutil.copyfile(src, dst)
            v = dict(v, filename=str(dst))
        out[k] = v
    return out


def flat_points(stack, prof, cfg):
    """A square plate in z = 0 wider than the profile's reach plus the points' blur, with its
    irradiance points at the scene density (``cfg`` a BssrdfConfig) and its ray caster:
    a namespace of vertices, faces, points, visibility, spacing, reach and half (its
    half-width), mm."""
    from types import SimpleNamespace
    from dermis.lighting.visibility import Visibility
    from dermis.subsurface import points as S
    from dermis.subsurface.profile_table import BLUR_REACH
    spacing = S.spacing_from_mfp(stack, cfg.point_density)
    reach = float(prof.cutoff_mm.max()) + BLUR_REACH * spacing
    half = reach + 2 * spacing + S.POU_RADIUS * spacing
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return SimpleNamespace(vertices=v, faces=f,
                           points=S.sample_points(v, f, spacing_mm=spacing, seed=4),
                           visibility=Visibility(v, f), spacing=spacing, reach=reach, half=half)
