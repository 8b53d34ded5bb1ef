"""Ray casting through Embree (open3d ``RaycastingScene``): primary hits and shadow rays.

One :class:`Visibility` is built per mesh and answers these questions, batched:

* :meth:`Visibility.intersect` - the first hit of each ray: triangle id, barycentrics
  ``(b1, b2)`` (point = (1 - b1 - b2) p0 + b1 p1 + b2 p2, Embree's convention) and the hit
  distance;
* :meth:`Visibility.occluded` - whether anything lies between a surface point and a light
  sample at a given distance (Embree's any-hit occlusion query, cheaper than a closest hit);
* :meth:`Visibility.closest` - the closest surface point to each query point (triangle id
  and barycentrics, as a hit).

:func:`interpolate` reads per-vertex values at hits in Embree's barycentric convention.

Why Embree through open3d: docs/software.md "Where the work runs" (a well-kept BVH, ~2M
rays/s per core measured here; no home-made BVH).

Self-intersection ("shadow acne"): shadow-ray origins are pushed off the surface along the
geometric normal, on the side the ray leaves, by :attr:`Visibility.offset_mm` =
``OFFSET_FRACTION`` x the bounding-box diagonal, and rays stop ``OFFSET_FRACTION`` x diagonal
short of the light sample.  Hit points are reconstructed in float32 from barycentrics, so
their error is a few ulps of the coordinates (~1e-5 mm for a 300 mm head); 1e-5 x diagonal
(~4e-3 mm for a head) is ~100x that and still 10x below the pore scale of a 1M-triangle scan
(edges ~0.3 mm).  Guarded by tests/test_render.py (analytic sphere: no acne) and
tests/test_lights.py (penumbra trend).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dermis.pipeline.errors import DermisError
from dermis.pipeline.reuse import content_key
from dermis.pipeline.shared import RunCache, Shared

__all__ = ["Visibility", "Hits", "interpolate", "OFFSET_FRACTION", "MISS", "EMBREE_SCENES", "embree_scene"]

# Shadow-ray origin offset and end shortening, as a fraction of the bounding-box diagonal
# (derivation in the module docstring).
OFFSET_FRACTION = 1e-5
# Triangle id of a ray that hit nothing.
MISS = -1


@dataclass
class Hits:
    """First hits of a batch of rays.

    tri : (N,) int32 triangle index, ``MISS`` (-1) where the ray hit nothing
    bary : (N, 2) float32 barycentrics (b1, b2) of corners 1 and 2 (0 on a miss)
    t : (N,) float32 hit distance in units of the ray direction's length (inf on a miss)
    """

    tri: np.ndarray
    bary: np.ndarray
    t: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0


class Visibility:
    """Embree scene of one triangle mesh (built once, queried many times).

    Parameters
    ----------
    vertices : (V, 3) float, mm
    faces : (F, 3) int
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import open3d as o3d   # heavy (Embree, ~1 s to import): only where a scene is built

        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise DermisError(f"visibility: vertices have shape {v.shape}; need (V, 3), V > 0")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise DermisError(f"visibility: faces have shape {f.shape}; need (F, 3), F > 0")
        if f.min() < 0 or f.max() >= len(v):
            raise DermisError(f"visibility: face indices span [{f.min()}, {f.max()}]; "
                              f"need [0, {len(v) - 1}]")
        if not np.all(np.isfinite(v)):
            raise DermisError("visibility: vertices contain NaN or Inf")
        self._o3c = o3d.core
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(
            np.ascontiguousarray(f, dtype=np.uint32)))
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.bbox = (lo.astype(np.float64), hi.astype(np.float64))
        #: bounding-box diagonal, mm
        self.diagonal_mm = float(max(np.linalg.norm(hi.astype(np.float64) - lo), 1e-6))
        #: shadow-ray origin offset and end shortening, mm (module docstring)
        self.offset_mm = OFFSET_FRACTION * self.diagonal_mm
        #: rays counted since construction (for rays/s reports)
        self.rays_cast = 0
        # open3d builds the BVH lazily on the first query: force it here, so that building
        # is paid (and timed) once, at construction
        self._scene.test_occlusions(o3d.core.Tensor(np.zeros((1, 6), dtype=np.float32)))

    # ------------------------------------------------------------------ queries
    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """Closest hit of each ray.

        Parameters
        ----------
        origins, directions : (N, 3) float, mm (directions need not be unit)

        Returns
        -------
        Hits
        """
        rays = _rays(origins, directions)
        out = self._scene.cast_rays(self._o3c.Tensor(rays))
        self.rays_cast += len(rays)
        t = out["t_hit"].numpy().astype(np.float32, copy=False)
        prim = out["primitive_ids"].numpy()
        ok = np.isfinite(t)
        tri = np.where(ok, prim, MISS).astype(np.int32)
        bary = np.where(ok[:, None], out["primitive_uvs"].numpy(), 0.0).astype(np.float32)
        return Hits(tri=tri, bary=bary, t=t)

    def occluded(self, points: np.ndarray, normals: np.ndarray, directions: np.ndarray,
                 max_distance: np.ndarray | float) -> np.ndarray:
        """Shadow rays: is the segment from each surface point towards the light blocked?

        Parameters
        ----------
        points : (N, 3) float, mm
            Surface points (not yet offset).
        normals : (N, 3) float
            Geometric normals at the points (either orientation); the origin is moved
            ``offset_mm`` along the normal, on the side the ray leaves.
        directions : (N, 3) float
            Unit directions towards the light.
        max_distance : (N,) float or float, mm
            Distance to the light sample; ``inf`` for lights at infinity.

        Returns
        -------
        (N,) bool, True where something blocks the ray before ``max_distance``.
        """
        p = np.asarray(points, dtype=np.float32)
        n = np.asarray(normals, dtype=np.float32)
        d = np.asarray(directions, dtype=np.float32)
        if len(p) == 0:
            return np.zeros(0, dtype=bool)
        side = np.where(np.einsum("ij,ij->i", n, d) < 0, -1.0, 1.0).astype(np.float32)
        # Embree's tfar is in units of the direction's length and a scalar per call, so the
        # per-ray end goes into the direction's length: d * (distance - offset), tfar = 1.
        # Lights at infinity end at a distance that clears the whole scene from any origin
        # inside its bounding box (2 diagonals).
        dist = np.broadcast_to(np.asarray(max_distance, dtype=np.float32), p.shape[:1])
        dist = np.minimum(dist, np.float32(2.0 * self.diagonal_mm)) - np.float32(self.offset_mm)
        dist = np.maximum(dist, np.float32(0.0))
        # the rays [origin, direction x length] written in place (no temporaries): the same
        # float32 operations as p + offset side n and d dist
        rays = _ray_buffer(p, d)
        np.multiply(n, (self.offset_mm * side)[:, None], out=rays[:, :3])
        rays[:, :3] += p
        np.multiply(d, dist[:, None], out=rays[:, 3:])
        self.rays_cast += len(rays)
        return self._scene.test_occlusions(self._o3c.Tensor(rays), tnear=0.0,
                                           tfar=1.0).numpy().astype(bool, copy=False)

    def closest(self, points: np.ndarray) -> Hits:
        """The closest surface point to each of ``points`` (N, 3) mm: its triangle,
        barycentrics (Embree's convention, as :meth:`intersect`) and distance ``t`` (mm)."""
        p = np.ascontiguousarray(points, dtype=np.float32)
        out = self._scene.compute_closest_points(self._o3c.Tensor(p))
        tri = out["primitive_ids"].numpy().astype(np.int32)
        bary = out["primitive_uvs"].numpy().astype(np.float32)
        t = np.linalg.norm(out["points"].numpy() - p, axis=1).astype(np.float32)
        return Hits(tri=tri, bary=bary, t=t)

    def occlusion_fn(self):
        """``occluded`` with the signature expected by :func:`lighting.irradiance.irradiance`."""
        return self.occluded


