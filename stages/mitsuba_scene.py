"""A dermis scene as a Mitsuba 3 scene: the path-traced ground truth's export and renders.

Mitsuba 3 (``pip install dermis[reference]``) path-traces light inside participating media
exactly; it has no diffusion BSSRDF.  This module turns dermis's mesh, camera, lights and
layer stack into a Mitsuba scene dictionary and renders it (docs/ground-truth.md):

* **Mesh** in mm (Mitsuba works in the scene's units; every coefficient is in 1/mm, so the
  unit factor is 1: ground-truth.md trap 1).  Vertices are split where per-corner UVs
  differ (Mitsuba's UVs are per vertex), the vertex normals are dermis's own
  (:meth:`Mesh.vertex_normals`, angle-weighted), and v is flipped: dermis's UV origin is the
  bottom-left (docs/science.md conventions), Mitsuba's bitmap origin the top-left (measured).
  The mesh is written as a binary PLY into a temporary folder.
* **Camera**: ``perspective`` with ``fov_axis = "smaller"`` (pbrt's and dermis's
  convention), ``look_at`` as in :func:`stages.render.camera_rays`; box pixel filter, so a
  reference pixel is the average over its footprint.  Its pixel-centre rays are the same
  rays as dermis's (``pixel_hits``; tests/test_reference.py).
* **Lights**: ``point`` (intensity I in W/sr); ``directional`` (Mitsuba's direction is the
  one light travels, dermis's points towards the light; ``irradiance`` = E); the disc as a
  ``disk`` shape with an ``area`` emitter of radiance I / (pi r^2), its normal turned to
  face the mesh (dermis's disc emits from both faces; the face turned away lights nothing
  the camera sees); the environment map as ``envmap`` with dermis's radiance array
  (:func:`lighting.lights.environment_map`, the same map, scale and clamping as every
  model), no rotation needed at ``rotation_deg = 0`` (Mitsuba's lat-long convention equals
  dermis's: centre along +z, u growing towards -x, measured) and ``rotate(+y, -rotation_deg)``
  otherwise.
* **Skin**: a ``roughdielectric`` boundary (GGX, alpha ``roughness``) with the stack's
  relative index; inside it the layer stack as homogeneous media with sigma_s =
  sigma_s' / (1 - g), sigma_a and a Henyey-Greenstein phase function of mean cosine g,
  exactly as the Monte Carlo slab and HK93 use them.  Medium colours are sigma_t / max
  sigma_t with ``scale`` = max sigma_t (trap 1).  A finite layer k is the shell between
  the surface offset inwards by the thickness of the layers above it and the surface offset
  by that plus its own thickness (vertex normals); index-matched interfaces are ``null``
  BSDFs, others rough dielectrics.  The media do not sample emitters (trap 6: a shadow ray
  from inside a closed boundary is always blocked).
* **Albedo texture**: a tint of the boundary's transmission, t = sqrt(albedo / Rd) per
  crossing (``specular_transmittance``), with Rd the path tracer's own total diffuse
  reflectance of the stack (:func:`slab_reflectance`).  A path that enters at x and leaves
  at y carries t(x) t(y), so a flat patch of uniform albedo a reflects exactly a: the texture
  reads as total diffuse reflectance, as in every dermis model (docs/ground-truth.md).
* **Integrator**: ``volpathmis`` (trap 4: spectral MIS), ``max_depth = -1`` with Russian
  roulette (trap 7), emitters hidden from camera rays (dermis's background is black).

Variant: :func:`load_mitsuba` picks ``cuda_ad_rgb`` where a CUDA device answers, else
``llvm_ad_rgb`` where libLLVM is found (Debian's ``libllvm19``; ``DRJIT_LIBLLVM_PATH`` is set
to it when unset) and its JIT works on this CPU (checked in a child process, since a failing
LLVM aborts the process), else Mitsuba counts as unavailable.  ``scalar_rgb`` is not offered:
the scene export and readback here use Dr.Jit arrays of many lanes (``pixel_hits``, the
wavefront renders), which the scalar variant lacks, and one path at a time would take hours.
"""
from __future__ import annotations

import glob
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from dermis.pipeline.errors import ConfigError, DermisError

