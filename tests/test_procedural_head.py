"""The procedural head: arguments, triangle budget, determinism, closed skin, UVs, texture, detail.

All builds use small triangle counts and textures so the file runs in a few seconds; the
1M-triangle timing lives in bench/bench_procedural_head.py.
"""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from dermis.pipeline.errors import ConfigError
from dermis.geometry import head_shape, procedural_head as ph

N_TRI = 20_000
TEX = 256
# The triangle count may miss its target by 2 %; the grid meets that budget to within one ring
# (n_t / T ~ 0.5% at 2k).
TRIANGLE_TOL = 0.02
HEIGHT_MM, HEIGHT_TOL = 300.0, 0.10          # top of the head to the bottom of the neck, +-10%
# Detail: pores <= 0.1 mm, wrinkles <= 0.35 mm (nasolabial), plus overlaps of pores, micro-relief
# and a crossing line: 0.6 mm bounds the deepest sum; the RMS of pores + micro-relief over the
# whole skin is a few hundredths of a mm (measured 0.016 mm), bounded loosely on both sides.
DETAIL_MAX_MM = 0.6
DETAIL_RMS_RANGE_MM = (0.004, 0.08)


@pytest.fixture(scope="module")
def head():
    return ph.make_head(triangles=N_TRI, texture_size=TEX, seed=0)


@pytest.fixture(scope="module")
def smooth():
    return ph.make_head(triangles=N_TRI, texture_size=TEX, detail=False, seed=0)


def _skin(mesh):
    comp = mesh.info["components"][0]
    assert comp["name"] == "skin"
    f0, f1 = comp["faces"]
    v0, v1 = comp["vertices"]
    return mesh.vertices[v0:v1], mesh.faces[f0:f1] - v0


