"""Inputs that used to give a useless run without a word (docs/hardening.md, "Silent useless
runs"): each is refused (exit 2) with a message naming the file or key, the value and what is
likely meant; and a property of every model's images under sharp shadows.

1. A truncated texture: a JPEG cut to a third of its bytes decoded with two thirds of its
   pixels grey 128 (OpenImageIO's ``ImageBuf`` reports no error for it; its ``ImageInput``
   does), and a truncated PNG, TIFF, EXR or HDR texture came back as pixels too.
2. A mesh declared in the wrong units by x1000: the head 1000 times too large gave a
   near-black image, 1000 times too small one that no camera ray hits.
3. ``dermis sweep`` of a knob that changes no node of the scene (``lights.samples`` under
   point lights): every error 0 and the cheapest value recommended.
4. No image of any model (every BRDF of the registry through ``rendering/shade.py``, every
   BSSRDF through the ``bssrdf`` stage's own ``run`` on the library's points, irradiance and
   profiles) has a negative or non-finite pixel, over small scenes with sharp shadows: a
   sphere or a plane beside a plate's shadow edge, under point and directional lights.

Cases 1-3 run ``dermis.pipeline.cli.main`` in-process on small scan scenes, ``--until
mesh_source`` where the refusal belongs to the mesh.
"""
from __future__ import annotations

import contextlib
import math
import re
import sys
import types
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.cli import main
from dermis.pipeline.errors import DermisError

sys.path.insert(0, str(Path(__file__).parent))
from render_fixtures import icosphere, plane  # noqa: E402
from scene_toml import quick_with_sweep  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "scenes" / "quick.toml"
CUBE_V = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
CUBE_F = [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (2, 3, 7), (2, 7, 6),
          (1, 2, 6), (1, 6, 5), (0, 4, 7), (0, 7, 3)]


# --------------------------------------------------------------------------- scan scenes
def _write_image(path: Path, img: np.ndarray, fmt: str = "uint8") -> Path:
    import OpenImageIO as oiio
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0],
                                                                   img.shape[2], fmt))
    out.write_image(np.ascontiguousarray(img))
    out.close()
    return path