__all__ = ["MitsubaUnavailable", "load_mitsuba", "mitsuba_missing_reason", "VARIANTS",
           "unweld", "write_ply", "offset_surface", "camera_dict", "light_dicts",
           "medium_dict", "head_scene", "render_passes", "pixel_hits", "slab_reflectance",
           "SlabResult", "tint_texture", "INSTALL_HINT", "MAX_LANES"]

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
INSTALL_HINT = ("pip install 'dermis[reference]' (mitsuba, drjit, flip-evaluator); without a "
                "CUDA device also apt-get install libllvm19 (the llvm_ad_rgb variant)")
# Samples traced by one render call (wavefront size): bounds the LLVM variant's memory at a
# few GB (measured ~0.5 kB per lane for volpathmis in skin).
MAX_LANES = 1 << 21


class MitsubaUnavailable(DermisError):
    """Mitsuba 3 is not installed (or no variant loads): the reference stage cannot run."""


_STATE: dict = {}


def mitsuba_missing_reason() -> str | None:
    """None if ``import mitsuba`` works, else one sentence saying what to install."""
    try:
        import importlib.util
        if importlib.util.find_spec("mitsuba") is None or importlib.util.find_spec("drjit") is None:
            return f"Mitsuba 3 is not installed: {INSTALL_HINT}"
    except (ImportError, ValueError):
        return f"Mitsuba 3 is not installed: {INSTALL_HINT}"
    return None


def _find_libllvm() -> str | None:
    pats = ["/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
            "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"]
    found = sorted({p for pat in pats for p in glob.glob(pat)}, reverse=True)
    # drjit needs LLVM >= 11; prefer the newest (names sort by version)
    return found[0] if found else None


