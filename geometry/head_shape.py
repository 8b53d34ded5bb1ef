"""The procedural head's shape: the implicit skin field, its ray solve on a ring grid, the eyes.

The skin is one closed, star-shaped surface around a centre ``C``: an implicit field built
from smooth unions of ellipsoids, capsules and slabs (cranium, face, jaw, neck, brow ridge,
eye sockets and lids, nose with alae and nostrils, lips, chin, ears) is solved for its radius
along every direction of a latitude-longitude grid.  The grid's polar angle is re-spaced so
that the meridian arc length per ring is constant (the neck would otherwise get a few rings).
Because every vertex sits on its own ray from ``C`` the surface cannot self-intersect, and the
grid's topology (rings closed by a fan at each pole) makes it a closed 2-manifold with Euler
characteristic 2.  The lids open onto the eyeballs per ray (:func:`eye_aperture`); the
eyeballs are separate icospheres (:func:`icosphere`).  :mod:`dermis.geometry.procedural_head`
assembles the head.

Design frame: mm, Y up, face towards +Z (shifted to the output frame by ``FRAME_OFFSET`` there).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["V_SKIN", "CENTRE", "R_IN", "R_OUT", "EYE_CENTRES", "EYE_RADIUS", "LID_RADIUS",
           "NECK_BOTTOM_Y", "ellipsoid", "smoothstep", "ray_points", "bisect_radius", "pilot_solve",
           "ring_schedule", "grid_size", "grid_faces", "grid_uv", "solve_grid", "eye_aperture",
           "icosphere"]

V_SKIN = 15.0 / 16.0           # skin atlas occupies v in [0, V_SKIN]; the strip above holds the eyes

# Ray centre of the star-shaped skin: at ear height so that the ear slabs, the underside of the
# nose and the throat are all seen from inside (their normals face away from C).
CENTRE = np.array([0.0, -8.0, 5.0])
R_IN, R_OUT = 20.0, 280.0      # every ray from C leaves the skin between these radii (mm)

# Landmarks (design frame, mm).  Rounded adult values in the spirit of Farkas, "Anthropometry
# of the Head and Face" (1994): head breadth ~150, glabella-opisthocranion ~200, vertex-menton
# ~230, interpupillary 63, mouth width 50, nose width 35, ear length 62, eyeball radius 12.
EYE_CENTRES = np.array([[32.0, 0.0, 69.0], [-32.0, 0.0, 69.0]])
EYE_RADIUS = 12.0              # human eyeball ~24 mm diameter
LID_RADIUS = 13.4              # lids ride ~1.4 mm in front of the eyeball
NECK_BOTTOM_Y = -180.0         # top of head ~ +120 -> about 300 mm tall


# ----------------------------------------------------------------------------------------------
# implicit primitives (F < 0 inside; values are approximate distances in mm near the surface)
# ----------------------------------------------------------------------------------------------
def ellipsoid(p, c, r):
    """Approximate signed distance to an axis-aligned ellipsoid (Quilez's bound); p = (x, y, z)."""
    qx, qy, qz = (p[0] - c[0]) / r[0], (p[1] - c[1]) / r[1], (p[2] - c[2]) / r[2]
    k0 = np.sqrt(qx * qx + qy * qy + qz * qz)
    k1 = np.sqrt((qx / r[0]) ** 2 + (qy / r[1]) ** 2 + (qz / r[2]) ** 2) + 1e-12
    return k0 * (k0 - 1.0) / k1


def _capsule(p, a, b, ra, rb):
    """Signed distance to a segment a-b with radius varying linearly from ra to rb; p = (x, y, z)."""
    ab = b - a
    h = ((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1] + (p[2] - a[2]) * ab[2]) / (ab @ ab)
    h = np.clip(h, 0.0, 1.0)
    dx, dy, dz = p[0] - a[0] - h * ab[0], p[1] - a[1] - h * ab[1], p[2] - a[2] - h * ab[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz) - (ra + (rb - ra) * h)


def _smin(a, b, k):
    """Polynomial smooth minimum (union) with blend width k mm."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a, b, k):
    """Smooth maximum (intersection / subtraction) with blend width k mm."""
    return -_smin(-a, -b, k)


def _mirror(p):
    """Fold x onto x >= 0 so paired features are modelled once."""
    return (np.abs(p[0]), p[1], p[2])


def _ear(q):
    """Ear as a lateral slab whose outer face is a height field over its outline (q has x >= 0)."""
    # Outline: ellipse 62 x 34 mm tilted 15 deg (top leaning back), behind the jaw joint.
    cy, cz, tilt = -12.0, -14.0, math.radians(15.0)
    dy, dz = q[1] - cy, q[2] - cz
    ey = dy * math.cos(tilt) - dz * math.sin(tilt)
    ez = dy * math.sin(tilt) + dz * math.cos(tilt)
    s = np.sqrt((ey / 31.0) ** 2 + (ez / 17.0) ** 2)
    back = np.clip((17.0 - ez) / 34.0, 0.0, 1.0)           # 0 at the attached front edge
    lobe = np.clip((-ey - 12.0) / 14.0, 0.0, 1.0)            # lower third: fleshy lobe
    # outer surface x: stands out ~25 deg from the head, helix rim ridge, concha bowl, antihelix
    x_out = (64.0 + 15.0 * back ** 0.8 * (1.0 - 0.45 * lobe)
             + 2.5 * np.exp(-((s - 0.86) / 0.09) ** 2) * (1.0 - lobe)
             + 1.6 * np.exp(-((s - 0.58) / 0.08) ** 2) * np.clip((ey + 10.0) / 8.0, 0.0, 1.0)
             - 8.5 * np.exp(-((ey + 6.0) / 10.0) ** 2 - ((ez - 1.0) / 7.0) ** 2)
             - 3.0 * np.exp(-((ey - 8.0) / 5.0) ** 2 - ((ez + 2.0) / 6.0) ** 2)
             + 3.0 * np.exp(-((ey + 9.0) / 4.0) ** 2 - ((ez - 11.0) / 3.0) ** 2))   # tragus
    slab = q[0] - x_out
    outline = (s - 1.0) * 17.0
    return _smax(slab, outline, 2.0)


def _neck(p):
    """Neck: elliptic cylinder cut flat at the bottom (rounded rim) and open into the head."""
    neck = np.sqrt((p[0] / 50.0) ** 2 + ((p[2] + 12.0) / 53.0) ** 2) * 50.0 - 50.0
    neck = _smax(neck, NECK_BOTTOM_Y - p[1], 5.0)
    return _smax(neck, p[1] - 40.0, 5.0)


def _ell(c, r):
    """Ellipsoid feature: (function, bounding box)."""
    c, r = np.asarray(c, float), np.asarray(r, float)
    return (lambda p: ellipsoid(p, c, r)), (c - r, c + r)


def _cap(a, b, ra, rb):
    """Tapered capsule feature: (function, bounding box)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    rm = max(ra, rb)
    return (lambda p: _capsule(p, a, b, ra, rb)), (np.minimum(a, b) - rm, np.maximum(a, b) + rm)


_UNION, _CARVE = "union", "carve"
# The skin as an ordered list of (operation, mirrored, blend k mm, feature); "mirrored" features
# are modelled on the x >= 0 side and apply to both.  The order matters (smooth CSG).
_FEATURES = (
    # face mass, neck with Adam's apple, maxilla/mouth mass (the cranium is the starting value)
    (_UNION, False, 24.0, _ell([0, -32, 20], [63, 68, 73])),
    (_UNION, False, 22.0, (_neck, (np.array([-56.0, NECK_BOTTOM_Y - 6, -70]), np.array([56.0, 46.0, 50.0])))),
    (_UNION, False, 6.0, _ell([0, -128, 34], [9, 12, 8])),
    (_UNION, False, 18.0, _ell([0, -64, 52], [36, 30, 36])),
    # cheeks, cheekbones, jaw line (mandible from gonion to the mental tubercle), chin
    (_UNION, True, 15.0, _ell([35, -42, 60], [20, 20, 22])),
    (_UNION, True, 12.0, _ell([45, -10, 64], [16, 10, 14])),
    (_UNION, True, 14.0, _cap([50, -76, 0], [16, -104, 72], 8.0, 8.0)),
    (_UNION, False, 8.0, _ell([0, -101, 76], [19, 12, 13])),
    # brow ridge and glabella
    (_UNION, True, 7.0, _ell([28, 15, 80], [24, 8, 12])),
    (_UNION, False, 7.0, _ell([0, 12, 83], [12, 8, 10])),
    # eye sockets, then lids wrapped over the eyeballs
    (_CARVE, True, 8.0, _ell([30, 2, 93], [16, 11.5, 12])),
    (_UNION, True, 7.0, _ell(EYE_CENTRES[0], [LID_RADIUS] * 3)),
    # nose: dorsum, body, tip, alae (one smooth union); nostrils as shallow pits underneath
    (_UNION, False, 5.0, _cap([0, 6, 86], [0, -37, 106], 4.5, 6.5)),
    (_UNION, False, 6.0, _ell([0, -36, 93], [13, 17, 13])),
    (_UNION, False, 4.0, _ell([0, -40, 104], [9.5, 8.0, 8.5])),
    (_UNION, True, 6.0, _ell([12.5, -47, 91], [6, 5.5, 7])),
    (_CARVE, True, 1.5, _ell([7, -53.5, 98], [4, 3, 6.5])),
    # lips, the mouth line between them, philtrum, mentolabial sulcus
    (_UNION, False, 6.0, _ell([0, -67, 84], [23, 5.5, 7.5])),
    (_UNION, False, 6.0, _ell([0, -80, 82.5], [20, 6.5, 7.5])),
    (_CARVE, False, 1.0, _ell([0, -73.5, 91], [25, 0.9, 9])),
    (_CARVE, False, 1.5, _ell([0, -60, 91.5], [2.5, 4, 1.5])),
    (_CARVE, False, 3.0, _ell([0, -90, 88], [18, 3, 4])),
    # ears
    (_UNION, True, 3.0, (_ear, (np.array([45.0, -45.0, -35.0]), np.array([95.0, 21.0, 7.0])))),
)
_CRANIUM = (np.array([0.0, 28.0, -10.0]), np.array([74.0, 92.0, 100.0]))
# How far outside its bounding box a feature must be evaluated (see _skin_field): its own blend
# width plus the widest blend applied after it, plus 4 mm for the inexact ellipsoid distance.
_GROW = tuple(k + max([0.0] + [f[2] for f in _FEATURES[i + 1:]]) + 4.0
              for i, (_op, _m, k, _f) in enumerate(_FEATURES))


def _feature_subsets(a, b):
    """Per feature, the indices of rays whose segment a-b ((x, y, z) arrays) may meet its grown box."""
    lo_p = [np.minimum(a[i], b[i]) for i in range(3)]
    hi_p = [np.maximum(a[i], b[i]) for i in range(3)]
    ax, bx = np.abs(a[0]), np.abs(b[0])
    lo_q = [np.where((a[0] < 0) != (b[0] < 0), 0.0, np.minimum(ax, bx)), lo_p[1], lo_p[2]]
    hi_q = [np.maximum(ax, bx), hi_p[1], hi_p[2]]
    subsets = []
    for (_op, mirrored, _k, (_fn, (lo, hi))), grow in zip(_FEATURES, _GROW):
        s_lo, s_hi = (lo_q, hi_q) if mirrored else (lo_p, hi_p)
        sel = (s_hi[0] > lo[0] - grow) & (s_lo[0] < hi[0] + grow)
        for i in (1, 2):
            sel &= (s_hi[i] > lo[i] - grow) & (s_lo[i] < hi[i] + grow)
        subsets.append(np.flatnonzero(sel))
    return subsets


def _skin_field(p, subsets=None):
    """Implicit skin field F(p), p = (x, y, z) arrays, mm in the design frame; F < 0 inside.

    Each feature is evaluated only inside its bounding box grown by ``_GROW`` (or on given
    precomputed ``subsets`` that contain those points).  Outside it the feature's distance g
    exceeds its blend k by the widest later blend K, so the smooth union/carve can only differ
    from the identity where the running F > K; no later operation can bring such a point to the
    surface, so the zero set (the skin) is exact while the cost drops several-fold.
    """
    if subsets is None:
        subsets = _feature_subsets(p, p)
    q = _mirror(p)
    f = ellipsoid(p, *_CRANIUM)
    for (op, mirrored, k, (fn, _box)), idx in zip(_FEATURES, subsets):
        if idx.size == 0:
            continue
        pts = q if mirrored else p
        g = fn((pts[0][idx], pts[1][idx], pts[2][idx]))
        f[idx] = _smin(f[idx], g, k) if op == _UNION else _smax(f[idx], -g, k)
    return f


def ray_points(d, r):
    """Points CENTRE + r d as an (x, y, z) tuple; d = (dx, dy, dz) arrays."""
    return (CENTRE[0] + r * d[0], CENTRE[1] + r * d[1], CENTRE[2] + r * d[2])


# ----------------------------------------------------------------------------------------------
# ray solve on (theta, phi) grids
# ----------------------------------------------------------------------------------------------
def _directions(theta, phi):
    """Unit directions as flat (dx, dy, dz) over the (theta, phi) grid, C order: theta from +Y, phi = 0 towards +Z, +pi/2 to +X."""
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    sp, cp = np.sin(phi)[None, :], np.cos(phi)[None, :]
    return tuple(np.ascontiguousarray(c).ravel() for c in np.broadcast_arrays(st * sp, ct, st * cp))




def _solve_radius(d, lo, hi, iterations, subsets=None, f_lo=None, f_hi=None):
    """Skin radius along unit directions d = (dx, dy, dz) from CENTRE, bracketed in [lo, hi] mm.

    Illinois regula falsi (Dowell & Jarratt 1971): keeps the bracket like bisection but
    converges superlinearly on the nearly-linear F along a ray, so a fixed, small number of
    field evaluations gives sub-micron radii.  Returns (r, residual |F| in mm).
    """
    if subsets is None:
        subsets = _feature_subsets(ray_points(d, lo), ray_points(d, hi))
    if f_lo is None:
        f_lo = _skin_field(ray_points(d, lo), subsets)
        f_hi = _skin_field(ray_points(d, hi), subsets)
    side = np.zeros(len(lo), np.int8)
    r, f_r = lo, f_lo
    for _ in range(iterations):
        r = lo + (hi - lo) * np.clip(f_lo / np.minimum(f_lo - f_hi, -1e-12), 0.0, 1.0)
        f_r = _skin_field(ray_points(d, r), subsets)
        inside = f_r < 0.0
        # Illinois: when the same end is replaced twice running, halve the other end's value
        f_hi = np.where(inside & (side == 1), 0.5 * f_hi, f_hi)
        f_lo = np.where(~inside & (side == -1), 0.5 * f_lo, f_lo)
        lo, f_lo = np.where(inside, r, lo), np.where(inside, f_r, f_lo)
        hi, f_hi = np.where(inside, hi, r), np.where(inside, f_hi, f_r)
        side = np.where(inside, 1, -1).astype(np.int8)
    # Rays where F is strongly curved (creases, carve rims) converge slowly: finish them by
    # bisection of their still-valid bracket, then one secant step.
    slow = np.flatnonzero(np.abs(f_r) > RESIDUAL_TOL_MM)
    if slow.size:
        ds = tuple(c[slow] for c in d)
        a, b = lo[slow], hi[slow]
        for _ in range(BISECT_FINISH):
            mid = 0.5 * (a + b)
            inside = _skin_field(ray_points(ds, mid)) < 0.0
            a, b = np.where(inside, mid, a), np.where(inside, b, mid)
        fa, fb = _skin_field(ray_points(ds, a)), _skin_field(ray_points(ds, b))
        r = r.copy()
        r[slow] = a + (b - a) * np.clip(fa / np.minimum(fa - fb, -1e-12), 0.0, 1.0)
        f_r = f_r.copy()
        f_r[slow] = _skin_field(ray_points(ds, r[slow]))
    return r, np.abs(f_r)


def bisect_radius(d, iterations=18):
    """Bracket (lo, hi) of the skin radius along d = (dx, dy, dz) by bisection of [R_IN, R_OUT]."""
    lo = np.full(len(d[0]), R_IN)
    hi = np.full(len(d[0]), R_OUT)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        inside = _skin_field(ray_points(d, mid)) < 0.0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return lo, hi


# ----------------------------------------------------------------------------------------------
# the skin grid
# ----------------------------------------------------------------------------------------------
PILOT_RINGS, PILOT_COLUMNS = 121, 240   # ~1.5 deg pilot: resolves every feature to ~3 mm
BRACKET_MM = 6.0                        # fine-grid bracket half-width around the pilot guess
ILLINOIS_STEPS = 6                      # leaves ~0.1% of rays above RESIDUAL_TOL_MM (measured)
RESIDUAL_TOL_MM = 1e-4                  # 0.1 um: far below the 20 um pore depth
BISECT_FINISH = 24                      # 12 mm bracket / 2^24 < 1e-6 mm


def pilot_solve():
    """Coarse uniform-angle solve: (theta (K,), radii (K, J)) for spacing and initial guesses."""
    theta = np.linspace(0.0, np.pi, PILOT_RINGS)
    phi = -np.pi + 2.0 * np.pi * np.arange(PILOT_COLUMNS) / PILOT_COLUMNS
    d = _directions(theta, phi)
    lo, hi = bisect_radius(d, iterations=16)
    r, _ = _solve_radius(d, lo, hi, 4)
    return theta, phi, r.reshape(PILOT_RINGS, PILOT_COLUMNS)


def ring_schedule(theta, phi, r_pilot):
    """Arc-length parametrisation of the meridians and the width/height aspect of the surface.

    Returns (S (K,) cumulative mean meridian length mm, aspect = mean ring perimeter / S[-1]).
    """
    p = np.stack(ray_points(_directions(theta, phi), r_pilot.ravel()), -1).reshape(*r_pilot.shape, 3)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=-1).mean(axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    perim = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=-1).sum(axis=1)
    mid_perim = 0.5 * (perim[1:] + perim[:-1])
    aspect = float((mid_perim * seg).sum() / seg.sum() / s[-1])
    return s, aspect


