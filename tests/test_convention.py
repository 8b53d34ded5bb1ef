"""The albedo convention: one meaning of the texture, shared by the Mitsuba reference and
every dermis model, measured on a flat textured plate (docs/ground-truth.md).

A texture value a is the reflectance, per unit of flux that crossed the skin's surface at
normal incidence, of the skin below it (the layer file's Rd, which the BSSRDF and HK93
divide the texture by).  The quantity compared is "the albedo part" of a plate's exitance
per unit irradiance: its exitance at albedo a minus its exitance at albedo 0 (what the
texture controls; the rest is each model's surface term).  The plate is the reference
stage's own export (its scene dictionary captured as the stage loads it, with the calibration
slab of this test), textured with three patches (two skin tones and black) 40 mm wide, read
20 mm from every border (> 14 diffusion lengths).  Lights: a directional light at normal
incidence (the path tracer reads it by reciprocity: a radiance meter straight down under a
uniform sky) and the uniform sky itself (an irradiance meter); the models' exitance comes
from their own code (tests/flat_plate.py).

Tolerances: K_SE standard errors of the path tracer (between BATCHES independent renders:
P(|t_15| > 4) = 1.2e-3 per comparison), plus the stated model errors, computed here:
* the model's own departure from the exact transport of the stack behind a smooth boundary
  (tests/flat_plate.py exact_albedo_part: 1 - F(1) at normal incidence; adding-doubling
  under the sky), |S_model - S_exact|, from the model's and the transport's code;
* the reference boundary's own departure from a smooth one (GGX, single scattering):
  at normal incidence (1 - its specular) / (1 - F(1)) - 1, from the plate's black patch;
  under the sky ROUGH_SKY (bench/results/convention.json: the untextured slab, GGX against
  Mitsuba's smooth dielectric, 2^20 paths each).
With the tint normalised by the slab's Rd per incident irradiance instead, the plate's
albedo part is 1 / (1 - specular) = 2.5 % too bright and these checks fail.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flat_plate import (bssrdf_plate, brdf_plate, exact_albedo_part, keep_files,
                        patch_albedo, plate_mesh, with_meters)
from dermis.pipeline.config import load_scene

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "scenes" / "quick.toml"

K_SE = 4.0
BATCHES = 16
# Paths: the calibration slab (the stage's default [reference] slab_samples is 2^18) and the
# plate's patches at normal incidence and under the sky (the irradiance meter's paths cost
# ~2x); the black patch ends every path at the boundary.  Relative standard errors on the
# two-layer skin: calibration ~0.28 %, patch ~0.3 % (normal), ~0.5 % (sky).
CAL_SAMPLES = 1 << 19
NORMAL_SAMPLES = 1 << 18
SKY_SAMPLES = 1 << 17
BLACK_SAMPLES = 1 << 16
# The GGX boundary's albedo part under the uniform sky over a smooth boundary's, both
# normalised at normal incidence (bench/results/convention.json "rough_vs_smooth" "sky",
# two_layer, alpha 0.3, 2^20 paths per reading) and its standard error.
ROUGH_SKY = (1.0081, 1.0168, 1.0250)
ROUGH_SKY_SE = (0.0033, 0.0033, 0.0043)
MODELS = ("lafortune", "hk93", "asperity", "bssrdf")


@pytest.fixture(scope="module")
def scene():
    return load_scene(QUICK, overrides={"reference": {"enabled": True, "width": 40,
                                                      "height": 40}})


class _Captured(Exception):
    """The stage's head scene dictionary was captured (the stage stops there)."""