def load_mitsuba(variant: str = "auto"):
    """Import Mitsuba and set a variant; returns the ``mitsuba`` module (``.variant()`` says which).

    ``variant = "auto"`` tries :data:`VARIANTS` in order and keeps the first that renders a
    one-pixel test scene.  Raises :class:`MitsubaUnavailable` with the install command.
    """
    reason = mitsuba_missing_reason()
    if reason:
        raise MitsubaUnavailable(reason)
    if "DRJIT_LIBLLVM_PATH" not in os.environ and "drjit" not in _STATE:
        lib = _find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import drjit  # noqa: F401
    import mitsuba as mi
    _STATE["drjit"] = True
    if variant != "auto":
        if variant not in mi.variants():
            raise ConfigError(f"reference.variant = {variant!r}: not one of this Mitsuba's "
                              f"variants ({', '.join(mi.variants())})")
        broken = _llvm_jit_fails(variant) if variant.startswith("llvm") else None
        if broken:
            raise MitsubaUnavailable(f"reference.variant = {variant!r}: {broken}")
        mi.set_variant(variant)
        return mi
    if _STATE.get("auto"):
        mi.set_variant(_STATE["auto"])
        return mi
    errors = []
    for v in VARIANTS:
        if v not in mi.variants():
            continue
        if v.startswith("cuda") and not _has_backend("CUDA"):
            errors.append(f"{v}: no CUDA device")
            continue
        if v.startswith("llvm"):
            broken = _llvm_jit_fails(v)
            if broken:
                errors.append(f"{v}: {broken}")
                continue
        try:
            mi.set_variant(v)
            scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "sensor": {
                "type": "perspective", "film": {"type": "hdrfilm", "width": 1, "height": 1}}})
            mi.render(scene, spp=1)
            _STATE["auto"] = v
            return mi
        except Exception as exc:  # no CUDA device, no libLLVM: try the next one
            errors.append(f"{v}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
    raise MitsubaUnavailable("no Mitsuba variant could render (" + "; ".join(errors) + "); "
                             + INSTALL_HINT)


# Run in a child process before the LLVM variant is used here: an LLVM that cannot compile
# Dr.Jit's code for this CPU aborts the whole process ("LLVM ERROR: Cannot select ... fmaximum":
# Debian 12's libLLVM-15 on an AVX-512 host, where drjit's dr.maximum became llvm.maximum;
# libllvm19 compiles it).  The child evaluates that operation and renders one pixel.
_LLVM_PROBE = """
import drjit as dr, mitsuba as mi
mi.set_variant({variant!r})
x = dr.maximum(dr.arange(mi.Float, 64) - 3.0, 0.0) + dr.minimum(dr.arange(mi.Float, 64), 2.0)
dr.eval(x)
mi.render(mi.load_dict({{"type": "scene", "integrator": {{"type": "path"}}, "sensor": {{
    "type": "perspective", "film": {{"type": "hdrfilm", "width": 1, "height": 1}}}}}}), spp=1)
"""


def _llvm_jit_fails(variant: str) -> str | None:
    """None if ``variant`` compiles and runs in a child process, else why not (one line);
    probed once per process and libLLVM."""
    key = ("llvm_probe", variant, os.environ.get("DRJIT_LIBLLVM_PATH"))
    if key not in _STATE:
        _STATE[key] = _probe_llvm(variant)
    return _STATE[key]


def _probe_llvm(variant: str) -> str | None:
    import subprocess
    import sys
    try:
        child = subprocess.run([sys.executable, "-c", _LLVM_PROBE.format(variant=variant)],
                               capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"the LLVM JIT probe did not finish ({type(exc).__name__})"
    if child.returncode == 0:
        return None
    lines = [ln for ln in child.stderr.splitlines() if ln.strip()]
    first = next((ln for ln in lines if "ERROR" in ln or "Error" in ln), lines[-1] if lines else "")
    return (f"the LLVM JIT fails on this CPU with {os.environ.get('DRJIT_LIBLLVM_PATH', 'libLLVM')}"
            f" (exit {child.returncode}: {first[:160]}); apt-get install libllvm19")


def _has_backend(name: str) -> bool:
    import drjit as dr
    try:
        return bool(dr.has_backend(getattr(dr.JitBackend, name)))
    except Exception:
        return False


# --------------------------------------------------------------------------- mesh
def unweld(vertices, faces, normals, uv=None, uv_faces=None):
    """Per-vertex attributes from per-corner UVs: vertices split where their corners' UVs differ.

    Returns (V', 3) float32 positions, (F, 3) int32 faces (same order as ``faces``, so a
    Mitsuba primitive index is a dermis face index), (V', 3) float32 normals and (V', 2)
    float32 Mitsuba UVs (v flipped, module docstring) or None.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = np.asarray(normals, dtype=np.float32)
    if uv is None or uv_faces is None:
        return v.astype(np.float32), f.astype(np.int32), n, None
    uvf = np.asarray(uv_faces, dtype=np.int64)
    t = np.asarray(uv, dtype=np.float32)
    key = f.ravel() * len(t) + uvf.ravel()
    uniq, inverse = np.unique(key, return_inverse=True)
    vi, ti = uniq // len(t), uniq % len(t)
    uv_out = t[ti].copy()
    uv_out[:, 1] = 1.0 - uv_out[:, 1]
    return (v[vi].astype(np.float32), inverse.reshape(f.shape).astype(np.int32), n[vi],
            uv_out)


def offset_surface(vertices, normals, depth_mm: float) -> np.ndarray:
    """Vertices moved ``depth_mm`` inwards along their unit normals (an inner layer boundary)."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return np.asarray(vertices, dtype=np.float64) - float(depth_mm) * n


def write_ply(path, vertices, faces, normals=None, uv=None) -> Path:
    """Binary little-endian PLY (float x y z [nx ny nz] [u v], uchar/int face lists)."""
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int32)
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else []) \
        + (["u", "v"] if uv is not None else [])
    vert = np.zeros(len(v), dtype=[(k, "<f4") for k in names])
    cols = [v] + ([np.asarray(normals, np.float32)] if normals is not None else []) \
        + ([np.asarray(uv, np.float32)] if uv is not None else [])
    allc = np.concatenate(cols, axis=1)
    for i, k in enumerate(names):
        vert[k] = allc[:, i]
    face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = f
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(v)}\n" + "".join(f"property float {k}\n" for k in names)
              + f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())
    return path


# --------------------------------------------------------------------------- camera, lights
def _look_at(mi, origin, target, up):
    return mi.ScalarTransform4f().look_at(origin=[float(c) for c in origin],
                                          target=[float(c) for c in target],
                                          up=[float(c) for c in up])