def grid_size(skin_triangles, aspect):
    """Rings n_t and (even) columns n_p with 2 n_t n_p ~ skin_triangles and n_p / n_t ~ aspect.

    n_p is even so that the midline (phi = 0 and pi) is a column and the mesh is mirror-symmetric;
    n_t is picked within +-15% of the ideal ring count to hit the budget most closely.
    """
    ideal = math.sqrt(skin_triangles / (2.0 * aspect))
    best = None
    for n_t in range(max(8, int(0.85 * ideal)), max(9, int(1.15 * ideal) + 1)):
        n_p = max(8, 2 * int(round(skin_triangles / (4.0 * n_t))))
        err = (abs(2 * n_t * n_p - skin_triangles), abs(n_t - ideal))
        if best is None or err < best[0]:
            best = (err, n_t, n_p)
    return best[1], best[2]


def grid_faces(n_t, n_p):
    """Faces (2 n_t n_p, 3) of the ring grid; vertex 0 = top pole, 1 + i n_p + j = ring i, column j,
    last = bottom pole.  Counter-clockwise seen from outside (theta x phi points outward)."""
    ring = 1 + np.arange(n_t)[:, None] * n_p
    j = np.arange(n_p)[None, :]
    jn = (j + 1) % n_p
    a, b = ring[:-1] + j, ring[1:] + j            # (i, j), (i+1, j)
    c, d = ring[1:] + jn, ring[:-1] + jn          # (i+1, j+1), (i, j+1)
    quads = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    bottom = 1 + n_t * n_p
    top_fan = np.stack(np.broadcast_arrays(0, 1 + j[0], 1 + jn[0]), -1)
    last = 1 + (n_t - 1) * n_p
    bot_fan = np.stack(np.broadcast_arrays(last + j[0], bottom, last + jn[0]), -1)
    return np.concatenate([top_fan, quads, bot_fan]).astype(np.int32)