def interpolate(values: np.ndarray, faces: np.ndarray, tri: np.ndarray,
                bary: np.ndarray) -> np.ndarray:
    """(M, C) float32 per-vertex ``values`` (V, C) at hits on triangles ``tri`` (M,) with
    barycentrics ``bary`` (M, 2) in Embree's convention: (1 - b1 - b2) v0 + b1 v1 + b2 v2."""
    f = np.asarray(faces)[np.asarray(tri)]
    b = np.asarray(bary, np.float32)
    vals = np.asarray(values, np.float32)
    out = vals[f[:, 0]] * (1.0 - b[:, 0] - b[:, 1])[:, None]
    out += vals[f[:, 1]] * b[:, 0:1]
    out += vals[f[:, 2]] * b[:, 1:2]
    return out


def _ray_buffer(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """An empty (N, 6) float32 ray array for (N, 3) origins and directions (checked)."""
    if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[1] != 3:
        raise DermisError(f"visibility: origins {origins.shape} and directions "
                          f"{directions.shape} must both be (N, 3)")
    return np.empty((len(origins), 6), dtype=np.float32)


def _rays(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, 6) float32 rays [ox, oy, oz, dx, dy, dz], contiguous, as open3d wants them."""
    o = np.asarray(origins, dtype=np.float32)
    d = np.asarray(directions, dtype=np.float32)
    rays = _ray_buffer(o, d)
    rays[:, :3] = o
    rays[:, 3:] = d
    return rays


# The Embree scene of a mesh, shared by every node of a run that traces that mesh (building
# it takes ~1 s for the 1.13M-triangle scan).  Two: the high and the low mesh of a scene.
EMBREE_SCENES = Shared("embree_scene", keep=2)


def embree_scene(mesh, shared: RunCache | None = None, key: str | None = None) -> "Visibility":
    """The Embree scene of ``mesh``, made once per run for every node that traces it.

    ``shared`` : the run's shared intermediates (``ctx.shared``); None builds a scene here.
    ``key`` : the mesh's content key (the cache key of the node that made it,
    ``ctx.input_keys``); by default a digest of its vertices and faces."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if shared is None:
        return Visibility(v, f)
    return shared.get(EMBREE_SCENES, key or content_key(v, f), lambda: Visibility(v, f))
