"""Per-texel geometry of the bake: the low surface under each texel, its rays, their hits.

For each covered texel (:func:`dermis.geometry.uv_raster.rasterise`): the point and unit
interpolated normal of the low triangle under it and the height of the low mesh's Phong-
tessellated surface there (:func:`texel_points`, from :class:`TriangleFrames`), the two rays
along +-normal (:func:`rays_both_ways`), the nearer facing hit on the high mesh
(:func:`nearest_hits`) and the high mesh's albedo texture at the hits (:class:`HighTexture`).
The per-texel arithmetic runs on (3, m) coordinate planes (see :class:`TriangleFrames`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dermis.geometry.texture_lookup import SRGB8_TO_LINEAR, bilinear_planes, channel_planes
from dermis.pipeline.artifacts import Mesh
from dermis.pipeline.errors import DermisError

__all__ = ["PHONG_ALPHA", "HighTexture", "TriangleFrames", "texel_points", "rays_both_ways",
           "nearest_hits"]

PHONG_ALPHA = 0.5   # shape factor of the Phong reference surface (see texel_points)
# Textures up to this many texels are decoded to linear float32 once (4096^2 -> 200 MB);
# larger ones are decoded per lookup through the 256-entry table.
_DECODE_ONCE_MAX_TEXELS = 4096 * 4096


@dataclass
class HighTexture:
    """The high mesh's albedo texture as (3, H * W) channel ``planes``, linear float32, or sRGB
    uint8 with ``lut``; ``face_uv`` (F, 6) holds per high face uv0, uv1 - uv0 and uv2 - uv0
    (one row gathered per hit instead of corner indices, then corners)."""

    planes: np.ndarray
    shape: tuple[int, int]
    lut: np.ndarray | None
    face_uv: np.ndarray

    @classmethod
    def of(cls, high: Mesh) -> "HighTexture | None":
        """The texture of ``high``, or None when it has no texture or no UVs."""
        if high.texture_srgb is None or high.uv is None:
            return None
        tex = np.asarray(high.texture_srgb)
        if tex.ndim == 2:
            tex = np.repeat(tex[..., None], 3, axis=2)
        if tex.dtype != np.uint8 or tex.ndim != 3 or tex.shape[2] < 3:
            raise DermisError(f"bake: high.texture_srgb has dtype {tex.dtype} shape {tex.shape}; "
                              "need (H, W, 3) uint8 sRGB")
        planes = channel_planes(tex[..., :3])
        lut = SRGB8_TO_LINEAR
        if tex.shape[0] * tex.shape[1] <= _DECODE_ONCE_MAX_TEXELS:
            planes, lut = SRGB8_TO_LINEAR[planes], None
        c = np.asarray(high.uv, dtype=np.float32)[np.asarray(high.uv_faces)]   # (F, 3, 2)
        face_uv = np.concatenate([c[:, 0], c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]], axis=1)
        return cls(planes, tex.shape[:2], lut, face_uv)

    def at_hits(self, ans, ray_idx: np.ndarray) -> np.ndarray:
        """Linear albedo at the hits of rays ``ray_idx``: the hit's barycentrics interpolate
        the high mesh's UVs, the texture is read bilinearly in linear RGB."""
        pid = ans["primitive_ids"].numpy().take(ray_idx)
        b = ans["primitive_uvs"].numpy().take(ray_idx, axis=0)
        f = self.face_uv.take(pid, axis=0)                                  # (k, 6)
        b1, b2 = b[:, 0], b[:, 1]
        u = f[:, 0] + b1 * f[:, 2] + b2 * f[:, 4]
        v = f[:, 1] + b1 * f[:, 3] + b2 * f[:, 5]
        del f, b
        return bilinear_planes(self.planes, *self.shape, u, v, self.lut)

    def mean_colour(self) -> np.ndarray:
        """Mean linear colour of a <= 256^2 subsample (albedo when no texel hit anything)."""
        h, w = self.shape
        sub = self.planes.reshape(3, h, w)[:, ::max(1, h // 256), ::max(1, w // 256)]
        sub = np.ascontiguousarray(sub.reshape(3, -1).T)        # (n, 3), as the image's rows
        return (sub if self.lut is None else self.lut[sub]).mean(0)


@dataclass
class TriangleFrames:
    """Per low triangle, float32 relative to corner 0 (mm-scale positions keep ~3e-5 mm in
    float32; the rays are float32 anyway), as (3, F) coordinate planes: position, edges,
    normals; (F, 3) face normals; and the barycentric gradients in texel space (4, F):
    lambda_1 = grad[0] dx + grad[1] dy, lambda_2 = grad[2] dx + grad[3] dy, (dx, dy) from x0, y0.

    Planes, so that every per-texel step of :func:`texel_points` runs on contiguous 1-D
    arrays: on the default scene's 1M-texel chunks that took it from 240 to ~110 ms against
    (m, 3) arrays times (m, 1) factors (numpy's inner loop then spans 3 values)."""

    p0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n0: np.ndarray
    dn1: np.ndarray
    dn2: np.ndarray
    face_normals: np.ndarray
    grad: np.ndarray
    x0: np.ndarray
    y0: np.ndarray

    @classmethod
    def of(cls, vertices, faces, normals, coef, uv, uv_faces, resolution: int) -> "TriangleFrames":
        corners_v = vertices[faces]
        corners_n = normals[faces]
        e1 = (corners_v[:, 1] - corners_v[:, 0]).astype(np.float32)
        e2 = (corners_v[:, 2] - corners_v[:, 0]).astype(np.float32)
        fn = np.cross(e1, e2)
        uvc = np.asarray(uv, dtype=np.float64)[uv_faces[:, 0]]
        plane = lambda a: np.ascontiguousarray(a.T, dtype=np.float32)  # noqa: E731
        return cls(p0=plane(corners_v[:, 0]), e1=plane(e1), e2=plane(e2),
                   n0=plane(corners_n[:, 0]),
                   dn1=plane(corners_n[:, 1] - corners_n[:, 0]),
                   dn2=plane(corners_n[:, 2] - corners_n[:, 0]),
                   face_normals=fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30),
                   grad=plane(coef[:, 1:, :2].reshape(-1, 4)),                    # (4, F)
                   x0=(uvc[:, 0] * (resolution - 1)).astype(np.float32),
                   y0=((1.0 - uvc[:, 1]) * (resolution - 1)).astype(np.float32))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per column dot product of (3, m) planes, bit for bit ``np.einsum("nd,nd->n")`` of the
    (m, 3) arrays: float32, summed in order from a +0 accumulator (so an all -0 sum is +0)."""
    d = a[0] * b[0]
    d += a[1] * b[1]
    d += a[2] * b[2]
    d += 0.0
    return d


def texel_points(tf: TriangleFrames, f_idx: np.ndarray, fl: np.ndarray, resolution: int,
                 reference: str):
    """Surface point ``p``, unit interpolated normal ``nrm`` (both (3, m) planes) and reference
    height ``h_ref`` (mm along ``nrm``; 0 for "flat") at each texel ``fl`` of triangle ``f_idx``."""
    f = f_idx.astype(np.intp)
    # Barycentrics relative to corner 0 in float32: (x - x0) stays small, so no
    # cancellation (an absolute affine form would lose ~1e-4 at 4096 texels).
    dx = (fl % resolution).astype(np.float32) - tf.x0.take(f)
    dy = (fl // resolution).astype(np.float32) - tf.y0.take(f)
    g = tf.grad.take(f, axis=1)                                      # (4, m)
    l1 = np.clip(g[0] * dx + g[1] * dy, 0.0, 1.0)
    l2 = np.clip(g[2] * dx + g[3] * dy, 0.0, 1.0)
    over = l1 + l2
    np.maximum(over, 1.0, out=over)          # clip back onto the triangle (edge texels)
    l1 /= over
    l2 /= over
    del g, dx, dy, over
    e1f, e2f = tf.e1.take(f, axis=1), tf.e2.take(f, axis=1)          # (3, m)
    d0 = l1 * e1f
    d0 += l2 * e2f                                                   # p - v0
    p = tf.p0.take(f, axis=1)
    p += d0
    n0f, dn1f, dn2f = tf.n0.take(f, axis=1), tf.dn1.take(f, axis=1), tf.dn2.take(f, axis=1)
    nrm = l1 * dn1f
    np.add(n0f, nrm, out=nrm)
    nrm += l2 * dn2f
    length = np.sqrt(_dot(nrm, nrm))
    bad = length < 1e-6         # opposite vertex normals cancel: use the face normal
    if bad.any():
        nrm[:, bad] = tf.face_normals[f_idx[bad]].T
        length[bad] = 1.0
    nrm /= length
    if reference != "phong":
        return p, nrm, np.zeros(len(length), np.float32)
    # Height of the Phong-tessellated surface (Boubekeur & Alexa 2008) above the flat
    # triangle, along nrm: alpha * sum_i l_i (projection of p on vertex i's tangent
    # plane - p).  The renderer's interpolated normals already bend with that smooth
    # surface, so the bump must hold only what lies beyond it, or every triangle's dip
    # below the curved surface shows as a facet pattern.  alpha = 1/2 (not their 3/4):
    # on a sphere the full projection sum is exactly twice the chord's dip to second
    # order, so 1/2 reproduces the sphere (tests/test_bake.py test04b).
    n1f, n2f = n0f + dn1f, n0f + dn2f
    del dn1f, dn2f
    h_ref = -PHONG_ALPHA * ((1.0 - l1 - l2) * _dot(d0, n0f) * _dot(n0f, nrm)
                            + l1 * _dot(d0 - e1f, n1f) * _dot(n1f, nrm)
                            + l2 * _dot(d0 - e2f, n2f) * _dot(n2f, nrm))
    return p, nrm, h_ref


def rays_both_ways(p: np.ndarray, nrm: np.ndarray, backoff: float) -> np.ndarray:
    """(2m, 6) float32 rays from (3, m) planes: m along +nrm, then m along -nrm, each starting
    ``backoff`` behind p."""
    m = p.shape[1]
    rays = np.empty((2 * m, 6), dtype=np.float32)
    off = np.float32(backoff) * nrm
    np.subtract(p, off, out=rays[:m, :3].T)
    rays[:m, 3:].T[...] = nrm
    np.add(p, off, out=rays[m:, :3].T)
    np.negative(nrm, out=rays[m:, 3:].T)
    return rays


def nearest_hits(ans, nrm: np.ndarray, backoff: float, max_distance: float):
    """Per texel the nearer of its two hits within reach on a high face facing like ``nrm``
    ((3, m) planes; a back-facing hit is the far side of a thin part, never the surface ``p``
    approximates).

    Returns (signed t: +t along +nrm, -t along -nrm; got; use_f: the +nrm ray won;
    number of in-reach hits rejected as back-facing).
    """
    m = nrm.shape[1]
    t_hit = ans["t_hit"].numpy() - np.float32(backoff)
    pn = ans["primitive_normals"].numpy()
    facing = np.concatenate([_dot(pn[:m].T, nrm), _dot(pn[m:].T, nrm)]) > 0
    del pn
    in_reach = np.isfinite(t_hit) & (t_hit <= max_distance)
    rejected = int(np.count_nonzero(in_reach & ~facing))
    ok = in_reach & facing
    tf = np.where(ok[:m], t_hit[:m], np.inf)
    tb = np.where(ok[m:], t_hit[m:], np.inf)
    use_f = tf <= tb
    got = np.isfinite(np.minimum(tf, tb))
    return np.where(use_f, tf, -tb), got, use_f, rejected