def grid_uv(t, n_p):
    """Per-corner UVs of the ring grid: columns duplicated at the seam (phi = -pi, back of the head).

    Returns (uv (T, 2) float32, uv_faces (F, 3) int32) matching :func:`grid_faces`.  The poles
    get one UV per fan triangle so the atlas shows no triangle spanning the whole width.
    """
    n_t = len(t)
    u = np.arange(n_p + 1) / n_p
    v = V_SKIN * (1.0 - t)
    uv_grid = np.stack(np.broadcast_arrays(u[None, :], v[:, None]), -1).reshape(-1, 2)
    top = np.stack([(np.arange(n_p) + 0.5) / n_p, np.full(n_p, V_SKIN)], -1)
    bot = np.stack([(np.arange(n_p) + 0.5) / n_p, np.zeros(n_p)], -1)
    uv = np.concatenate([uv_grid, top, bot]).astype(np.float32)
    ring = np.arange(n_t)[:, None] * (n_p + 1)
    j = np.arange(n_p)[None, :]
    a, b = ring[:-1] + j, ring[1:] + j
    c, d = ring[1:] + j + 1, ring[:-1] + j + 1
    quads = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    n_grid = n_t * (n_p + 1)
    jj = np.arange(n_p)
    top_fan = np.stack([n_grid + jj, jj, jj + 1], -1)
    last = (n_t - 1) * (n_p + 1)
    bot_fan = np.stack([last + jj, n_grid + n_p + jj, last + jj + 1], -1)
    return uv, np.concatenate([top_fan, quads, bot_fan]).astype(np.int32)