def _texture(path: Path, *, truncate: bool = False) -> Path:
    """A 64 x 96 noise image in the format of ``path``'s suffix; ``truncate`` keeps the
    first third of its bytes (as an interrupted download or copy leaves it)."""
    rng = np.random.default_rng(7)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix in (".exr", ".hdr"):
        _write_image(path, rng.random((96, 64, 3)).astype(np.float32), "half"
                     if path.suffix == ".exr" else "float")
    else:
        _write_image(path, (rng.random((96, 64, 3)) * 255).astype(np.uint8))
    if truncate:
        data = path.read_bytes()
        path.write_bytes(data[:len(data) // 3])
    return path


def _cube_obj(folder: Path, size: float, texture: str = "albedo.png") -> Path:
    """A textured cube OBJ of side ``size`` in the file's units (+ MTL naming ``texture``)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "m.mtl").write_text(f"newmtl skin\nmap_Kd {texture}\n")
    if not (folder / texture).exists():
        _texture(folder / texture)
    lines = ["mtllib m.mtl", "usemtl skin"]
    lines += ["v " + " ".join(repr(c * size) for c in v) for v in CUBE_V]
    lines += ["vt 0.1 0.1", "vt 0.9 0.1", "vt 0.5 0.9"]
    lines += [f"f {a + 1}/1 {b + 1}/2 {c + 1}/3" for a, b, c in CUBE_F]
    path = folder / "mesh.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def _scan_scene(folder: Path, mesh: Path, units: str) -> Path:
    path = folder / "scene.toml"
    path.write_text(f"""
[scene]
name = "scan"
[mesh]
source = "{mesh}"
units = "{units}"
high_triangles = 2000
low_triangles = 400
[bake]
resolution = 64
[camera]
position = [150.0, 150.0, 1000.0]
look_at = [150.0, 150.0, 150.0]
fov_deg = 30.0
width = 32
height = 32
[[lights]]
name = "point"
type = "point"
position = [350.0, 450.0, 600.0]
intensity = [4.0e5, 4.0e5, 4.0e5]
[render]
models = ["lafortune"]
lights = ["point"]
geometries = ["high"]
[output]
output_dir = "{folder / 'out'}"
previews = false
""")
    return path


def _run(scene: Path, cache: Path, capsys, *extra) -> tuple[int, str]:
    rc = main(["run", str(scene), "--cache", str(cache), "-q", *extra])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


# --------------------------------------------------------------------------- 1. textures
def test01_truncated_jpeg_texture_is_refused_naming_the_file(tmp_path, capsys):
    """Before: rc 0, the mesh's albedo two thirds grey 128, no word.  Now exit 2 naming the
    texture, what the decoder said and that the file is truncated; nothing is cached."""
    tex = _texture(tmp_path / "mesh" / "albedo.jpg", truncate=True)
    scene = _scan_scene(tmp_path, _cube_obj(tmp_path / "mesh", 300.0, tex.name), "mm")
    rc, err = _run(scene, tmp_path / "cache", capsys, "--until", "mesh_source")
    assert rc == 2, err
    assert str(tex) in err and "Premature end of JPEG file" in err and "truncated" in err, err
    assert not list((tmp_path / "cache").glob("mesh_source/*/meta.json"))


@pytest.mark.parametrize("suffix", [".jpg", ".png", ".tif", ".exr", ".hdr"])
def test02_truncated_textures_of_every_format_are_refused(tmp_path, suffix):
    """The scan reader (textures named by the material or by mesh.texture) refuses each
    truncated format; the engine's reader (mesh.displacement, environment maps) too."""
    from dermis.geometry.scan import load_scan
    from dermis.pipeline.imageio import read_image
    tex = _texture(tmp_path / f"albedo{suffix}", truncate=True)
    mesh = _cube_obj(tmp_path / "mesh", 300.0)
    with pytest.raises(DermisError, match=re.escape(str(tex)) + ".*could not be decoded"):
        load_scan(mesh, texture=tex)
    with pytest.raises(DermisError, match=re.escape(str(tex)) + ".*cannot be decoded"):
        read_image(tex, what="mesh.displacement")


def test03_intact_textures_read_as_before(tmp_path):
    """The pixels of intact files are those an ImageBuf reads (the reader the scan loader
    used before it checked the decoder's errors): uint8 as stored, EXR through the sRGB
    curve, grey repeated."""
    import OpenImageIO as oiio
    from dermis.geometry.scan import _read_texture
    from dermis.rendering.color import linear_to_srgb8
    for suffix in (".jpg", ".png", ".tif"):
        tex = _texture(tmp_path / f"albedo{suffix}")
        want = np.asarray(oiio.ImageBuf(str(tex)).get_pixels(oiio.UINT8))
        np.testing.assert_array_equal(_read_texture(tex), want)
    tex = _texture(tmp_path / "albedo.exr")
    want = linear_to_srgb8(oiio.ImageBuf(str(tex)).get_pixels(oiio.FLOAT), np.float64)
    np.testing.assert_array_equal(_read_texture(tex), want)
    grey = _write_image(tmp_path / "grey.png", np.arange(48, dtype=np.uint8).reshape(6, 8, 1))
    np.testing.assert_array_equal(_read_texture(grey),
                                  np.repeat(np.arange(48, dtype=np.uint8).reshape(6, 8, 1), 3, 2))


# --------------------------------------------------------------------------- 2. units
@pytest.mark.parametrize("size, units, expect", [
    (300.0, "m", ['mesh.units = "m"', "3e+05 x 3e+05 x 3e+05 mm", 'set mesh.units = "mm"']),
    (0.3, "mm", ['mesh.units = "mm"', "0.3 x 0.3 x 0.3 mm", 'set mesh.units = "m"']),
], ids=["mm_file_declared_m", "m_file_declared_mm"])
def test04_mesh_in_the_wrong_units_by_1000_is_refused(tmp_path, capsys, size, units, expect):
    """Before: rc 0 and a near-black image (the LPS head in mm declared m: mean 1.7e-6
    against 0.0147), or one that no ray hits.  Now exit 2 with the measured size, the
    declared units and the likely unit; the same file with the right units runs."""
    mesh = _cube_obj(tmp_path / "mesh", size)
    rc, err = _run(_scan_scene(tmp_path, mesh, units), tmp_path / "cache", capsys,
                   "--until", "mesh_source")
    assert rc == 2, err
    assert str(mesh) in err and all(e in err for e in expect), err
    right = {"m": "mm", "mm": "m"}[units]
    rc, err = _run(_scan_scene(tmp_path, mesh, right), tmp_path / "cache", capsys,
                   "--until", "mesh_source")
    assert rc == 0, err


def test05_subject_size_bounds():
    """A skin patch of 1 cm and a body of 5 m pass; beyond either end is refused, naming the
    unit that brings the size nearest a head's, or none where no unit brings it inside."""
    from dermis.geometry.validation import SUBJECT_SIZE_MM, check_extent
    v = np.array(CUBE_V, float)
    f = np.array(CUBE_F)
    mesh = lambda s: types.SimpleNamespace(vertices=v * s, faces=f)  # noqa: E731
    lo, hi = SUBJECT_SIZE_MM
    for s in (lo, 300.0, hi):
        check_extent(mesh(s), source="x.obj", units="mm")
    with pytest.raises(DermisError, match='likely in cm .*set mesh.units = "cm"'):
        check_extent(mesh(lo * 0.9), source="x.obj", units="mm")     # 90 mm in cm
    with pytest.raises(DermisError, match='likely in m .*set mesh.units = "m"'):
        check_extent(mesh(0.5), source="x.obj", units="mm")          # 5 mm in cm, 500 in m
    with pytest.raises(DermisError, match="no unit of mesh.units brings it there"):
        check_extent(mesh(hi * 1.1), source="x.obj", units="mm")


# --------------------------------------------------------------------------- 3. sweep
def _sweep_scene(folder: Path, lights: str, knobs: str) -> Path:
    """The quick scene cut to one Lafortune image per light, with a [sweep] table."""
    return quick_with_sweep(folder, model="lafortune", lights=lights,
                            sweep="[sweep]\n[sweep.knobs]\n" + knobs)


def test06_sweep_of_a_knob_that_changes_no_node_is_refused(tmp_path, capsys):
    """Before: lights.samples on a scene lit by point and directional lights ran every
    point, all errors 0, "recommended: lights.samples 4".  Now exit 2 before any node
    runs, naming the knob, "has no effect on this scene" and the lights rendered."""
    scene = _sweep_scene(tmp_path, '["point", "dir_left+dir_right"]',
                         '"lights.samples" = [4, 16, 64]\n')
    assert main(["sweep", str(scene), "--cache", str(tmp_path / "cache")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert str(scene) in err and "sweep.knobs.lights.samples: has no effect on this scene" in err
    assert "point 'point'" in err and "directional 'dir_left'" in err, err
    assert not list(tmp_path.glob("cache/*/*/meta.json"))


def test07_idle_knobs_finds_only_knobs_without_effect(tmp_path):
    """The same knob under an area light has an effect; a BSSRDF knob on a scene without a
    BSSRDF has none; one value equal to the scene's own is not judged."""
    import tomllib
    from dermis.reports.sweep import idle_knobs, parse_sweep

    def idle(lights, knobs):
        path = _sweep_scene(tmp_path, lights, knobs)
        table = tomllib.loads(path.read_text())
        return idle_knobs(table, str(path), parse_sweep(table.pop("sweep"), str(path)))

    assert idle('["area"]', '"lights.samples" = [4, 16]\n') == {}
    assert set(idle('["point"]', '"lights.samples" = [4]\n"render.spp" = [1, 2]\n'
                    '"bssrdf.epsilon" = [1.0, 0.5]\n')) == {"lights.samples", "bssrdf.epsilon"}
    assert idle('["point"]', '"bssrdf.epsilon" = [0.5]\n') == {}    # the scene's own value


# --------------------------------------------------------------------------- 4. images
R = 15.0   # sphere radius, mm (the plane is 4 R wide)


def _shadow_scene(shape: str, kinds: tuple, elevation: float, azimuth: float, edge: float):
    """A sphere of radius R at the origin (or a 4 R plane at z = 0) and a plate at R / 2
    above its top on the side of the light, whose straight edge shades the lit side beyond
    ``edge`` mm from the top; point lights 1 m away and directional lights from ``elevation``
    and ``azimuth`` (deg), and a camera above.  Returns (mesh, lights, camera)."""
    from dermis.geometry.normals import angle_weighted_normals
    from dermis.pipeline.artifacts import Mesh
    from dermis.pipeline.config import CameraConfig, LightConfig
    body = icosphere(R, 3) if shape == "sphere" else plane(size=4 * R, n=6)
    top = R if shape == "sphere" else 0.0
    el, az = math.radians(elevation), math.radians(azimuth)
    toward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    side = np.array([math.cos(az), math.sin(az), 0.0])
    across = np.array([-math.sin(az), math.cos(az), 0.0])
    x0 = edge + 0.5 * R / math.tan(el)       # where the plate's edge lies over the top
    corners = [x0 * side - 2 * R * across, (x0 + 3 * R) * side - 2 * R * across,
               (x0 + 3 * R) * side + 2 * R * across, x0 * side + 2 * R * across]
    plate = np.array(corners) + [0.0, 0.0, top + 0.5 * R]
    v = np.vstack([np.asarray(body.vertices, np.float64), plate])
    f = np.vstack([np.asarray(body.faces), np.array([[0, 1, 2], [0, 2, 3]]) + len(body.vertices)])
    mesh = Mesh(vertices=v, faces=f.astype(np.int32),
                normals=angle_weighted_normals(v, f).astype(np.float32))
    lights = []
    for kind in kinds:
        if kind == "point":
            lights.append(LightConfig(name="lamp", type="point", position=tuple(1000.0 * toward),
                                      intensity=(1.5e6, 1.5e6, 1.5e6)))
        else:
            lights.append(LightConfig(name="sun", type="directional", direction=tuple(toward),
                                      intensity=(1.5, 1.5, 1.5)))
    camera = CameraConfig(position=(0.0, -0.3 * R, 400.0), look_at=(0.0, 0.0, 0.0),
                          fov_deg=2 * math.degrees(math.atan(1.6 * R / 400.0)), width=24,
                          height=24)
    return mesh, lights, camera


@pytest.fixture(scope="module")
def bssrdf_profiles(cl_env):
    """The profile tables each BSSRDF model reads: the multipole of skin1 (the scene's
    ``[optics] profile``), the Monte Carlo table at 20k photons per channel (CI-sized)."""
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    from dermis.pipeline import registry
    stack = PRESETS["skin1"]
    out = {}
    for name in registry.model_names():
        m = registry.model(name)
        if m.stage == "bssrdf":
            kind = m.profile or "multipole"
            if kind == "single_layer":     # the stack's single-layer twin (stages/profiles.py)
                from dermis.optics.single_layer import single_layer_equivalent
                single, _ = single_layer_equivalent(stack, build_profiles(stack).Rd)
                out[name] = build_profiles(single)
                continue
            out[name] = build_profiles(stack, model=kind, photons=20000, env=cl_env)
    return stack, out


@contextlib.contextmanager
def _recorded_exitance():
    """The exitance the bssrdf stage computes, before its image replaces non-finite values
    by 0 (so the property sees them)."""
    import dermis.stages.bssrdf as B
    seen, orig = [], B.exitance

    def wrapped(*args, **kw):
        M, stats = orig(*args, **kw)
        seen.append(np.asarray(M))
        return M, stats
    B.exitance = wrapped
    try:
        yield seen
    finally:
        B.exitance = orig


def _bssrdf_image(mesh, lights, camera, stack, profile, spp, cl_env, tmp: Path):
    """One image of the bssrdf stage's ``run`` on the library's points and irradiance."""
    from dermis.lighting.emitters import light_params
    from dermis.lighting.irradiance import irradiance
    from dermis.lighting.visibility import Visibility
    from dermis.optics.transmittance import Transmittance
    from dermis.pipeline.config import BssrdfConfig
    from dermis.rendering.cast import cast
    from dermis.rendering.options import RenderOptions
    from dermis.stages import bssrdf as B
    from dermis.subsurface.points import sample_points, spacing_from_mfp
    cfg = BssrdfConfig()
    vis = Visibility(mesh.vertices, mesh.faces)
    pts = sample_points(mesh.vertices, mesh.faces, seed=1, vertex_normals=mesh.normals,
                        spacing_mm=spacing_from_mfp(stack, cfg.point_density))
    eta = stack.layers[0].eta / stack.eta_above
    E = irradiance(pts.positions, pts.normals, lights, vis.occluded,
                   transmittance=Transmittance(eta, cfg.surface_reflection))
    samples = cast(mesh, lights, camera, RenderOptions(visibility=vis, spp=spp), cl_env=cl_env)
    params = {"label": "l", "geometry": "high", "camera": asdict(camera), "bump": None,
              "bssrdf": asdict(cfg), **light_params(lights), "seed": 0, "eta": eta}
    ctx = types.SimpleNamespace(cl=cl_env, shared=None, progress=None, out_dir=tmp,
                                input_keys={"mesh": "m", "points": "p", "irradiance": "e",
                                            "profile": "r"})
    inputs = {"mesh": mesh, "profile": profile, "visibility": samples, "points": pts,
              "irradiance": types.SimpleNamespace(irradiance=E)}
    return B.run(params, inputs, ctx).artifact


try:
    from hypothesis import example, given, strategies as st
except ImportError:  # pragma: no cover - hypothesis is a dev extra
    pass
else:
    @given(shape=st.sampled_from(["sphere", "plane"]),
           kinds=st.sampled_from([("point",), ("directional",), ("point", "directional")]),
           elevation=st.floats(4.0, 80.0), azimuth=st.floats(0.0, 360.0),
           edge=st.floats(-0.8 * R, 0.8 * R), spp=st.sampled_from([1, 2]))
    @example(shape="sphere", kinds=("point",), elevation=10.0, azimuth=0.0, edge=0.0, spp=1)
    @example(shape="plane", kinds=("directional",), elevation=35.0, azimuth=120.0, edge=3.0,
             spp=2)
    def test08_no_model_renders_a_negative_or_non_finite_pixel(cl_env, bssrdf_profiles,
                                                               tmp_path_factory, shape, kinds,
                                                               elevation, azimuth, edge, spp):
        """Every registered model's image of a sharp-shadow scene (sphere or plane, a plate's
        shadow edge across it, point and/or directional lights from 4-80 deg elevation, 1 or
        2 camera samples per pixel) is finite and >= 0 in every pixel, lit somewhere, and 0
        where no camera ray hits; a BSSRDF's exitance is finite and >= 0 before the stage
        replaces non-finite values; a BRDF image reports no non-finite pixel replaced."""
        from dermis.lighting.visibility import Visibility
        from dermis.pipeline import registry
        from dermis.rendering.options import RenderOptions
        from dermis.rendering.shade import render
        mesh, lights, camera = _shadow_scene(shape, kinds, elevation, azimuth, edge)
        vis = Visibility(mesh.vertices, mesh.faces)
        stack, profiles = bssrdf_profiles
        tmp = tmp_path_factory.mktemp("images")
        images = {}
        for name in registry.model_names():
            model = registry.model(name)
            if model.stage == "render":
                bases = [None] if not model.bases else ["none"] + [b.name for b in model.bases]
                for base in bases:
                    res = render(mesh, lights, model, None, camera,
                                 RenderOptions(visibility=vis, spp=spp, base=base), cl_env=cl_env)
                    assert res.info["nonfinite_pixels"] == 0, (name, base)
                    images[f"{name}/{base}" if base else name] = res
            elif model.stage == "bssrdf":
                with _recorded_exitance() as seen:
                    images[name] = _bssrdf_image(mesh, lights, camera, stack, profiles[name],
                                                 spp, cl_env, tmp)
                M = np.concatenate(seen)
                assert np.isfinite(M).all() and M.min() >= 0.0, (name, float(np.nanmin(M)))
            # other stages (Blender's Cycles models) render in a process of their own: their
            # images are checked finite and >= 0 by tests/test_cycles.py
        assert any(k.startswith("bssrdf") for k in images) and "lafortune" in images
        for name, img in images.items():
            linear = np.asarray(img.linear)
            assert np.isfinite(linear).all(), name
            low = linear < 0
            assert not low.any(), (name, int(low.any(axis=2).sum()), float(linear.min()))
            assert (linear[~np.asarray(img.mask)] == 0).all(), name
            assert linear.max() > 0, name
