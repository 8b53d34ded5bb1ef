"""Tracing the reference at chosen pixels, in this process or on a worker.

:func:`trace_pixels` traces paths at a list of pixels of an exported head
(:mod:`dermis.groundtruth.scene_export`): each path starts at a uniform point of its pixel (a
box filter, as ``mi.render`` with the export's ``box`` filter), takes the sensor's ray and is
traced by the scene's integrator (``volpathmis``).  Called on the pixels the head covers
only, it spends no path on the background (:mod:`dermis.groundtruth.progressive`).

:class:`TraceJob` is everything a process needs to build the scene itself (mesh, layer stack,
camera, lights, export options, Mitsuba variant); :func:`trace_tile` traces one task of a
pass with it, so the same function runs in the planning process and on Dask workers
(``pipeline/taskpool.py``), with the same bytes: a tile's result depends on its pixels,
samples and seeds alone.

Loading the exported head is most of a reference's cost beyond its paths (the PLY export and
Mitsuba's scene build of the ~1.1 M-triangle scan and its offset layer: ~11 CPU seconds,
bench/results/reference_cost.json), and the camera is no part of it: a path's radiance does
not depend on the sensor that started it.  So a process keeps the :data:`KEEP_SCENES` most
recently used scenes by content (``TraceJob.scene_key``: mesh, stack, export options,
lights, variant) and traces through each job's own sensor: the close-ups lit by a lighting
condition of the main camera (``point@nose_shadow``, ``area@lips``) reuse its scene.
"""
from __future__ import annotations

import hashlib
import json
import threading
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from dermis.groundtruth import mitsuba
from dermis.groundtruth.passes import MAX_LANES
from dermis.groundtruth.scene_export import HeadSceneOptions, camera_dict, head_scene, release

__all__ = ["trace_pixels", "call_lanes", "MIN_CALL_LANES", "sensor_mean", "TraceJob", "trace_tile", "job_scene", "job_sensor",
           "forget", "KEEP_SCENES"]

# Scenes a process keeps (each ~0.3 GB for the default scan: two 1.1 M-triangle surfaces and
# their acceleration structure): the reference nodes run the close-ups right after the main
# camera's condition of the same lights (stages/reference.py), so two suffice.
KEEP_SCENES = 2


def _sampler(mi, seed: int, lanes: int):
    """An independent sampler of ``lanes`` lanes seeded with ``seed`` (mod 2^32).

    The seed is an opaque Dr.Jit value, not a literal: a literal seed is compiled into the
    path tracer's kernel, so every call with a new seed (every task of every pass) built the
    whole ``volpathmis`` kernel again, ~2 s of LLVM compilation a call against ~0.2 s of
    tracing 16k paths of a small scene (measured: same bytes either way).  The default
    scene's point-light reference on an empty kernel cache built 28 kernels instead of 51,
    and its run to the reference took 244 CPU s instead of 253 (its paths dominate)."""
    import drjit as dr
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, int(seed) % (1 << 32)), int(lanes))
    return sampler


def _lanes(spectrum, n: int) -> np.ndarray:
    """(n, 3) float64 of a Dr.Jit RGB array of ``n`` lanes (numpy reads it channel-major)."""
    v = np.asarray(spectrum, np.float64)
    return (v.T if v.ndim == 2 and v.shape == (3, n) else v).reshape(n, 3)


# The LLVM kernel is also built anew for every wavefront size (measured: 8,192 and 8,000
# lanes each compile, ~2 s), so a call's lanes are rounded up to a ladder of a few sizes:
# MIN_CALL_LANES, then four steps an octave (x 1, 1.25, 1.5, 1.75), at most 25 % of the
# lanes traced and thrown away, against a compilation per distinct size.
MIN_CALL_LANES = 4096


def call_lanes(n: int) -> int:
    """The ladder's size for a call of ``n`` paths (at most :data:`MAX_LANES`)."""
    q = max(int(n), MIN_CALL_LANES)
    if q >= MAX_LANES:
        return MAX_LANES
    step = 1 << (q.bit_length() - 3)          # a quarter of the octave q lies in
    return min(-(-q // step) * step, MAX_LANES)


def trace_pixels(mi, scene, pixels: np.ndarray, spp: int, seed: int, *, width: int,
                 height: int, sensor=None) -> np.ndarray:
    """(M, 3) float64 sums of ``spp`` paths at each of ``pixels`` ((M, 2) x, y).

    Each path starts at a uniform point of its pixel (a box filter, as ``mi.render``) through
    ``sensor`` (None: the scene's first) and is traced by the scene's integrator.  The M x spp
    paths go in calls of :func:`call_lanes` lanes, call k seeded ``seed + k`` (mod 2^32); the
    last call's spare lanes repeat its first pixels and are discarded.
    """
    sensor = scene.sensors()[0] if sensor is None else sensor
    integrator = scene.integrator()
    px = np.asarray(pixels, np.int64).reshape(-1, 2)
    out = np.zeros((len(px), 3))
    owner = np.repeat(np.arange(len(px)), int(spp))
    if len(owner) == 0:
        return out
    lanes = call_lanes(len(owner))
    for k, lo in enumerate(range(0, len(owner), lanes)):
        idx = owner[lo:lo + lanes]
        n = len(idx)
        full = np.resize(idx, call_lanes(n))
        sampler = _sampler(mi, seed + k, len(full))
        x = mi.Float(px[full, 0].astype(np.float32))
        y = mi.Float(px[full, 1].astype(np.float32))
        u = sampler.next_2d()
        pos = mi.Point2f((x + u.x) / float(width), (y + u.y) / float(height))
        ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), pos, sampler.next_2d())
        spec, _, _ = integrator.sample(scene, sampler, ray, None, True)
        vals = _lanes(spec * weight, len(full))[:n]
        for c in range(3):          # np.add.at is ~10x slower on millions of lanes
            out[:, c] += np.bincount(idx, weights=vals[:, c], minlength=len(px))
    return out