def _stage_plate_dict(mi, scene, calibration, folder: Path) -> dict:
    """The scene dictionary the reference stage builds for the plate mesh, with the test's
    calibration slab as the run's shared slab: whatever the stage passes as the tint's
    normaliser is what this test measures."""
    from dermis.groundtruth.slab import SLABS
    from dermis.pipeline.api import RunContext
    from dermis.pipeline.shared import RunCache
    from dermis.stages import reference
    label, lights = scene.light_groups()[0]
    node = reference.node(scene, label, lights)
    got, real = {}, mi.load_dict

    def capture(d, *args, **kwargs):
        if "head" in d:
            got["dict"] = keep_files(d, folder)
            raise _Captured
        return real(d, *args, **kwargs)

    class Calibrated(RunCache):
        def get_made(self, kind, key, make):
            return (calibration, False) if kind is SLABS else super().get_made(kind, key, make)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mi, "load_dict", capture)
        with pytest.raises(_Captured):
            reference.run(node.params, {"mesh": plate_mesh()},
                          RunContext(out_dir=folder, shared=Calibrated()))
    return got["dict"]


@pytest.fixture(scope="module")
def plate(mi, scene, tmp_path_factory):
    """The path tracer's plate: per light ("normal", "sky") and patch ("A", "B", "0") the
    exitance per unit irradiance and its standard error, the calibration, the seconds."""
    import time
    from dermis.groundtruth.slab import meter_reading, slab_reflectance
    t0 = time.perf_counter()
    r = scene.reference
    cal = slab_reflectance(mi, scene.optics, roughness=r.roughness, samples=CAL_SAMPLES,
                           batches=BATCHES, seed=3, max_depth=r.max_depth, rr_depth=r.rr_depth)
    d = _stage_plate_dict(mi, scene, cal, tmp_path_factory.mktemp("plate"))
    sc = mi.load_dict(with_meters(mi, d))
    out = {"calibration": cal}
    for light, prefix, n, scale in (("normal", "rad", NORMAL_SAMPLES, 1.0),
                                    ("sky", "irr", SKY_SAMPLES, 1.0 / math.pi)):
        out[light] = {}
        for p in ("A", "B", "0"):
            m, se = meter_reading(mi, sc, f"{prefix}_{p}", samples=BLACK_SAMPLES if p == "0"
                                  else n, batches=BATCHES, seed=5)
            out[light][p] = (m * scale, se * scale)
    out["seconds"] = time.perf_counter() - t0
    return out


def _albedo_part(plate, light, p):
    """(3,) the reference plate's albedo part over the albedo, its (3,) relative standard
    error from the plate's readings (the patch and the black patch) and from the
    calibration's normaliser."""
    (m, se), (m0, se0) = plate[light][p], plate[light]["0"]
    cal = plate["calibration"]
    return (m - m0) / patch_albedo(p), np.hypot(se, se0) / (m - m0), cal.Rd_stderr / cal.Rd


@pytest.fixture(scope="module")
def models(cl_env, scene):
    """Per model and light: (3,) albedo part over the albedo at patches A and B."""
    stack = scene.optics
    albedos = [np.zeros(3), patch_albedo("A"), patch_albedo("B")]
    out = {}
    for name in ("lafortune", "hk93", "asperity"):
        got = [brdf_plate(cl_env, name, stack, a) for a in albedos]
        out[name] = {light: {p: (got[k][light] - got[0][light]) / albedos[k]
                             for k, p in ((1, "A"), (2, "B"))} for light in ("normal", "sky")}
    got = bssrdf_plate(cl_env, stack, albedos)
    out["bssrdf"] = {light: {p: (got[light][k] - got[light][0]) / albedos[k]
                             for k, p in ((1, "A"), (2, "B"))} for light in ("normal", "sky")}
    return out


def test01_normal_incidence_albedo_part_is_the_albedo_per_entered_flux(plate):
    """Under a normally incident light a patch of albedo a reflects a (1 - specular) above
    the black patch: a is per entered flux (the convention), not per incident irradiance
    (which reads 1 / (1 - specular) = 2.5 % brighter)."""
    spec = plate["normal"]["0"][0]
    assert np.allclose(spec, plate["calibration"].specular, rtol=0.05), spec
    for p in ("A", "B"):
        got, rel, rel_cal = _albedo_part(plate, "normal", p)
        rel = np.hypot(rel, rel_cal)
        dev = got / (1.0 - spec) - 1.0
        print(f"normal {p}: albedo part / (1 - specular) - 1 = {np.round(100 * dev, 2)} % "
              f"({K_SE:g} standard errors {np.round(100 * K_SE * rel, 2)} %)")
        assert np.all(np.abs(dev) <= K_SE * rel), (p, dev, rel)
        # the check can fail: the albedo per incident irradiance (albedo part 1) is outside it
        assert np.all(np.abs(got - 1.0) > K_SE * rel), (p, got, rel)