def camera_dict(mi, camera, *, width: int, height: int, spp: int = 1) -> dict:
    """Mitsuba ``perspective`` sensor of a dermis CameraConfig at ``width`` x ``height``."""
    pos = np.asarray(camera.position, np.float64)
    dist = float(np.linalg.norm(np.asarray(camera.look_at, np.float64) - pos))
    return {"type": "perspective", "fov": float(camera.fov_deg), "fov_axis": "smaller",
            "near_clip": max(1e-3, 1e-4 * dist), "far_clip": 1e3 * max(dist, 1.0),
            "to_world": _look_at(mi, camera.position, camera.look_at, camera.up),
            "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb",
                     "sample_border": False},
            "sampler": {"type": "independent", "sample_count": int(spp)}}


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(c) for c in value]}


def environment_radiance(light, *, clamp: float = 0.0) -> tuple[np.ndarray, float]:
    """(H, W, 3) float32 radiance of an environment light as dermis samples it (scale
    applied; values above ``clamp`` cut when clamp > 0) and its rotation in degrees."""
    from dermis.lighting.lights import environment_map
    env = environment_map(light)
    rad = np.asarray(env.radiance, np.float32)
    if clamp > 0:
        rad = np.minimum(rad, np.float32(clamp))
    return rad, math.degrees(env.rotation)


def light_dicts(mi, lights, *, target, env_clamp: float = 0.0) -> dict:
    """Mitsuba emitters (and the disc's shape) for dermis LightConfigs; keys ``light_<name>``.

    ``target`` (3,) mm: a point of the lit object (the disc's emitting face turns to it).
    """
    out = {}
    target = np.asarray(target, np.float64)
    for lt in lights:
        key = f"light_{lt.name}"
        if lt.type == "point":
            out[key] = {"type": "point", "position": [float(c) for c in lt.position],
                        "intensity": _rgb(lt.intensity)}
        elif lt.type == "directional":
            d = np.asarray(lt.direction, np.float64)
            if not np.linalg.norm(d) > 0:
                raise ConfigError(f"lights.{lt.name}.direction = {lt.direction!r}: must be non-zero")
            d = d / np.linalg.norm(d)
            out[key] = {"type": "directional", "direction": [float(c) for c in -d],
                        "irradiance": _rgb(lt.intensity)}
        elif lt.type == "disc":
            c = np.asarray(lt.position, np.float64)
            n = np.asarray(lt.direction, np.float64)
            n = n / np.linalg.norm(n)
            if np.dot(n, target - c) < 0:
                n = -n
            up = [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0]
            r = float(lt.radius)
            xf = _look_at(mi, c, c + n, up) @ mi.ScalarTransform4f().scale([r, r, 1.0])
            radiance = np.asarray(lt.intensity, np.float64) / (math.pi * r * r)
            out[key] = {"type": "disk", "to_world": xf,
                        "emitter": {"type": "area", "radiance": _rgb(radiance)}}
        elif lt.type == "environment":
            rad, rot = environment_radiance(lt, clamp=env_clamp)
            em = {"type": "envmap", "bitmap": mi.Bitmap(rad), "scale": 1.0}
            if rot:
                em["to_world"] = mi.ScalarTransform4f().rotate([0.0, 1.0, 0.0], -rot)
            out[key] = em
        else:
            raise ConfigError(f"lights.{lt.name}.type = {lt.type!r}: not exportable")
    return out


# --------------------------------------------------------------------------- materials
def medium_dict(layer) -> dict:
    """Homogeneous medium of a dermis Layer (1/mm, scene in mm: unit factor 1, trap 1)."""
    sa = np.asarray(layer.sigma_a, np.float64)
    ss = np.asarray(layer.sigma_s, np.float64)
    st = sa + ss
    m = float(st.max())
    if not m > 0:
        raise ConfigError("reference: a layer with sigma_a + sigma_s = 0 has no medium")
    return {"type": "homogeneous", "albedo": _rgb(ss / st), "sigma_t": _rgb(st / m),
            "scale": m, "phase": {"type": "hg", "g": float(layer.g)},
            "sample_emitters": False}


def _boundary_bsdf(eta_in: float, eta_out: float, roughness: float, tint=None) -> dict:
    if abs(eta_in - eta_out) < 1e-9 and tint is None:
        return {"type": "null"}
    b = {"type": "roughdielectric", "distribution": "ggx", "alpha": float(roughness),
         "int_ior": float(eta_in), "ext_ior": float(eta_out)}
    if tint is not None:
        b["specular_transmittance"] = tint
    return b