def sensor_mean(mi, scene, samples: int, seed: int, sensor=None) -> np.ndarray:
    """(3,) float64 mean of ``samples`` paths of ``sensor`` (default: the scene's first) over
    its whole film (one pixel: a radiance or irradiance meter), summed here in a fixed order:
    ``mi.render`` adds a one-pixel film's samples with atomics, whose order (so the last
    bits) varies run to run."""
    sensor = scene.sensors()[0] if sensor is None else sensor
    integrator = scene.integrator()
    total, done, k = np.zeros(3), 0, 0
    while done < samples:
        n = min(int(samples) - done, MAX_LANES)
        sampler = _sampler(mi, seed + k, n)
        ray, weight = sensor.sample_ray_differential(0.0, sampler.next_1d(),
                                                     sampler.next_2d(), sampler.next_2d())
        spec, _, _ = integrator.sample(scene, sampler, mi.Ray3f(ray), None, True)
        total += _lanes(spec * weight, n).sum(axis=0)
        done, k = done + n, k + 1
    return total / max(int(samples), 1)


@dataclass(frozen=True)
class TraceJob:
    """The reference scene of one lighting condition, as data a worker can build it from.

    token : names the job (its sensor); mesh : the high mesh (``Mesh`` artifact); stack :
    ``LayerStack``; camera : CameraConfig; lights : list of LightConfig; width, height :
    reference pixels; options : the export's ``HeadSceneOptions``; variant : the Mitsuba
    variant the planning process chose; mesh_key : the mesh's content (its cache key), which
    with the rest of :attr:`scene_key` names the loaded scene a process may reuse
    """

    token: str
    mesh: Any
    stack: Any
    camera: Any
    lights: list
    width: int
    height: int
    options: HeadSceneOptions
    variant: str
    mesh_key: str = ""

    @property
    def scene_key(self) -> str:
        """The loaded scene's content: the same for every camera (empty mesh key: this job's
        own scene)."""
        if not self.mesh_key:
            return self.token
        opts = {k: (None if v is None else np.asarray(v).tolist()) if k == "tint_rd" else v
                for k, v in asdict(self.options).items()}
        blob = json.dumps([self.mesh_key, self.stack.to_dict(), opts,
                           [asdict(l) for l in self.lights], self.variant],
                          sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()


_SCENES: OrderedDict = OrderedDict()   # scene key -> (mitsuba module, HeadScene), per process
_SENSORS: dict = {}                    # job token -> its sensor, per process
_LOCK = threading.Lock()


def job_scene(job: TraceJob):
    """(mitsuba module, loaded HeadScene) of ``job`` in this process, built on first use (a
    scene of the same content loaded for an earlier job is reused)."""
    key = job.scene_key
    with _LOCK:
        if key in _SCENES:
            _SCENES.move_to_end(key)
        else:
            mi = mitsuba.load_mitsuba(job.variant)
            head = head_scene(mi, job.mesh, job.stack, job.camera, job.lights,
                              width=job.width, height=job.height, options=job.options)
            release(head)   # Mitsuba has read the PLY files
            _SCENES[key] = (mi, head)
            while len(_SCENES) > KEEP_SCENES:
                _SCENES.popitem(last=False)
        return _SCENES[key]


def job_sensor(job: TraceJob):
    """The Mitsuba sensor of ``job``'s camera at its size (made once per process and job)."""
    mi, _ = job_scene(job)
    with _LOCK:
        if job.token not in _SENSORS:
            _SENSORS[job.token] = mi.load_dict(camera_dict(mi, job.camera, width=job.width,
                                                           height=job.height))
        return _SENSORS[job.token]


def trace_tile(job: TraceJob, tile) -> tuple[np.ndarray, np.ndarray, float]:
    """Sums of half A and half B of one :class:`~dermis.groundtruth.progressive.Tile`, and
    the seconds they took (the scene built first if this process has not yet)."""
    mi, head = job_scene(job)
    sensor = job_sensor(job)
    t0 = time.perf_counter()
    a, b = (trace_pixels(mi, head.scene, tile.pixels, tile.spp, seed, width=job.width,
                         height=job.height, sensor=sensor) for seed in tile.seeds)
    return a, b, time.perf_counter() - t0


def forget(token: str) -> None:
    """Release this process's sensor of the job ``token`` and its own scene (a scene named by
    content stays for the next job of the same content, :data:`KEEP_SCENES`)."""
    with _LOCK:
        _SENSORS.pop(token, None)
        _SCENES.pop(token, None)