def solve_grid(theta, phi, pilot):
    """Skin radii (n_t * n_p,) on the fine grid, started from the pilot and verified per ray.

    Returns (r, d, rays re-bracketed from scratch, max residual |F| mm).
    """
    th_p, ph_p, r_p = pilot
    d = _directions(theta, phi)
    # linear interpolation of the pilot radii (wrapping in phi) as the initial guess
    ri = np.interp(theta, th_p, np.arange(len(th_p)))
    rj = (phi - ph_p[0]) / (ph_p[1] - ph_p[0])
    r_wrap = np.concatenate([r_p, r_p[:, :1]], axis=1)
    ii, jj = np.meshgrid(ri, rj, indexing="ij")
    guess = ndimage.map_coordinates(r_wrap, [ii.ravel(), jj.ravel()], order=1, mode="nearest")
    lo, hi = guess - BRACKET_MM, guess + BRACKET_MM
    subsets = _feature_subsets(ray_points(d, lo), ray_points(d, hi))
    f_lo = _skin_field(ray_points(d, lo), subsets)
    f_hi = _skin_field(ray_points(d, hi), subsets)
    bad = (f_lo >= 0.0) | (f_hi <= 0.0)
    n_bad = int(bad.sum())
    if n_bad:   # rays where the pilot missed a feature edge: bracket them from scratch
        idx = np.flatnonzero(bad)
        lo[idx], hi[idx] = bisect_radius(tuple(c[idx] for c in d), iterations=14)
        subsets = _feature_subsets(ray_points(d, lo), ray_points(d, hi))
        f_lo = _skin_field(ray_points(d, lo), subsets)
        f_hi = _skin_field(ray_points(d, hi), subsets)
    r, residual = _solve_radius(d, lo, hi, ILLINOIS_STEPS, subsets, f_lo, f_hi)
    return r, d, n_bad, float(residual.max())