def _digest(mesh):
    h = hashlib.sha256()
    for a in (mesh.vertices, mesh.faces, mesh.uv, mesh.uv_faces, mesh.texture_srgb):
        h.update(str((a.dtype, a.shape)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _closed_manifold_report(v, f):
    """(Euler characteristic, every undirected edge used twice, every directed edge once)."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    _, und_counts = np.unique(und, axis=0, return_counts=True)
    _, dir_counts = np.unique(directed, axis=0, return_counts=True)
    euler = len(np.unique(f)) - len(und_counts) + len(f)
    return euler, bool(np.all(und_counts == 2)), bool(np.all(dir_counts == 1))


def _signed_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


# ------------------------------------------------------------------------------------------ args
@pytest.mark.parametrize("kwargs, name", [
    ({"triangles": 1_999}, "triangles"),
    ({"triangles": 20_000_001}, "triangles"),
    ({"triangles": 20_000.0}, "triangles"),
    ({"triangles": True}, "triangles"),
    ({"texture_size": 100}, "texture_size"),
    ({"texture_size": 32}, "texture_size"),
    ({"texture_size": 32_768}, "texture_size"),
    ({"seed": -1}, "seed"),
    ({"seed": 1.5}, "seed"),
    ({"detail": "yes"}, "detail"),
])
def test01_bad_args_name_the_parameter(kwargs, name):
    with pytest.raises(ConfigError, match=rf"{name} = .*must be"):
        ph.make_head(**kwargs)


# ------------------------------------------------------------------------------ triangle budget
@pytest.mark.parametrize("target", [2_000, 7_777, 54_321])
def test02_triangle_count_within_tolerance(target):
    mesh = ph.make_head(triangles=target, texture_size=64, detail=False)
    assert abs(mesh.n_triangles - target) <= TRIANGLE_TOL * target
    assert mesh.faces.dtype == np.int32 and mesh.uv_faces.dtype == np.int32
    assert mesh.vertices.dtype == np.float64 and mesh.uv.dtype == np.float32
    assert mesh.uv_faces.shape == mesh.faces.shape


# ------------------------------------------------------------------------------- determinism
def test03_same_arguments_give_identical_arrays(head):
    again = ph.make_head(triangles=N_TRI, texture_size=TEX, seed=0)
    assert _digest(again) == _digest(head)
    assert again.info == head.info


def test04_seed_changes_detail_and_texture_only(head, smooth):
    other = ph.make_head(triangles=N_TRI, texture_size=TEX, seed=1)
    other_smooth = ph.make_head(triangles=N_TRI, texture_size=TEX, detail=False, seed=1)
    # the base shape does not depend on the seed
    np.testing.assert_array_equal(other_smooth.vertices, smooth.vertices)
    np.testing.assert_array_equal(other.faces, head.faces)
    np.testing.assert_array_equal(other.uv, head.uv)
    # the relief and the texture noise do
    assert not np.array_equal(other.vertices, head.vertices)
    assert not np.array_equal(other.texture_srgb, head.texture_srgb)
    # ... but only at detail scale
    assert np.abs(other.vertices - head.vertices).max() < 2 * DETAIL_MAX_MM


# ------------------------------------------------------------------------------- topology
@pytest.mark.parametrize("detail", [True, False])
def test05_skin_is_closed_oriented_manifold(head, smooth, detail):
    v, f = _skin(head if detail else smooth)
    euler, edges_twice, directed_once = _closed_manifold_report(v, f)
    assert edges_twice, "an edge is not shared by exactly two skin faces"
    assert directed_once, "neighbouring faces are not consistently oriented"
    assert euler == 2
    assert len(np.unique(f)) == len(v), "unreferenced skin vertices"
    # no degenerate or duplicate faces
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area2.min() > 1e-10 * np.ptp(v, axis=0).max() ** 2
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
    assert _signed_volume(v, f) > 0.0, "faces are not counter-clockwise seen from outside"


@pytest.mark.parametrize("detail", [True, False])
def test06_skin_is_embedded_star_shaped(head, smooth, detail):
    """Every skin triangle turns counter-clockwise seen from the ray centre: the radial surface
    folds nowhere, so it cannot self-intersect (also after the relief is applied)."""
    v, f = _skin(head if detail else smooth)
    c = head_shape.CENTRE + ph.FRAME_OFFSET
    a, b, d = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    det = np.einsum("ij,ij->i", a, np.cross(b, d))
    assert det.min() > 0.0


def test07_eyeballs_are_closed_spheres_in_the_sockets(head):
    import igl
    v_skin, f_skin = _skin(head)
    for comp in head.info["components"][1:]:
        v0, v1 = comp["vertices"]
        f = head.faces[comp["faces"][0]:comp["faces"][1]] - v0
        v = head.vertices[v0:v1]
        euler, edges_twice, directed_once = _closed_manifold_report(v, f)
        assert (euler, edges_twice, directed_once) == (2, True, True)
        centre = v.mean(axis=0)
        radius = np.linalg.norm(v - centre, axis=1)
        np.testing.assert_allclose(radius, head_shape.EYE_RADIUS, rtol=1e-9)
        assert _signed_volume(v, f) > 0.0
        # centre and the part under the upper lid are inside the skin, the cornea is outside
        probes = np.array([centre, centre + head_shape.EYE_RADIUS * np.array([0.0, 0.8, 0.6]),
                           centre + (head_shape.EYE_RADIUS + 0.05) * np.array([0.0, 0.0, 1.0])])
        w = igl.winding_number(v_skin, f_skin.astype(np.int64), probes)
        np.testing.assert_allclose(w, [1.0, 1.0, 0.0], atol=0.05)


# ------------------------------------------------------------------------------- shape
def test08_size_and_frame(head):
    v, _ = _skin(head)
    ext = np.ptp(v, axis=0)
    assert abs(ext[1] - HEIGHT_MM) <= HEIGHT_TOL * HEIGHT_MM
    # adult head breadth ~150 mm (+ ears) and length ~200 mm (Farkas 1994), generous bounds
    assert 130.0 < ext[0] < 200.0 and 170.0 < ext[2] < 250.0
    # face towards +Z: the most forward point is the nose tip, on the midline, near the LPS tip
    tip = v[np.argmax(v[:, 2])]
    np.testing.assert_allclose(tip, [0.0, -35.0, 51.0], atol=3.0)
    # bilateral symmetry of the base mesh: the mirrored vertex set matches itself
    top = v[np.argmax(v[:, 1])]
    assert abs(top[0]) < 1.0


# ------------------------------------------------------------------------------- UVs
def test09_uv_in_range_with_a_seam_at_the_back(head):
    v, f = _skin(head)
    comp = head.info["components"][0]
    uvf = head.uv_faces[comp["faces"][0]:comp["faces"][1]]
    assert head.uv.min() >= 0.0 and head.uv.max() <= 1.0
    pairs = np.unique(np.stack([f.ravel(), uvf.ravel()], 1), axis=0)
    n_uv = np.bincount(pairs[:, 0], minlength=len(v))
    split = np.flatnonzero(n_uv > 1)
    assert split.size > 10, "no UV seam"
    # apart from the two poles every split vertex lies on the seam: midline, back of the head
    on_seam = split[n_uv[split] == 2]
    assert len(split) - len(on_seam) == 2
    np.testing.assert_allclose(v[on_seam, 0], 0.0, atol=1e-9)
    assert np.all(v[on_seam, 2] < (head_shape.CENTRE + ph.FRAME_OFFSET)[2])
    # every skin triangle keeps its orientation in UV space (no flipped charts)
    t = head.uv[uvf]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    assert area.min() > 0.0
    # the skin stays below the eye strip
    assert head.uv[uvf][..., 1].max() <= head_shape.V_SKIN + 1e-6


# ------------------------------------------------------------------------------- texture
def _texel_at(mesh, point, offset=True):
    """Mean sRGB over 3x3 texels at the UV of the skin vertex nearest a design-frame point."""
    v, f = _skin(mesh)
    p = np.asarray(point, float) + (ph.FRAME_OFFSET if offset else 0.0)
    vi = int(np.argmin(np.linalg.norm(v - p, axis=1)))
    fi, k = np.argwhere(f == vi)[0]
    uv = mesh.uv[mesh.uv_faces[fi, k]]
    tex = mesh.texture_srgb.astype(float)
    h, w = tex.shape[:2]
    row, col = int(round((1 - uv[1]) * (h - 1))), int(round(uv[0] * (w - 1)))
    return tex[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].reshape(-1, 3).mean(axis=0)


def test10_texture_varies_with_plausible_regions(head):
    tex = head.texture_srgb
    assert tex.dtype == np.uint8 and tex.shape == (TEX, TEX, 3)
    skin = tex[int(TEX * (1 - head_shape.V_SKIN)) + 1:]
    # not flat: the region masks and noise give several sRGB levels of spread (measured ~10)
    assert skin.reshape(-1, 3).std(axis=0).min() > 3.0
    forehead = _texel_at(head, (0.0, 50.0, 88.0))
    lips = _texel_at(head, (0.0, -77.0, 90.0))
    cheek = _texel_at(head, (44.0, -32.0, 75.0))
    brow = _texel_at(head, (30.0, 21.0, 88.0))
    redness = lambda c: c[0] / c[1]   # noqa: E731
    assert redness(lips) > redness(forehead) + 0.15
    assert redness(cheek) > redness(forehead)
    assert brow.sum() < 0.7 * forehead.sum()
    # skin tone: red > green > blue everywhere on the forehead/cheek samples
    for c in (forehead, cheek):
        assert c[0] > c[1] > c[2]


def test11_eye_strip_shows_iris_and_sclera(head):
    tex = head.texture_srgb.astype(float)
    strip = int(round(TEX * (1 - head_shape.V_SKIN)))
    centre = tex[strip // 2, strip // 2]           # pupil
    sclera = tex[strip // 2, int(strip * 0.15)]    # ~8.5 mm from the axis
    assert centre.sum() < 60 and sclera.sum() > 450


# ------------------------------------------------------------------------------- detail
def test12_detail_is_a_small_displacement_along_the_normal(head, smooth):
    import igl
    v_d, f = _skin(head)
    v_s, _ = _skin(smooth)
    disp = v_d - v_s
    mag = np.linalg.norm(disp, axis=1)
    assert mag.max() <= DETAIL_MAX_MM
    rms = float(np.sqrt(np.mean(mag ** 2)))
    assert DETAIL_RMS_RANGE_MM[0] < rms < DETAIL_RMS_RANGE_MM[1]
    # along the normal of the smooth surface (central-difference normal vs igl's angle-weighted
    # normal differ by the discretisation only: median |cos| close to 1)
    n = igl.per_vertex_normals(v_s, f.astype(np.int64))
    moved = mag > 1e-4
    cos = np.abs(np.einsum("ij,ij->i", disp[moved], n[moved])) / mag[moved]
    assert np.median(cos) > 0.98
    # the forehead lines and the nasolabial folds are grooves deeper than the pores
    depth = np.einsum("ij,ij->i", disp, n)
    design = v_s - ph.FRAME_OFFSET
    fold = (np.abs(np.abs(design[:, 0]) - 27.0) < 6.0) & (np.abs(design[:, 1] + 64.0) < 8.0) & (design[:, 2] > 60)
    assert depth[fold].min() < -0.2
    assert depth.min() > -DETAIL_MAX_MM