def test02_the_texture_is_read_patch_by_patch(plate):
    """Both skin patches give the same albedo part per unit albedo under both lights: the
    tint reaches each patch (v flipped, bilinear within a texel of the borders only) and is
    linear in the albedo (sqrt at each of the two crossings)."""
    for light in ("normal", "sky"):
        (a, ra, _), (b, rb, _) = (_albedo_part(plate, light, p) for p in ("A", "B"))
        rel = np.hypot(ra, rb)          # the calibration's normaliser is common to both
        print(f"{light}: A / B - 1 = {np.round(100 * (a / b - 1), 2)} % "
              f"({K_SE:g} standard errors {np.round(100 * K_SE * rel, 2)} %)")
        assert np.all(np.abs(a / b - 1.0) <= K_SE * rel), (light, a / b - 1.0, rel)


def test03_sky_albedo_part_is_the_exact_transport(plate, scene):
    """Under the uniform sky the albedo part per unit albedo is the exact plane-parallel
    transport's under the same convention (adding-doubling, smooth boundary: it reflects
    1.9 / 4.4 / 5.5 % more per entered flux than at normal incidence) times the GGX
    boundary's own factor (ROUGH_SKY, measured on the untextured slab)."""
    exact = exact_albedo_part(scene.optics)["sky"] * np.asarray(ROUGH_SKY)
    for p in ("A", "B"):
        got, rel, rel_cal = _albedo_part(plate, "sky", p)
        tol = K_SE * np.sqrt(rel ** 2 + rel_cal ** 2
                             + (np.asarray(ROUGH_SKY_SE) / np.asarray(ROUGH_SKY)) ** 2)
        print(f"sky {p}: albedo part / exact - 1 = {np.round(100 * (got / exact - 1), 2)} % "
              f"(tolerance {np.round(100 * tol, 2)} %)")
        assert np.all(np.abs(got / exact - 1.0) <= tol), (p, got / exact - 1.0, tol)


@pytest.mark.parametrize("model", MODELS)
def test04_every_model_agrees_with_the_reference(plate, models, scene, model):
    """Each model's albedo part equals the reference's within K_SE standard errors plus the
    stated model errors (module docstring): the model's own departure from the exact
    transport behind a smooth boundary and the reference boundary's from a smooth one."""
    exact = exact_albedo_part(scene.optics)
    spec = plate["normal"]["0"][0]
    # the reference boundary's departure from a smooth one, with what its estimate may miss
    boundary = {"normal": np.abs((1.0 - spec) / exact["normal"] - 1.0),
                "sky": np.abs(np.asarray(ROUGH_SKY) - 1.0) + K_SE * np.asarray(ROUGH_SKY_SE)}
    rows = []
    for light in ("normal", "sky"):
        for p in ("A", "B"):
            ref, rel, rel_cal = _albedo_part(plate, light, p)
            mine = models[model][light][p]
            stated = np.abs(mine - exact[light]) + exact[light] * boundary[light]
            noise = K_SE * np.hypot(rel, rel_cal) * ref
            rows.append((light, p, mine / ref - 1.0, stated / ref, noise / ref))
            assert np.all(np.abs(ref - mine) <= noise + stated), \
                (model, light, p, mine, ref, stated, noise)
    # the measured agreement, shown with -rA
    for light, p, dev, stated, noise in rows:
        pct = lambda x: np.round(100 * x, 2)   # noqa: E731
        print(f"{model} {light} {p}: model / reference - 1 = {pct(dev)} %, stated model "
              f"error {pct(stated)} %, {K_SE:g} standard errors {pct(noise)} %")