def tint_texture(mi, texture_srgb, rd) -> dict:
    """Bitmap texture t = sqrt(albedo / Rd) (linear albedo from the sRGB texture)."""
    from dermis.rendering.color import srgb_to_linear
    lin = srgb_to_linear(np.asarray(texture_srgb, np.float32) / 255.0)
    t = np.sqrt(np.maximum(lin, 0.0) / np.maximum(np.asarray(rd, np.float32), 1e-6))
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(t, np.float32)),
            "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}


def _check_stack(stack) -> None:
    if not math.isinf(stack.layers[-1].thickness_mm):
        raise ConfigError("reference: the last layer of [optics] must be semi-infinite "
                          '(thickness_mm = "inf") to fill a head; finite stacks are for slabs')


@dataclass
class HeadScene:
    """A loaded Mitsuba scene of a head and what was exported (for ``info``)."""

    scene: object
    folder: str
    export: dict = field(default_factory=dict)


def head_scene(mi, mesh, stack, camera, lights, *, width: int, height: int, roughness: float,
               tint_rd=None, env_clamp: float = 0.0, integrator: str = "volpathmis",
               max_depth: int = -1, rr_depth: int = 1024,
               material: str = "skin", lambert_albedo=(0.5, 0.5, 0.5)) -> HeadScene:
    """Build and load the Mitsuba scene of ``mesh`` under ``lights`` seen by ``camera``.

    ``material = "skin"``: the layer stack (module docstring) with the albedo texture as a
    transmission tint normalised by ``tint_rd`` (None: no tint).  ``"lambert"``: a diffuse
    surface of the texture's linear albedo (or ``lambert_albedo``), the export round-trip
    test's material, rendered with the ``path`` integrator.
    """
    from dermis.rendering.color import srgb_to_linear
    folder = tempfile.mkdtemp(prefix="dermis-mitsuba-")
    normals = mesh.vertex_normals()
    v, f, n, uv = unweld(mesh.vertices, mesh.faces, normals, mesh.uv, mesh.uv_faces)
    outer = write_ply(Path(folder) / "outer.ply", v, f, n, uv)
    tex = mesh.texture_srgb if (mesh.texture_srgb is not None and uv is not None) else None
    target = np.asarray(mesh.vertices, np.float64).mean(axis=0)
    d: dict = {"type": "scene"}
    export = {"vertices": int(len(v)), "faces": int(len(f)), "textured": tex is not None,
              "material": material}
    if material == "lambert":
        if tex is not None:
            lin = srgb_to_linear(np.asarray(tex, np.float32) / 255.0).astype(np.float32)
            refl = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(lin)),
                    "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}
        else:
            refl = _rgb(lambert_albedo)
        d["head"] = {"type": "ply", "filename": str(outer), "face_normals": False,
                     "bsdf": {"type": "diffuse", "reflectance": refl}}
        d["integrator"] = {"type": "path", "max_depth": -1, "hide_emitters": True}
    elif material == "skin":
        _check_stack(stack)
        layers = stack.layers
        tint = tint_texture(mi, tex, tint_rd) if (tex is not None and tint_rd is not None) \
            else None
        media = [medium_dict(l) for l in layers]
        d["head"] = {"type": "ply", "filename": str(outer), "face_normals": False,
                     "bsdf": {"type": "roughdielectric", "distribution": "ggx",
                              "alpha": float(roughness), "int_ior": float(layers[0].eta),
                              "ext_ior": float(stack.eta_above),
                              **({"specular_transmittance": tint} if tint else {})},
                     "interior": media[0]}
        depth = 0.0
        wv = np.asarray(mesh.vertices, np.float64)
        for k in range(1, len(layers)):
            depth += layers[k - 1].thickness_mm
            inner = offset_surface(wv, normals, depth)
            path = write_ply(Path(folder) / f"layer{k}.ply", inner, mesh.faces,
                             normals.astype(np.float32))
            d[f"layer{k}"] = {"type": "ply", "filename": str(path), "face_normals": False,
                              "bsdf": _boundary_bsdf(layers[k].eta, layers[k - 1].eta,
                                                     roughness),
                              "interior": media[k], "exterior": media[k - 1]}
            export[f"layer{k}_depth_mm"] = depth
        d["integrator"] = {"type": integrator, "max_depth": int(max_depth),
                           "rr_depth": int(rr_depth), "hide_emitters": True}
        export.update(roughness=float(roughness), tint_rd=None if tint_rd is None
                      else [float(c) for c in tint_rd], tinted=tint is not None)
    else:
        raise ConfigError(f"material = {material!r}: must be 'skin' or 'lambert'")
    d["sensor"] = camera_dict(mi, camera, width=width, height=height)
    d.update(light_dicts(mi, lights, target=target, env_clamp=env_clamp))
    try:
        scene = mi.load_dict(d)
    except Exception:
        _cleanup(folder)
        raise
    return HeadScene(scene, folder, export)