# ----------------------------------------------------------------------------------------------
# eyes: aperture in the lids, eyeball meshes
# ----------------------------------------------------------------------------------------------
EYE_HALF_WIDTH = 12.5      # palpebral fissure ~28-30 mm wide (Farkas 1994), measured on the eyeball
UPPER_LID_MM, LOWER_LID_MM = 5.2, 3.6   # fissure height ~9-10 mm
CANTHAL_TILT_MM = 1.2      # lateral canthus sits a little higher than the medial one
LID_TUCK_MM = 1.0          # inside the fissure the skin is pulled this far behind the eyeball
LID_MARGIN_MM = 1.0        # width of the soft edge of the fissure (lid margin)


def smoothstep(e0, e1, x):
    """Hermite smoothstep from 0 at e0 to 1 at e1."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def eye_aperture(d, r):
    """Pull the skin behind each eyeball inside the almond-shaped fissure; returns new radii.

    Done per ray rather than in the implicit field so that the lid margin follows the rays from
    C (a fissure carved along z would hide parts of its own wall from C and break star-shape).
    """
    r = r.copy()
    for e in EYE_CENTRES:
        oc = CENTRE - e
        b = d[0] * oc[0] + d[1] * oc[1] + d[2] * oc[2]
        disc = b * b - (oc @ oc - EYE_RADIUS ** 2)
        hit = np.flatnonzero((disc > 0.0) & (b < 0.0))   # the line meets the eye in front of C
        t_front = -b[hit] + np.sqrt(disc[hit])      # C is behind the eye: the exit is its front
        lx = (CENTRE[0] + t_front * d[0][hit] - e[0]) * np.sign(e[0])   # + = lateral
        ly = CENTRE[1] + t_front * d[1][hit] - e[1]
        w = np.clip(1.0 - (lx / EYE_HALF_WIDTH) ** 2, 0.0, None)
        centre_line = CANTHAL_TILT_MM * lx / EYE_HALF_WIDTH
        upper = centre_line + UPPER_LID_MM * w ** 0.7 * (1.0 - 0.12 * lx / EYE_HALF_WIDTH)
        lower = centre_line - LOWER_LID_MM * w ** 0.85
        m = smoothstep(0.0, LID_MARGIN_MM, np.minimum(upper - ly, ly - lower))
        rh = r[hit]
        r[hit] = rh - m * np.maximum(0.0, rh - (t_front - LID_TUCK_MM))
    return r


def icosphere(level):
    """Unit icosphere: (vertices (V, 3), faces (20 * 4**level, 3)) counter-clockwise outward."""
    g = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], float)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(level):
        edges = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(-1, 3) + len(v)
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
        v = np.concatenate([v, mid])
    return v, f