def _cleanup(folder: str) -> None:
    import shutil
    shutil.rmtree(folder, ignore_errors=True)


def release(head: HeadScene) -> None:
    """Delete the temporary PLY files of a loaded scene (Mitsuba has read them)."""
    _cleanup(head.folder)


# --------------------------------------------------------------------------- rendering
def render_passes(mi, scene, *, spp: int, seed: int, checkpoints=(),
                  progress: Callable[[int], None] | None = None
                  ) -> tuple[np.ndarray, list, float]:
    """Render ``spp`` samples per pixel in calls of at most :data:`MAX_LANES` samples.

    Returns the (H, W, 3) float64 mean image, a list of (spp so far, mean image so far) at
    each of ``checkpoints`` (sample counts; the final count is always included) and the
    seconds spent.  Call k uses seed ``seed * 65536 + k`` (independent streams; seeds < 65536).
    ``progress(samples_done)`` is called after every call.
    """
    film = scene.sensors()[0].film()
    w, h = (int(c) for c in film.crop_size())
    per_call = max(1, min(int(spp), MAX_LANES // max(w * h, 1)))
    marks = sorted({int(c) for c in checkpoints if 0 < int(c) < spp} | {int(spp)})
    acc = np.zeros((h, w, 3), np.float64)
    done, k, out = 0, 0, []
    t0 = time.perf_counter()
    for mark in marks:
        while done < mark:
            n = min(per_call, mark - done)
            img = np.asarray(mi.render(scene, spp=n, seed=int(seed) * 65536 + k),
                             dtype=np.float64)
            acc += img[..., :3] * n
            done += n
            k += 1
            if progress is not None:
                progress(done)
        out.append((done, acc / done))
    return acc / max(done, 1), out, time.perf_counter() - t0


def pixel_hits(mi, scene, *, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's camera rays through the pixel centres: (H, W) hit mask and (H, W) int64
    primitive (face) index of the first shape hit (-1 where none)."""
    sensor = scene.sensors()[0]
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    pos = mi.Point2f(((j + 0.5) / width).ravel().astype(np.float32),
                     ((i + 0.5) / height).ravel().astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = np.asarray(si.is_valid(), bool).reshape(height, width)
    prim = np.asarray(si.prim_index, np.int64).reshape(height, width)
    return valid, np.where(valid, prim, -1)


# --------------------------------------------------------------------------- flat slab
@dataclass
class SlabResult:
    """Total reflectance of a flat slab under a normally incident directional light.

    Rd : (3,) subsurface reflectance per incident irradiance (boundary reflection removed)
    Rd_stderr : (3,) its standard error (between independent batches)
    specular : (3,) the boundary's own reflection (rendered with a black interior)
    Rd_entered : (3,) Rd / (1 - specular): per unit of flux that entered (the Monte Carlo
        slab's and the layer file's normalisation)
    seconds, samples : cost
    """

    Rd: np.ndarray
    Rd_stderr: np.ndarray
    specular: np.ndarray
    Rd_entered: np.ndarray
    seconds: float
    samples: int
    info: dict = field(default_factory=dict)


# A slab of this half-width and depth stands for an infinite one: skin's diffusion lengths
# are < 10 mm (sigma_tr >= 0.1 / mm in every preset), so the escaped fraction is ~e^-100.
SLAB_HALF_WIDTH_MM = 50.0
SLAB_DEPTH_MM = 50.0


def _slab_scene(mi, stack, roughness: float, *, black: bool, incidence_deg: float = 0.0,
                max_depth: int = -1, rr_depth: int = 1024):
    """Scene: stacked boxes (top at z = 0), an irradiance meter just above, a directional light."""
    T = mi.ScalarTransform4f
    layers = stack.layers
    d: dict = {"type": "scene", "integrator": {"type": "volpathmis", "max_depth": int(max_depth),
                                               "rr_depth": int(rr_depth)}}
    W = SLAB_HALF_WIDTH_MM
    finite = not math.isinf(layers[-1].thickness_mm)
    total = sum(l.thickness_mm for l in layers) if finite else SLAB_DEPTH_MM
    top = 0.0
    for k, lay in enumerate(layers):
        inset = 1e-3 * k  # nested boxes share no face: each lies just inside the one above
        med = medium_dict(lay)
        if black:  # purely absorbing interior: only the boundary's own reflection returns
            med = {"type": "homogeneous", "albedo": _rgb((0.0, 0.0, 0.0)),
                   "sigma_t": _rgb((1.0, 1.0, 1.0)), "scale": 1e3, "sample_emitters": False}
        lo, hi = -total + inset, top
        xf = T().translate([0.0, 0.0, 0.5 * (lo + hi)]) @ T().scale([W - inset, W - inset,
                                                                     0.5 * (hi - lo)])
        eta_out = stack.eta_above if k == 0 else layers[k - 1].eta
        box = {"type": "cube", "to_world": xf, "interior": med,
               "bsdf": (_boundary_bsdf(lay.eta, eta_out, roughness) if k else
                        {"type": "roughdielectric", "distribution": "ggx",
                         "alpha": float(roughness), "int_ior": float(lay.eta),
                         "ext_ior": float(stack.eta_above)})}
        if k:
            box["exterior"] = medium_dict(layers[k - 1])
        d[f"layer{k}"] = box
        if black or math.isinf(lay.thickness_mm):
            break
        top -= lay.thickness_mm
    th = math.radians(incidence_deg)
    d["light"] = {"type": "directional", "direction": [math.sin(th), 0.0, -math.cos(th)],
                  "irradiance": _rgb((1.0, 1.0, 1.0))}
    # meter: a 200 mm square 1 mm above the slab facing down, transparent to light
    d["meter"] = {"type": "rectangle", "bsdf": {"type": "null"},
                  "to_world": T().translate([0.0, 0.0, 0.1]) @ T().rotate([1.0, 0.0, 0.0], 180.0)
                  @ T().scale([10.0, 10.0, 1.0]),
                  "sensor": {"type": "irradiancemeter",
                             "film": {"type": "hdrfilm", "width": 1, "height": 1,
                                      "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                             "sampler": {"type": "independent", "sample_count": 1}}}
    return mi.load_dict(d)


def slab_reflectance(mi, stack, *, roughness: float, samples: int = 1 << 18, batches: int = 8,
                     seed: int = 0, max_depth: int = -1, rr_depth: int = 1024) -> SlabResult:
    """Mitsuba's total diffuse reflectance of a flat slab of ``stack`` at normal incidence.

    An irradiance meter above a wide slab measures the exitance M under irradiance E = 1;
    the same render with a black interior gives the boundary's own reflection, and
    Rd = M - specular (per incident irradiance, the reading every dermis model gives the
    albedo texture).  A finite stack ends on vacuum.  Standard errors from ``batches``
    independent renders.
    """
    t0 = time.perf_counter()
    sc = _slab_scene(mi, stack, roughness, black=False, max_depth=max_depth, rr_depth=rr_depth)
    per = max(1, samples // batches)
    vals = []
    for b in range(batches):
        vals.append(np.asarray(mi.render(sc, spp=per, seed=int(seed) * 1000 + b),
                               np.float64).reshape(-1)[:3])
    vals = np.array(vals)
    spec_sc = _slab_scene(mi, stack, roughness, black=True)
    spec = np.asarray(mi.render(spec_sc, spp=1 << 14, seed=int(seed) * 1000 + 999),
                      np.float64).reshape(-1)[:3]
    M = vals.mean(axis=0)
    err = vals.std(axis=0, ddof=1) / math.sqrt(batches)
    rd = M - spec
    return SlabResult(rd, err, spec, rd / np.maximum(1.0 - spec, 1e-9),
                      time.perf_counter() - t0, per * batches,
                      {"roughness": float(roughness), "batches": batches,
                       "max_depth": int(max_depth), "rr_depth": int(rr_depth),
                       "variant": mi.variant()})
